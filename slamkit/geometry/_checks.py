"""Input checks shared by the geometry modules: shapes and dtypes with messages naming the parameter."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


def as_float_array(value: Any, name: str) -> F64:
    """``value`` as a float64 array, or ValueError naming ``name`` when it is not numeric."""
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected a numeric array, got {type(value).__name__}") from exc


def as_points(value: Any, dim: int, name: str) -> tuple[F64, bool]:
    """``value`` of shape (N, dim) or (dim,) -> ((N, dim) float64, whether a single point was given)."""
    arr = as_float_array(value, name)
    if arr.ndim == 1 and arr.shape[0] == dim:
        return arr[None, :], True
    if arr.ndim == 2 and arr.shape[1] == dim:
        return arr, False
    raise ValueError(f"{name}: expected an array of shape (N, {dim}) or ({dim},), got shape {arr.shape}")


def as_matrix(value: Any, shape: tuple[int, ...], name: str, *, finite: bool = True) -> F64:
    """``value`` as a float64 array of exactly ``shape`` (finite unless told otherwise)."""
    arr = as_float_array(value, name)
    if arr.shape != shape:
        raise ValueError(f"{name}: expected an array of shape {shape}, got shape {arr.shape}")
    if finite and not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or inf")
    return arr


def as_batch_matrix(value: Any, shape: tuple[int, int], name: str) -> F64:
    """``value`` of shape (..., *shape) as float64 (any number of leading batch dimensions)."""
    arr = as_float_array(value, name)
    if arr.ndim < 2 or arr.shape[-2:] != shape:
        raise ValueError(f"{name}: expected an array of shape (..., {shape[0]}, {shape[1]}), got {arr.shape}")
    return arr


def same_length(a: F64, b: F64, name_a: str, name_b: str) -> None:
    """ValueError when two (N, d) arrays do not have the same N."""
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"{name_a} and {name_b}: expected the same number of rows, got {a.shape[0]} and {b.shape[0]}")
