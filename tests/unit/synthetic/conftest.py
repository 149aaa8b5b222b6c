"""Shared synthetic datasets: textures are generated lazily and cached per dataset, so tests reuse them."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from slamkit.io.synthetic import SyntheticDataset


@pytest.fixture(scope="session")
def synthetic() -> Callable[..., SyntheticDataset]:
    """make(**options) -> a SyntheticDataset, built once per distinct set of options in the session."""
    cache: dict[tuple[tuple[str, Any], ...], SyntheticDataset] = {}

    def make(**options: Any) -> SyntheticDataset:
        key = tuple(sorted((k, repr(v)) for k, v in options.items()))
        if key not in cache:
            cache[key] = SyntheticDataset(**options)
        return cache[key]

    return make
