"""The checks a message's fields pass at decoding and at publishing: the limits (finite,
bounded; the fields declare them, ``common.runtime.schema``), rigid transforms, covariances,
image headers, the pose invariant. Each failure names the message type and the field
(``MessageError``)."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Optional

import numpy as np

from common.constraints import MAX_NUMBER
from common.errors import NeedletrackError

if TYPE_CHECKING:
    from common.runtime.messages import PoseEstimate

MAX_IMAGE_SIDE = 16384
"""Largest image width or height (px) a message may state or carry."""

MAX_INT = (1 << 63) - 1
"""Largest ``seq``/``stamp_ns``/``epoch`` (int64): a msgpack uint64 beyond it is refused."""

MAX_COORD = MAX_NUMBER
"""Largest magnitude of any array element or float a message may carry (px, m, rad all fit):
values beyond are refused at decode, so no handler sees an overflow-prone 1e300."""

RIGID_TOL = 1e-6
"""Tolerance of the rigid-transform check: |R^T R - I|, |det R - 1| and the bottom row."""


class MessageError(NeedletrackError, ValueError):
    """A payload that is not a valid message; the text names the message type and field."""


MAX_ARRAY_ELEMENTS = 1 << 20
"""Largest number of elements of an array field (a centreline has a few hundred points)."""


def rigid_error(T, where: str) -> Optional[str]:
    """None if ``T`` is a 4x4 rigid transform (finite, R orthonormal with det +1 and bottom row
    [0 0 0 1] within ``RIGID_TOL``), else why not, prefixed by ``where``."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        return f"{where}: expected shape (4, 4), got {T.shape}"
    if not np.isfinite(T).all():
        return f"{where}: not finite"
    R = T[:3, :3]
    if np.abs(R).max() > 2.0:       # no rotation has an element beyond 1 (and R.T @ R would overflow)
        return f"{where}: not a rigid transform (rotation elements beyond 1)"
    if (np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)).max() > RIGID_TOL
            or np.abs(R.T @ R - np.eye(3)).max() > RIGID_TOL or abs(np.linalg.det(R) - 1.0) > RIGID_TOL):
        return f"{where}: not a rigid transform (rotation not orthonormal with det 1, or bottom row not 0 0 0 1)"
    return None


def require_rigid(T, where: str) -> None:
    """``T`` (when not None) a rigid 4x4 transform, else MessageError naming ``where``."""
    if T is not None:
        err = rigid_error(T, where)
        if err:
            raise MessageError(err)


def covariance_error(C, where: str) -> Optional[str]:
    """None if ``C`` is a finite symmetric positive semi-definite matrix, else why not."""
    C = np.asarray(C, dtype=float)
    if not np.isfinite(C).all():
        return f"{where}: not finite"
    scale = max(1.0, float(np.abs(C).max()))
    if np.abs(C - C.T).max() > 1e-9 * scale:
        return f"{where}: not symmetric"
    if np.linalg.eigvalsh(0.5 * (C + C.T)).min() < -1e-9 * scale:
        return f"{where}: not positive semi-definite"
    return None


def image_header_size(data) -> Optional[tuple]:
    """``(width, height)`` read from a PNG's IHDR or a JPEG's SOF header without decoding the
    pixels, or None for data that is neither (empty, truncated, another format)."""
    b = bytes(data[:65536]) if len(data) > 65536 else bytes(data)
    if b[:8] == b"\x89PNG\r\n\x1a\n" and len(b) >= 24 and b[12:16] == b"IHDR":
        return int.from_bytes(b[16:20], "big"), int.from_bytes(b[20:24], "big")
    if b[:2] != b"\xff\xd8":
        return None
    p = 2
    while p + 4 <= len(b):
        if b[p] != 0xFF:
            return None
        marker = b[p + 1]
        if marker == 0xFF:                  # fill byte
            p += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            p += 2
            continue
        length = int.from_bytes(b[p + 2:p + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if p + 9 > len(b):
                return None
            return int.from_bytes(b[p + 7:p + 9], "big"), int.from_bytes(b[p + 5:p + 7], "big")
        if length < 2:
            return None
        p += 2 + length
    return None


def pose_invariant_error(msg: "PoseEstimate", max_range_m: Optional[float] = None) -> Optional[str]:
    """The pose invariant: None if ``msg`` holds, else the first violation. Every transform
    rigid (finite, rotation orthonormal with det +1), ``covariance`` symmetric positive
    semi-definite, and, with ``max_range_m``, the needle within that distance of the ECM (m)."""
    for name in ("T_ecm_needle", "T_world_needle", "T_world_ecm"):
        T = getattr(msg, name)
        if T is not None:
            err = rigid_error(T, f"PoseEstimate.{name}")
            if err:
                return err
    if msg.covariance is not None:
        err = covariance_error(msg.covariance, "PoseEstimate.covariance")
        if err:
            return err
        if not np.abs(np.asarray(msg.covariance, dtype=float)).max() <= MAX_COORD:
            return f"PoseEstimate.covariance: beyond {MAX_COORD:g}"
    if msg.model_sigma_m is not None and not 0.0 <= float(msg.model_sigma_m) <= 1.0:
        return f"PoseEstimate.model_sigma_m: must be in [0, 1] m, got {msg.model_sigma_m}"
    if msg.model_sigma_rad is not None and not 0.0 <= float(msg.model_sigma_rad) <= math.pi:
        return f"PoseEstimate.model_sigma_rad: must be in [0, pi] rad, got {msg.model_sigma_rad}"
    if msg.end_identity is not None and not 0.0 <= float(msg.end_identity) <= 1.0:
        return f"PoseEstimate.end_identity: must be a probability in [0, 1], got {msg.end_identity}"
    if not abs(float(msg.residual)) <= MAX_COORD:     # what decode would refuse downstream
        return f"PoseEstimate.residual: not finite, or beyond {MAX_COORD:g}: {msg.residual}"
    if max_range_m is not None:
        d = float(np.linalg.norm(np.asarray(msg.T_ecm_needle, dtype=float)[:3, 3]))
        if not d <= max_range_m:
            return f"PoseEstimate.T_ecm_needle: needle {d:.3g} m from the ECM, beyond the working volume ({max_range_m} m)"
    return None


def finite_array(where: str, value, shape) -> np.ndarray:
    """``value`` as a finite float array of ``shape`` (None: any 1-D length), or MessageError."""
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise MessageError(f"{where}: expected numbers, got {type(value).__name__}") from None
    if (a.ndim != 1 if shape is None else a.shape != shape):
        raise MessageError(f"{where}: expected shape {shape or '(N,)'}, got {a.shape}")
    if not np.isfinite(a).all():
        raise MessageError(f"{where}: not finite")
    return a


# The checks a message passes before a node publishes it, by message type: the counter a failure
# adds to and ``check(msg, pose_volume_m)`` -> the violation or None. The generic runtime knows
# no message type; a type added here is checked at every node's ``publish``.
PUBLISH_CHECKS = {"PoseEstimate": ("invalid_pose", pose_invariant_error)}


def publish_check_error(msg, pose_volume_m: Optional[float]) -> Optional[tuple]:
    """``(counter, violation)`` if ``msg`` fails its type's check before publishing
    (``PUBLISH_CHECKS``), else None."""
    entry = PUBLISH_CHECKS.get(type(msg).__name__)
    if entry is None:
        return None
    err = entry[1](msg, pose_volume_m)
    return None if err is None else (entry[0], err)
