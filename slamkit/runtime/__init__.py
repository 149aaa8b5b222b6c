"""slamkit.runtime."""
