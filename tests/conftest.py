"""Shared pytest fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def shared_datasets_dir() -> Path | None:
    """../shared/datasets beside the checkout (or $SLAMKIT_SHARED_DATASETS), if present."""
    env = os.environ.get("SLAMKIT_SHARED_DATASETS")
    path = Path(env) if env else REPO_ROOT.parent / "shared" / "datasets"
    return path if path.is_dir() else None


@pytest.fixture(scope="session")
def shared_datasets() -> Path:
    """Path to the real datasets in ../shared/datasets; skips the test when they are not beside the checkout."""
    path = shared_datasets_dir()
    if path is None:
        pytest.skip("../shared/datasets is not beside this checkout (real-data test skipped)")
    return path
