"""Messages the dataflow carries, and their msgpack codec (no pickle).

Every payload is a msgpack map ``{"schema": NAME, "version": V, "body": {...}}``. numpy arrays
travel as a msgpack extension (dtype, shape, raw bytes) and round-trip exactly. ``decode``
validates the schema, version and every field, and raises ``MessageError`` naming the message
type and the field.

Stereo frames travel as two ``CameraImage`` messages (one per camera) that share ``seq``;
consumers pair them by ``seq`` (see ``common.runtime.pairing``).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Optional

import msgpack
import numpy as np

_EXT_NDARRAY = 1
_DTYPES = {"bool", "uint8", "uint16", "int32", "int64", "float32", "float64"}


MAX_IMAGE_SIDE = 16384
"""Largest image width or height (px) a message may state or carry."""

MAX_INT = (1 << 63) - 1
"""Largest ``seq``/``stamp_ns``/``epoch`` (int64): a msgpack uint64 beyond it is refused."""

MAX_COORD = 1e7
"""Largest magnitude of any array element or float a message may carry (px, m, rad all fit):
values beyond are refused at decode, so no handler sees an overflow-prone 1e300."""

RIGID_TOL = 1e-6
"""Tolerance of the rigid-transform check: |R^T R - I|, |det R - 1| and the bottom row."""


class MessageError(ValueError):
    """A payload that is not a valid message; the text names the message type and field."""


# ---------------------------------------------------------------- ndarray extension

_DTYPE = {name: np.dtype(name) for name in _DTYPES}
_DTYPE_NAME = {dt: name for name, dt in _DTYPE.items()}     # (``dtype.name`` is slow to get)
_UINT_BYTES = {0xcc: 1, 0xcd: 2, 0xce: 4, 0xcf: 8}          # msgpack uint 8/16/32/64 markers


def _default(obj):
    if isinstance(obj, np.ndarray):
        name = _DTYPE_NAME.get(obj.dtype)
        if name is None:                       # not native byte order, or not sendable
            name = obj.dtype.name
            if name not in _DTYPES:
                raise TypeError(f"ndarray dtype {obj.dtype} cannot be sent")
            obj = obj.astype(name)
        head = msgpack.packb([name, list(obj.shape)])
        return msgpack.ExtType(_EXT_NDARRAY, head + obj.tobytes())    # tobytes: C order
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot encode {type(obj).__name__}")


def _ndarray_header(data: bytes):
    """``(dtype, shape, offset of the raw bytes)`` of an ndarray extension, whose header is
    the msgpack ``[dtype name, [dims]]`` that ``_default`` writes, read directly (a msgpack
    Unpacker per array costs more than the rest of a small message); None for another form."""
    if data[0] != 0x92 or not 0xa0 <= data[1] <= 0xbf:          # fixarray(2), fixstr
        return None
    p = 2 + (data[1] & 0x1f)
    if not 0x90 <= data[p] <= 0x9f:                              # fixarray(ndim)
        return None
    dtype, ndim, p = data[2:p].decode("ascii", "replace"), data[p] & 0x0f, p + 1
    shape = []
    for _ in range(ndim):
        b = data[p]
        if b < 0x80:                                             # positive fixint
            shape.append(b)
            p += 1
        elif b in _UINT_BYTES:
            k = _UINT_BYTES[b]
            shape.append(int.from_bytes(data[p + 1:p + 1 + k], "big"))
            p += 1 + k
        else:
            return None
    return dtype, shape, p


def _ext_hook(code, data):
    if code != _EXT_NDARRAY:
        raise MessageError(f"unknown msgpack extension type {code}")
    try:
        head = _ndarray_header(data)
    except IndexError:
        head = None
    if head is None:
        unpacker = msgpack.Unpacker(raw=False)
        unpacker.feed(data)
        try:
            dtype, shape = next(unpacker)
        except Exception as exc:  # malformed header
            raise MessageError(f"malformed ndarray header: {exc}") from None
        offset = unpacker.tell()
    else:
        dtype, shape, offset = head
    dt = _DTYPE.get(dtype) if isinstance(dtype, str) else None
    if dt is None or not isinstance(shape, list) or not all(type(d) is int and d >= 0 for d in shape):
        raise MessageError(f"bad ndarray header dtype={dtype!r} shape={shape!r}")
    n = math.prod(shape) * dt.itemsize
    if len(data) - offset != n:
        raise MessageError(f"ndarray of {dtype}{tuple(shape)} needs {n} bytes, got {len(data) - offset}")
    return np.frombuffer(data, dtype=dt, offset=offset).reshape(shape).copy()


# ---------------------------------------------------------------- field validation

def _check(msg_name: str, fname: str, value, spec):
    """Validate and normalise one field value against its spec; returns the value to store."""
    kind = spec[0]
    where = f"{msg_name}.{fname}"
    if value is None:
        if "optional" in spec[1:]:
            return None
        raise MessageError(f"{where}: required, got null")
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise MessageError(f"{where}: expected int, got {type(value).__name__}")
        if not -MAX_INT <= value <= MAX_INT:
            raise MessageError(f"{where}: out of the int64 range, got {value}")
        return value
    if kind == "float":
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise MessageError(f"{where}: expected number, got {type(value).__name__}")
        value = float(value)
        if not abs(value) <= MAX_COORD:          # NaN and inf fail this too
            raise MessageError(f"{where}: not finite, or beyond {MAX_COORD:g}: got {value}")
        return value
    if kind == "bool":
        if not isinstance(value, bool):
            raise MessageError(f"{where}: expected bool, got {type(value).__name__}")
        return value
    if kind == "str":
        if not isinstance(value, str):
            raise MessageError(f"{where}: expected string, got {type(value).__name__}")
        if len(spec) > 1 and isinstance(spec[1], tuple) and value not in spec[1]:
            raise MessageError(f"{where}: must be one of {spec[1]}, got {value!r}")
        return value
    if kind == "bytes":
        if not isinstance(value, (bytes, bytearray, memoryview)):
            raise MessageError(f"{where}: expected bytes, got {type(value).__name__}")
        return value if isinstance(value, (bytes, memoryview)) else bytes(value)
    if kind == "dict":
        if not isinstance(value, dict):
            raise MessageError(f"{where}: expected map, got {type(value).__name__}")
        return value
    if kind == "array":
        shape = spec[1]
        if isinstance(value, list):  # tolerate plain lists from other writers
            try:
                value = np.asarray(value, dtype=float)
            except (TypeError, ValueError):
                raise MessageError(f"{where}: expected numeric array") from None
        if not isinstance(value, np.ndarray):
            raise MessageError(f"{where}: expected array, got {type(value).__name__}")
        if len(value.shape) != len(shape) or any(s is not None and s != v for s, v in zip(shape, value.shape)):
            want = tuple("N" if s is None else s for s in shape)
            raise MessageError(f"{where}: expected shape {want}, got {value.shape}")
        if value.size > MAX_ARRAY_ELEMENTS:
            raise MessageError(f"{where}: {value.size} elements, at most {MAX_ARRAY_ELEMENTS}")
        _check_values(where, value, "nan" in spec)
        return value
    if kind == "camera_map":  # {"left": array, "right": array}, each of shape spec[1]
        if not isinstance(value, dict) or set(value) - {"left", "right"}:
            raise MessageError(f"{where}: expected a map with keys left/right")
        out = {}
        for k, v in value.items():
            if v is None:
                out[k] = None
                continue
            try:
                a = v if isinstance(v, np.ndarray) else np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                raise MessageError(f"{where}.{k}: expected a numeric array") from None
            if a.shape != spec[1]:
                raise MessageError(f"{where}.{k}: expected shape {spec[1]}, got {a.shape}")
            _check_values(f"{where}.{k}", a, True)
            out[k] = a
        return out
    raise AssertionError(kind)


MAX_ARRAY_ELEMENTS = 1 << 20
"""Largest number of elements of an array field (a centreline has a few hundred points)."""


def _check_values(where: str, a: np.ndarray, nan_ok: bool) -> None:
    """Numeric arrays: every element finite (NaN allowed when ``nan_ok``: "missing") and at most
    ``MAX_COORD`` in size; inf is never allowed."""
    if a.dtype.kind not in "fiub":
        raise MessageError(f"{where}: expected a numeric array, got dtype {a.dtype}")
    if a.dtype.kind == "f":
        bad = ~(np.abs(a) <= MAX_COORD)
        if nan_ok:
            bad &= ~np.isnan(a)
        if bad.any():
            raise MessageError(f"{where}: not finite, or beyond {MAX_COORD:g} ({int(bad.sum())} element(s))")
    elif a.dtype.kind in "iu" and a.size and np.abs(a.astype(np.float64)).max() > MAX_COORD:
        raise MessageError(f"{where}: element(s) beyond {MAX_COORD:g}")


def rigid_error(T, where: str) -> Optional[str]:
    """None if ``T`` is a 4x4 rigid transform (finite, R orthonormal with det +1 and bottom row
    [0 0 0 1] within ``RIGID_TOL``), else why not, prefixed by ``where``."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        return f"{where}: expected shape (4, 4), got {T.shape}"
    if not np.isfinite(T).all():
        return f"{where}: not finite"
    R = T[:3, :3]
    if (np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)).max() > RIGID_TOL
            or np.abs(R.T @ R - np.eye(3)).max() > RIGID_TOL or abs(np.linalg.det(R) - 1.0) > RIGID_TOL):
        return f"{where}: not a rigid transform (rotation not orthonormal with det 1, or bottom row not 0 0 0 1)"
    return None


def _rigid(T, where: str) -> None:
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


class Message:
    """Base of all messages: a dataclass with a schema name, a version and field specs."""

    SCHEMA: str = ""
    VERSION: int = 1
    FIELDS: dict = {}

    def to_body(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


_REGISTRY: dict[str, type] = {}


def register(cls):
    _REGISTRY[cls.SCHEMA] = cls
    return cls


_TAIL_MIN = 1 << 16     # a bytes field at least this large travels as the payload's tail


def encode(msg: Message) -> bytes:
    """Message -> msgpack bytes.

    The largest bytes field of at least 64 KiB (an image) is packed last, as a bin32 after the
    rest, and joined in one copy: the result is plain msgpack, and ``decode`` can hand that
    field out as a view of the payload instead of copying it.
    """
    head, tail = encode_parts(msg)
    return head if tail is None else b"".join((head, tail))


def encode_parts(msg: Message) -> tuple:
    """``(head, tail)`` with ``encode(msg) == head + tail``; ``tail`` is None or the large bytes
    field (not copied), so a transport can write both into one buffer of its own."""
    body = msg.to_body()
    tail_key, tail = None, None
    for k, v in body.items():
        if isinstance(v, (bytes, bytearray, memoryview)) and len(v) >= _TAIL_MIN and (tail is None or len(v) > len(tail)):
            tail_key, tail = k, v
    if tail_key is None:
        return msgpack.packb({"schema": msg.SCHEMA, "version": msg.VERSION, "body": body},
                             default=_default, use_bin_type=True), None
    tail = memoryview(tail).cast("B") if not isinstance(tail, bytes) else tail
    del body[tail_key]
    packer = msgpack.Packer(default=_default, use_bin_type=True, autoreset=False)
    packer.pack_map_header(3)
    packer.pack("schema"), packer.pack(msg.SCHEMA), packer.pack("version"), packer.pack(msg.VERSION)
    packer.pack("body")
    packer.pack_map_header(len(body) + 1)
    for k, v in body.items():
        packer.pack(k), packer.pack(v)
    packer.pack(tail_key)
    head = packer.bytes() + b"\xc6" + len(tail).to_bytes(4, "big")
    return head, tail


def _unpack_with_tail(buf: bytes):
    """Fast path for payloads made by ``encode`` with a tail field: unpack the small head and
    return the tail as a memoryview of ``buf``; None if ``buf`` does not have that layout."""
    n = len(buf)
    limit = min(n - 5, _TAIL_MIN)
    p = buf.find(b"\xc6", 0, limit)
    while p != -1:
        if int.from_bytes(buf[p + 1:p + 5], "big") == n - p - 5:
            try:
                data = msgpack.unpackb(buf[:p] + b"\xc0", ext_hook=_ext_hook, raw=False, strict_map_key=False)
            except Exception:
                return None
            body = data.get("body") if isinstance(data, dict) else None
            if not isinstance(body, dict) or not body or list(body.values())[-1] is not None:
                return None
            body[list(body)[-1]] = memoryview(buf)[p + 5:]
            return data
        p = buf.find(b"\xc6", p + 1, limit)
    return None


_NONNEGATIVE = ("seq", "stamp_ns", "epoch", "frames")


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


def pose_error(msg: "PoseEstimate", max_range_m: Optional[float] = None) -> Optional[str]:
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


def decode(payload, expect: type | None = None) -> Message:
    """msgpack bytes -> validated Message. ``expect`` restricts the accepted message type."""
    try:
        buf = payload if isinstance(payload, bytes) else bytes(payload)
        data = _unpack_with_tail(buf) if len(buf) > _TAIL_MIN else None
        if data is None:
            data = msgpack.unpackb(buf, ext_hook=_ext_hook, raw=False, strict_map_key=False)
    except MessageError:
        raise
    except Exception as exc:
        what = expect.__name__ if expect else "message"
        raise MessageError(f"{what}: not valid msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(data, dict) or "schema" not in data or "body" not in data:
        raise MessageError(f"{expect.__name__ if expect else 'message'}: missing schema envelope")
    cls = _REGISTRY.get(data["schema"])
    if cls is None:
        raise MessageError(f"message: unknown schema {data['schema']!r}")
    if expect is not None and cls is not expect:
        raise MessageError(f"{expect.__name__}: got a {cls.__name__} instead")
    if data.get("version") != cls.VERSION:
        raise MessageError(f"{cls.__name__}.version: expected {cls.VERSION}, got {data.get('version')!r}")
    body = data["body"]
    if not isinstance(body, dict):
        raise MessageError(f"{cls.__name__}: body is not a map")
    unknown = set(body) - set(cls.FIELDS)
    if unknown:
        raise MessageError(f"{cls.__name__}.{min(unknown, key=str)}: unknown field")
    kwargs = {}
    for fname, spec in cls.FIELDS.items():
        if fname not in body:
            if "optional" in spec[1:]:
                continue
            raise MessageError(f"{cls.__name__}.{fname}: missing")
        kwargs[fname] = _check(cls.__name__, fname, body[fname], spec)
    for fname in _NONNEGATIVE:
        if kwargs.get(fname) is not None and kwargs[fname] < 0:
            raise MessageError(f"{cls.__name__}.{fname}: must not be negative, got {kwargs[fname]}")
    msg = cls(**kwargs)
    try:
        msg.validate()
    except MessageError:
        raise
    except Exception as exc:   # a validate() that trips on a value it did not foresee
        raise MessageError(f"{cls.__name__}: invalid ({type(exc).__name__}: {exc})") from None
    return msg


# ---------------------------------------------------------------- the messages

CAMERAS = ("left", "right")
ENCODINGS = ("bgr8", "png", "jpeg")


@register
@dataclass
class CameraImage(Message):
    """One camera's image of a stereo frame. ``data`` is raw BGR (h*w*3 bytes) or a PNG/JPEG file.

    A decoded image's ``data`` may be a read-only memoryview of the payload (no copy); use
    ``to_bgr()`` or ``bytes(msg.data)``.
    """

    SCHEMA = "needletrack.CameraImage"
    FIELDS = {"camera": ("str", CAMERAS), "seq": ("int",), "stamp_ns": ("int",),
              "width": ("int",), "height": ("int",), "encoding": ("str", ENCODINGS),
              "data": ("bytes",), "epoch": ("int", "optional")}
    camera: str
    seq: int
    stamp_ns: int
    width: int
    height: int
    encoding: str
    data: bytes
    epoch: Optional[int] = None

    def validate(self):
        if not (1 <= self.width <= MAX_IMAGE_SIDE and 1 <= self.height <= MAX_IMAGE_SIDE):
            raise MessageError(f"CameraImage.width/height: must be in 1..{MAX_IMAGE_SIDE}, got {self.width}x{self.height}")
        if self.encoding == "bgr8" and len(self.data) != self.width * self.height * 3:
            raise MessageError(f"CameraImage.data: bgr8 {self.width}x{self.height} needs "
                               f"{self.width * self.height * 3} bytes, got {len(self.data)}")
        if self.encoding != "bgr8":
            size = image_header_size(self.data)
            if size is None:
                raise MessageError(f"CameraImage.data: not a {self.encoding} file ({len(self.data)} bytes)")
            if size != (self.width, self.height):
                raise MessageError(f"CameraImage.data: the {self.encoding} header says {size[0]}x{size[1]}, "
                                   f"the message {self.width}x{self.height}")

    @classmethod
    def from_bgr(cls, camera: str, seq: int, stamp_ns: int, img: np.ndarray, encoding: str = "bgr8",
                 jpeg_quality: int = 95, copy: bool = True) -> "CameraImage":
        """``copy=False`` (bgr8) keeps a view of ``img`` instead of copying it: only for an
        array the caller will not modify while the message is in use."""
        h, w = img.shape[:2]
        if encoding == "bgr8":
            arr = np.ascontiguousarray(img, dtype=np.uint8)
            data = arr.tobytes() if copy else memoryview(arr.reshape(-1))
        else:
            import cv2
            ext = ".png" if encoding == "png" else ".jpg"
            params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if encoding == "jpeg" else []
            ok, buf = cv2.imencode(ext, img, params)
            if not ok:
                raise MessageError(f"CameraImage.data: could not encode {encoding}")
            data = buf.tobytes()
        return cls(camera, seq, stamp_ns, w, h, encoding, data)

    def to_bgr(self) -> np.ndarray:
        """The pixels as an (h, w, 3) uint8 BGR array; raises MessageError on corrupt data."""
        if self.encoding == "bgr8":
            return np.frombuffer(self.data, np.uint8).reshape(self.height, self.width, 3)
        import cv2
        size = image_header_size(self.data)                       # checked before decoding
        if size is None:
            raise MessageError(f"CameraImage.data: corrupt {self.encoding} ({len(self.data)} bytes, no header)")
        if size != (self.width, self.height):
            raise MessageError(f"CameraImage.data: the {self.encoding} header says {size[0]}x{size[1]}, "
                               f"the message {self.width}x{self.height}")
        try:
            img = cv2.imdecode(np.frombuffer(self.data, np.uint8), cv2.IMREAD_COLOR)
        except cv2.error as exc:
            raise MessageError(f"CameraImage.data: corrupt {self.encoding}: {str(exc).strip()[:200]}") from None
        if img is None:
            raise MessageError(f"CameraImage.data: corrupt {self.encoding} ({len(self.data)} bytes)")
        if img.shape[:2] != (self.height, self.width):
            raise MessageError(f"CameraImage.data: decoded {img.shape[1]}x{img.shape[0]}, "
                               f"header says {self.width}x{self.height}")
        return img


@register
@dataclass
class EcmJoints(Message):
    """ECM joint state q = [yaw, pitch, insertion, roll] (rad, rad, m, rad)."""

    SCHEMA = "needletrack.EcmJoints"
    FIELDS = {"seq": ("int",), "stamp_ns": ("int",), "q": ("array", (4,)), "epoch": ("int", "optional")}
    seq: int
    stamp_ns: int
    q: np.ndarray
    epoch: Optional[int] = None

    def validate(self):
        if not np.all(np.isfinite(self.q)):
            raise MessageError("EcmJoints.q: not finite")


@register
@dataclass
class EcmPose(Message):
    """Endoscope pose from forward kinematics: ``T_world_ecm`` at a joint state, and the
    cameras' poses ``T_world_left``/``T_world_right`` when the calibration is known."""

    SCHEMA = "needletrack.EcmPose"
    FIELDS = {"seq": ("int",), "stamp_ns": ("int",), "T_world_ecm": ("array", (4, 4)),
              "q": ("array", (4,), "optional"), "T_world_left": ("array", (4, 4), "optional"),
              "T_world_right": ("array", (4, 4), "optional"), "epoch": ("int", "optional")}
    seq: int
    stamp_ns: int
    T_world_ecm: np.ndarray
    q: Optional[np.ndarray] = None
    T_world_left: Optional[np.ndarray] = None
    T_world_right: Optional[np.ndarray] = None
    epoch: Optional[int] = None

    def validate(self):
        for name in ("T_world_ecm", "T_world_left", "T_world_right"):
            _rigid(getattr(self, name), f"EcmPose.{name}")


@register
@dataclass
class Keypoints(Message):
    """A detector's output for one camera image.

    ``found`` is False for "no needle" (then ``reason`` says why and ``uv`` is all NaN).
    ``uv`` (5, 2) pixels of A..E, ``scores`` (5,) in [0, 1], ``confidence`` overall in [0, 1],
    ``bbox`` [x0, y0, x1, y1] pixels. ``centreline`` optionally carries the dense observation
    of the needle's projected arc, (N, 2) pixels ordered from A to E, with ``centreline_w`` (N,),
    and optionally ``centreline_sigma_px``, the detector's 1-sigma error of a centreline point
    across the curve (px; absent: the consumer's default), and ``centreline_corr_points``, how
    many consecutive points' errors move together (>= 1; absent: independent). ``on_arc`` (5,) optionally marks (1)
    the keypoints the detector placed on its fitted arc instead of observing them on their own.
    ``keypoint_sigma_px`` optionally states the 1-sigma error of a keypoint per image axis as a
    stereo fit should take it (px; errors the two cameras' detections share included; absent:
    the consumer's default). ``end_identity`` optionally states the probability that A is the
    needle's tip as said (0.5: the image cannot tell the tip from the tail; absent: A is taken as
    said).
    """

    SCHEMA = "needletrack.Keypoints"
    FIELDS = {"camera": ("str", CAMERAS), "seq": ("int",), "stamp_ns": ("int",),
              "found": ("bool",), "uv": ("array", (5, 2), "nan"), "scores": ("array", (5,)),
              "confidence": ("float",), "bbox": ("array", (4,), "optional"),
              "detector": ("str",), "reason": ("str", "optional"),
              "centreline": ("array", (None, 2), "optional"),
              "centreline_w": ("array", (None,), "optional"),
              "centreline_sigma_px": ("float", "optional"),
              "on_arc": ("array", (5,), "optional"),
              "centreline_corr_points": ("float", "optional"),
              "keypoint_sigma_px": ("float", "optional"),
              "end_identity": ("float", "optional"), "epoch": ("int", "optional")}
    camera: str
    seq: int
    stamp_ns: int
    found: bool
    uv: np.ndarray
    scores: np.ndarray
    confidence: float
    bbox: Optional[np.ndarray] = None
    detector: str = ""
    reason: Optional[str] = None
    centreline: Optional[np.ndarray] = None
    centreline_w: Optional[np.ndarray] = None
    centreline_sigma_px: Optional[float] = None
    on_arc: Optional[np.ndarray] = None
    centreline_corr_points: Optional[float] = None
    keypoint_sigma_px: Optional[float] = None
    end_identity: Optional[float] = None
    epoch: Optional[int] = None

    def validate(self):
        s = self.centreline_sigma_px
        if s is not None and not (np.isfinite(s) and s > 0):
            raise MessageError(f"Keypoints.centreline_sigma_px: must be positive, got {s}")
        c = self.centreline_corr_points
        if c is not None and not (np.isfinite(c) and c >= 1):
            raise MessageError(f"Keypoints.centreline_corr_points: must be at least 1, got {c}")
        k = self.keypoint_sigma_px
        if k is not None and not (np.isfinite(k) and k > 0):
            raise MessageError(f"Keypoints.keypoint_sigma_px: must be positive, got {k}")
        e = self.end_identity
        if e is not None and not (0.0 <= e <= 1.0):
            raise MessageError(f"Keypoints.end_identity: must be a probability in [0, 1], got {e}")

    @classmethod
    def not_found(cls, camera: str, seq: int, stamp_ns: int, detector: str, reason: str,
                  confidence: float = 0.0) -> "Keypoints":
        return cls(camera, seq, stamp_ns, False, np.full((5, 2), np.nan), np.zeros(5),
                   float(confidence), None, detector, reason)


@register
@dataclass
class PoseEstimate(Message):
    """A needle pose. ``T_ecm_needle`` maps needle to ECM frame (m). ``residual`` is the
    method's RMS (reprojection px, or registration m, as ``residual_unit`` says).
    ``covariance`` (6, 6) over [rotation vector (rad), translation (m)] in the ECM frame, when known.
    ``model_sigma_m``, ``model_sigma_rad``: the part of the position and orientation error,
    1 sigma per axis (m, rad), that every estimate of this needle shares (the needle model's and
    the rig's own error; already inside ``covariance``): a fusion of views does not average it down.
    ``end_identity``: the probability that the needle's tip is where this pose puts it; the other
    answer is the pose turned end for end (``common.geometry.refine.tip_for_tail``, the same arc).
    Absent: the detectors stated nothing (A was taken as the tip).
    """

    SCHEMA = "needletrack.PoseEstimate"
    FIELDS = {"seq": ("int",), "stamp_ns": ("int",), "method": ("str",),
              "T_ecm_needle": ("array", (4, 4)), "T_world_needle": ("array", (4, 4), "optional"),
              "T_world_ecm": ("array", (4, 4), "optional"),
              "residual": ("float",), "residual_unit": ("str", "optional"),
              "n_views": ("int",), "covariance": ("array", (6, 6), "optional"),
              "ambiguous": ("bool", "optional"), "points_ecm": ("array", (None, 3), "optional", "nan"),
              "sequence": ("int", "optional"), "epoch": ("int", "optional"),
              "model_sigma_m": ("float", "optional"), "model_sigma_rad": ("float", "optional"),
              "end_identity": ("float", "optional")}
    seq: int
    stamp_ns: int
    method: str
    T_ecm_needle: np.ndarray
    T_world_needle: Optional[np.ndarray] = None
    T_world_ecm: Optional[np.ndarray] = None
    residual: float = 0.0
    residual_unit: Optional[str] = None
    n_views: int = 1
    covariance: Optional[np.ndarray] = None
    ambiguous: Optional[bool] = None
    points_ecm: Optional[np.ndarray] = None
    sequence: Optional[int] = None
    epoch: Optional[int] = None
    model_sigma_m: Optional[float] = None
    model_sigma_rad: Optional[float] = None
    end_identity: Optional[float] = None

    def validate(self):
        err = pose_error(self)
        if err:
            raise MessageError(err)


@register
@dataclass
class Points3D(Message):
    """Triangulated keypoints A..E in the ECM frame (m); NaN rows where a point is missing."""

    SCHEMA = "needletrack.Points3D"
    FIELDS = {"seq": ("int",), "stamp_ns": ("int",), "points_ecm": ("array", (5, 3), "nan"),
              "valid": ("array", (5,)), "epoch": ("int", "optional")}
    seq: int
    stamp_ns: int
    points_ecm: np.ndarray
    valid: np.ndarray
    epoch: Optional[int] = None

    def validate(self):
        pass


@register
@dataclass
class GroundTruth(Message):
    """Per-frame ground truth, with the dataset spec's optional per-frame fields."""

    SCHEMA = "needletrack.GroundTruth"
    FIELDS = {"seq": ("int",), "stamp_ns": ("int",), "sequence": ("int", "optional"),
              "step": ("int", "optional"), "ecm_joints": ("array", (4,), "optional"),
              "T_world_ecm": ("array", (4, 4), "optional"),
              "T_world_needle": ("array", (4, 4), "optional"),
              "keypoints": ("camera_map", (5, 2), "optional"), "visible": ("camera_map", (5,), "optional"),
              "bbox": ("camera_map", (4,), "optional"), "epoch": ("int", "optional")}
    seq: int
    stamp_ns: int
    sequence: Optional[int] = None
    step: Optional[int] = None
    ecm_joints: Optional[np.ndarray] = None
    T_world_ecm: Optional[np.ndarray] = None
    T_world_needle: Optional[np.ndarray] = None
    keypoints: Optional[dict] = None
    visible: Optional[dict] = None
    bbox: Optional[dict] = None
    epoch: Optional[int] = None

    def validate(self):
        for name in ("T_world_ecm", "T_world_needle"):
            _rigid(getattr(self, name), f"GroundTruth.{name}")

    @classmethod
    def from_frame(cls, frame, seq: int, stamp_ns: int) -> "GroundTruth | None":
        """The ground truth of a frame: a dataset's (``common.data.dataset.Frame``) or the
        simulator's (``common.sim.live.SimFrame``), anything with ``sequence``, ``step``,
        ``ecm_joints``, ``T_world_ecm``, ``T_world_needle`` and ``keypoints`` / ``visible`` /
        ``bbox`` by camera (each may be None). None when the frame has no truth at all."""
        kp, vis, bbox = frame.keypoints, frame.visible, frame.bbox
        if all(v is None for v in (frame.T_world_needle, kp, vis, bbox, frame.T_world_ecm)):
            return None
        q = frame.ecm_joints
        return cls(seq=seq, stamp_ns=stamp_ns, sequence=frame.sequence, step=frame.step,
                   ecm_joints=None if q is None else np.asarray(q, float),
                   T_world_ecm=frame.T_world_ecm, T_world_needle=frame.T_world_needle,
                   keypoints=None if kp is None else {c: np.asarray(kp[c], float) for c in CAMERAS},
                   visible=None if vis is None else {c: np.asarray(vis[c], bool) for c in CAMERAS},
                   bbox=None if bbox is None else {c: None if bbox[c] is None else np.asarray(bbox[c], float)
                                                   for c in CAMERAS})


@register
@dataclass
class Command(Message):
    """A request to a node (e.g. the sim's ``place_needle``); ``args`` is a plain map."""

    SCHEMA = "needletrack.Command"
    FIELDS = {"name": ("str",), "args": ("dict", "optional")}
    name: str
    args: Optional[dict] = None

    def validate(self):
        pass


@register
@dataclass
class NodeStats(Message):
    """A node's periodic statistics, published on its stats key. ``proc_ms_p50``/``p99``: handler
    times of the messages whose handler published (the frame's work; a sink: every message)."""

    SCHEMA = "needletrack.NodeStats"
    FIELDS = {"node": ("str",), "module": ("str",), "pid": ("int",), "stamp_ns": ("int",),
              "uptime_s": ("float",), "counters": ("dict",), "rates_hz": ("dict",),
              "proc_ms_p50": ("float",), "proc_ms_p99": ("float",)}
    node: str
    module: str
    pid: int
    stamp_ns: int
    uptime_s: float
    counters: dict
    rates_hz: dict
    proc_ms_p50: float
    proc_ms_p99: float

    def validate(self):
        pass


@register
@dataclass
class EndOfStream(Message):
    """Sent by a finite source (replay) after its last frame: ``frames`` were published."""

    SCHEMA = "needletrack.EndOfStream"
    FIELDS = {"frames": ("int",), "stamp_ns": ("int",)}
    frames: int
    stamp_ns: int

    def validate(self):
        pass


@register
@dataclass
class Calibration(Message):
    """What a camera source knows of its rig, published before its first frame and then once a
    second: ``cameras`` and ``image_size`` as in dataset.yaml, ``needle`` (radius_m,
    keypoint_angles_deg) and optionally ``ecm`` (T_world_base, L_rcc, L_scopelen)."""

    SCHEMA = "needletrack.Calibration"
    FIELDS = {"stamp_ns": ("int",), "image_size": ("array", (2,)), "cameras": ("dict",),
              "needle": ("dict",), "ecm": ("dict", "optional"), "source": ("str", "optional")}
    stamp_ns: int
    image_size: np.ndarray
    cameras: dict
    needle: dict
    ecm: Optional[dict] = None
    source: Optional[str] = None

    def validate(self):
        w, h = (float(x) for x in np.asarray(self.image_size, dtype=float))
        if not (1 <= w <= MAX_IMAGE_SIDE and 1 <= h <= MAX_IMAGE_SIDE and w == int(w) and h == int(h)):
            raise MessageError(f"Calibration.image_size: expected two whole numbers in 1..{MAX_IMAGE_SIDE}, "
                               f"got {self.image_size.tolist()}")
        for name in ("left", "right"):
            cam = self.cameras.get(name)
            if not isinstance(cam, dict):
                raise MessageError(f"Calibration.cameras.{name}: expected a map with K, T_ecm_cam")
            for key, shape in (("K", (3, 3)), ("T_ecm_cam", (4, 4)), ("dist", None)):
                if key == "dist" and cam.get(key) is None:
                    continue
                a = _finite_array(f"Calibration.cameras.{name}.{key}", cam.get(key), shape)
                if key == "dist" and len(a) not in (4, 5, 8, 12, 14):
                    raise MessageError(f"Calibration.cameras.{name}.dist: OpenCV takes 4, 5, 8, 12 or 14 "
                                       f"coefficients, got {len(a)}")
        _finite_array("Calibration.needle.radius_m", self.needle.get("radius_m", 0.01), ())
        if "keypoint_angles_deg" in self.needle:
            _finite_array("Calibration.needle.keypoint_angles_deg", self.needle["keypoint_angles_deg"], (5,))
        if self.ecm is not None:
            _finite_array("Calibration.ecm.T_world_base", self.ecm.get("T_world_base", np.eye(4)), (4, 4))
            for key in ("L_rcc", "L_scopelen"):
                _finite_array(f"Calibration.ecm.{key}", self.ecm.get(key, 0.0), ())
        # ranges, and what every consumer builds from it (rig, needle, arm), built once here
        for name in ("left", "right"):
            K = np.asarray(self.cameras[name]["K"], dtype=float)
            if not (K[0, 0] > 0 and K[1, 1] > 0 and K[1, 0] == 0 and (K[2] == (0.0, 0.0, 1.0)).all()):
                raise MessageError(f"Calibration.cameras.{name}.K: must be a pinhole matrix [[fx, s, cx], "
                                   f"[0, fy, cy], [0, 0, 1]] with positive focal lengths, got {K.tolist()}"[:300])
            _rigid(self.cameras[name]["T_ecm_cam"], f"Calibration.cameras.{name}.T_ecm_cam")
        r = float(np.asarray(self.needle.get("radius_m", 0.01), dtype=float))
        if not 0 < r < 1:
            raise MessageError(f"Calibration.needle.radius_m: must be in (0, 1) m, got {r:g}")
        if self.ecm is not None:
            _rigid(self.ecm.get("T_world_base", np.eye(4)), "Calibration.ecm.T_world_base")
            for key in ("L_rcc", "L_scopelen"):
                v = float(np.asarray(self.ecm.get(key, 0.0), dtype=float))
                if not abs(v) <= 10:
                    raise MessageError(f"Calibration.ecm.{key}: must be within 10 m, got {v:g}")
        # the rest of what consumers build from it (the runtime builds no geometry itself)
        if "wire_diameter_m" in self.needle:
            w = _finite_array("Calibration.needle.wire_diameter_m", self.needle["wire_diameter_m"], ())
            if not 0 < float(w) < 0.01:
                raise MessageError(f"Calibration.needle.wire_diameter_m: must be in (0, 0.01) m, got {float(w):g}")


def _finite_array(where: str, value, shape) -> np.ndarray:
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


MESSAGE_TYPES = dict(_REGISTRY)
