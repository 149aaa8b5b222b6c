"""A minimal MapStore written against slamkit's MapStore protocol only (map=dict)."""
