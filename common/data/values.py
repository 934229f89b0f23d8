"""The value parsers of the dataset reader: each takes a decoded JSON/YAML value and returns it
checked and converted, or raises ``_Bad`` with the reason (the caller adds the file, line and
field, see ``common.data.dataset.DatasetError``). ``FileValue``: a parser as the type of a
declared field (``common.runtime.schema``), as dataset.yaml's sections declare theirs."""
from __future__ import annotations

import math
from typing import Optional

import numpy as np


class _Bad(Exception):
    """Raised by the parsers below with the reason; wrapped into a DatasetError with the place.
    ``sub``: the part of the field at fault (e.g. ``psm1.T_world_jaw`` of ``instruments``)."""

    def __init__(self, msg: str, sub: Optional[str] = None):
        super().__init__(msg)
        self.sub = sub


class FileValue:
    """A field type of a dataset file: ``check`` parses a decoded value with ``parse`` (one of
    the parsers below, and the field's own constraints), ValueError with the reason."""

    @staticmethod
    def parse(v):
        raise NotImplementedError

    @classmethod
    def check(cls, v):
        try:
            return cls.parse(v)
        except _Bad as exc:
            raise ValueError(str(exc)) from None


def _num(v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _Bad(f"expected a number, got {type(v).__name__} {v!r}"[:120])
    if not math.isfinite(v):
        raise _Bad(f"expected a finite number, got {v!r}")
    return float(v)


def _int(v) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        if isinstance(v, float) and v.is_integer():
            return int(v)
        raise _Bad(f"expected an integer, got {type(v).__name__} {v!r}"[:120])
    return v


def _matrix(v, rows: int, cols: int) -> np.ndarray:
    if not isinstance(v, (list, tuple)) or len(v) != rows:
        raise _Bad(f"expected {rows} rows of {cols} numbers")
    out = np.empty((rows, cols))
    for i, row in enumerate(v):
        if not isinstance(row, (list, tuple)) or len(row) != cols:
            raise _Bad(f"row {i}: expected {cols} numbers, got {row!r}"[:120])
        for j, x in enumerate(row):
            try:
                out[i, j] = _num(x)
            except _Bad as exc:
                raise _Bad(f"[{i}][{j}]: {exc}") from None
    return out


def _vector(v, n: Optional[int]) -> np.ndarray:
    if not isinstance(v, (list, tuple)) or (n is not None and len(v) != n):
        raise _Bad(f"expected a list of {n} numbers, got {v!r}"[:120])
    out = np.empty(len(v))
    for i, x in enumerate(v):
        try:
            out[i] = _num(x)
        except _Bad as exc:
            raise _Bad(f"[{i}]: {exc}") from None
    return out


def _rigid(v) -> np.ndarray:
    T = _matrix(v, 4, 4)
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9):
        raise _Bad(f"last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise _Bad("rotation part is not a rotation (R^T R != I or det < 0)")
    return T


def _bools(v, n: int) -> np.ndarray:
    if not isinstance(v, (list, tuple)) or len(v) != n or not all(isinstance(b, bool) for b in v):
        raise _Bad(f"expected a list of {n} booleans, got {v!r}"[:120])
    return np.array(v, dtype=bool)
