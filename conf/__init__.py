"""Hydra configs of slamkit, shipped as the package ``slamkit.conf`` (found after any install)."""
