"""Typed access to OpenCV-style YAML files (``%YAML:1.0``, ``!!opencv-matrix``) via cv2.FileStorage.

EuRoC ``sensor.yaml`` and ORB-SLAM settings files use this dialect, which PyYAML rejects. Every getter
raises CalibrationError naming the file and the key, and what was expected.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from slamkit.errors import CalibrationError

F64 = NDArray[np.float64]

_PARSE_ERROR = re.compile(r"'(?P<file>.*)\((?P<line>\d+)\): (?P<msg>[^']*)'")


class CvYaml:
    """A read-only OpenCV YAML file. ``what`` describes the file in messages (e.g. 'ORB-SLAM settings')."""

    def __init__(self, path: Path, what: str) -> None:
        self.path = Path(path)
        self.what = what
        if not self.path.is_file():
            raise CalibrationError(f"{what}: file {self.path} does not exist")
        try:
            fs = cv2.FileStorage(str(self.path), cv2.FILE_STORAGE_READ)
        except (SystemError, cv2.error) as exc:
            cause = exc.__cause__ or exc.__context__ or exc
            m = _PARSE_ERROR.search(str(cause))
            where = f"{self.path}:{m.group('line')}: {m.group('msg')}" if m else f"{self.path}: {cause}"
            raise CalibrationError(f"{where} (cannot parse {what} as OpenCV YAML)") from exc
        if not fs.isOpened():
            raise CalibrationError(f"{self.path}: cannot open {what} (expected an OpenCV YAML file)")
        self._fs = fs

    def _node(self, key: str) -> Any:
        node = self._fs.getNode(key)
        return None if node.empty() or node.isNone() else node

    def has(self, key: str) -> bool:
        return self._node(key) is not None

    def _missing(self, key: str, expected: str) -> CalibrationError:
        return CalibrationError(f"{self.path}: {self.what} lacks '{key}' (expected {expected})")

    def real(self, key: str) -> float:
        """A required number."""
        node = self._node(key)
        if node is None:
            raise self._missing(key, "a number")
        if not (node.isReal() or node.isInt()):
            raise CalibrationError(f"{self.path}: '{key}' should be a number in the {self.what}")
        return float(node.real())

    def real_or(self, key: str, default: float | None) -> float | None:
        return self.real(key) if self.has(key) else default

    def integer(self, key: str) -> int:
        value = self.real(key)
        if value != int(value):
            raise CalibrationError(f"{self.path}: '{key}' should be an integer in the {self.what}, got {value}")
        return int(value)

    def string(self, key: str) -> str:
        node = self._node(key)
        if node is None:
            raise self._missing(key, "a string")
        if not node.isString():
            raise CalibrationError(f"{self.path}: '{key}' should be a string in the {self.what}")
        return str(node.string())

    def string_or(self, key: str, default: str | None) -> str | None:
        return self.string(key) if self.has(key) else default

    def vector(self, key: str, length: int | None = None) -> F64:
        """A sequence of numbers ``[a, b, ...]`` (or an opencv-matrix, flattened)."""
        node = self._node(key)
        if node is None:
            raise self._missing(key, "a list of numbers")
        if node.isSeq():
            vals = []
            for i in range(node.size()):
                item = node.at(i)
                if not (item.isReal() or item.isInt()):
                    raise CalibrationError(f"{self.path}: '{key}' item {i} should be a number")
                vals.append(float(item.real()))
            out = np.array(vals, dtype=np.float64)
        else:
            out = self.matrix(key).ravel()
        if length is not None and out.shape[0] != length:
            raise CalibrationError(
                f"{self.path}: '{key}' has {out.shape[0]} numbers; expected {length} in the {self.what}"
            )
        return out

    def matrix(self, key: str, shape: tuple[int, int] | None = None) -> F64:
        """An ``!!opencv-matrix`` or a ``{rows, cols, data}`` map (EuRoC's T_BS) as float64."""
        node = self._node(key)
        if node is None:
            raise self._missing(key, "a matrix")
        if node.isMap() and node.getNode("dt").empty():  # EuRoC style: no dtype, so not an opencv-matrix
            rows, cols, data = node.getNode("rows"), node.getNode("cols"), node.getNode("data")
            if rows.empty() or cols.empty() or data.empty() or not data.isSeq():
                raise CalibrationError(f"{self.path}: '{key}' should be a matrix with rows, cols and data")
            r, c = int(rows.real()), int(cols.real())
            if data.size() != r * c:
                raise CalibrationError(
                    f"{self.path}: '{key}' has {data.size()} data values; expected rows*cols = {r * c}"
                )
            mat = np.array([data.at(i).real() for i in range(data.size())], dtype=np.float64).reshape(r, c)
        else:
            m = node.mat()
            if m is None:
                raise CalibrationError(f"{self.path}: '{key}' should be an !!opencv-matrix in the {self.what}")
            mat = np.asarray(m, dtype=np.float64)
        if shape is not None and mat.shape != shape:
            raise CalibrationError(f"{self.path}: '{key}' is {mat.shape}; expected a {shape[0]}x{shape[1]} matrix")
        return mat
