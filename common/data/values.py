"""The value parsers of the dataset reader: each takes a decoded JSON/YAML value and returns it
checked and converted, or raises ``BadValue`` with the reason (the caller adds the file, line and
field, see ``common.data.dataset.DatasetError``). ``FileValue``: a parser as the type of a
declared field (``common.runtime.schema``), as dataset.yaml's sections declare theirs."""
from __future__ import annotations

import math
from typing import Optional

import numpy as np


class BadValue(Exception):
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
        except BadValue as exc:
            raise ValueError(str(exc)) from None


def parse_number(v) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise BadValue(f"expected a number, got {type(v).__name__} {v!r}"[:120])
    if not math.isfinite(v):
        raise BadValue(f"expected a finite number, got {v!r}")
    return float(v)


def parse_int(v) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        if isinstance(v, float) and v.is_integer():
            return int(v)
        raise BadValue(f"expected an integer, got {type(v).__name__} {v!r}"[:120])
    return v


def parse_matrix(v, rows: int, cols: int) -> np.ndarray:
    if not isinstance(v, (list, tuple)) or len(v) != rows:
        raise BadValue(f"expected {rows} rows of {cols} numbers")
    out = np.empty((rows, cols))
    for i, row in enumerate(v):
        if not isinstance(row, (list, tuple)) or len(row) != cols:
            raise BadValue(f"row {i}: expected {cols} numbers, got {row!r}"[:120])
        for j, x in enumerate(row):
            try:
                out[i, j] = parse_number(x)
            except BadValue as exc:
                raise BadValue(f"[{i}][{j}]: {exc}") from None
    return out


def parse_vector(v, n: Optional[int]) -> np.ndarray:
    if not isinstance(v, (list, tuple)) or (n is not None and len(v) != n):
        raise BadValue(f"expected a list of {n} numbers, got {v!r}"[:120])
    out = np.empty(len(v))
    for i, x in enumerate(v):
        try:
            out[i] = parse_number(x)
        except BadValue as exc:
            raise BadValue(f"[{i}]: {exc}") from None
    return out


def parse_rigid(v) -> np.ndarray:
    T = parse_matrix(v, 4, 4)
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9):
        raise BadValue(f"last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise BadValue("rotation part is not a rotation (R^T R != I or det < 0)")
    return T


def parse_bools(v, n: int) -> np.ndarray:
    if not isinstance(v, (list, tuple)) or len(v) != n or not all(isinstance(b, bool) for b in v):
        raise BadValue(f"expected a list of {n} booleans, got {v!r}"[:120])
    return np.array(v, dtype=bool)
