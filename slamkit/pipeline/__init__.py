"""slamkit.pipeline."""
