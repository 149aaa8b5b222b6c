"""slamkit.geometry."""
