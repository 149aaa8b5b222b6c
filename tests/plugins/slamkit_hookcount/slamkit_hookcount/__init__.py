"""Example third-party slamkit plugin on the lifecycle hooks (tests/integration/test_lifecycle_hooks.py)."""
