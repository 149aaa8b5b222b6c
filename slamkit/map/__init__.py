"""slamkit.map."""
