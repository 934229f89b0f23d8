"""The messages' msgpack codec (no pickle): ``{"schema": NAME, "version": V, "body": {...}}``,
numpy arrays as a msgpack extension (dtype, shape, raw bytes) that round-trips exactly, a large
bytes field (an image) as the payload's tail, handed out by ``decode`` as a view. ``decode``
validates the schema, version and every field (``common.runtime.checks``). The message types
register themselves (``register``) in ``common.runtime.messages``.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import msgpack
import msgspec
import numpy as np

from common.runtime.checks import MessageError
from common.runtime.schema import dec_hook, fields_of, refusal, wire_struct

_EXT_NDARRAY = 1
_DTYPES = {"bool", "uint8", "uint16", "int32", "int64", "float32", "float64"}


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
    dtype, ndim, p = bytes(data[2:p]).decode("ascii", "replace"), data[p] & 0x0f, p + 1
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


class Message:
    """Base of all messages: a dataclass with a schema name and a version, whose annotations
    declare the fields and their constraints (``common.runtime.schema``)."""

    SCHEMA: str = ""
    VERSION: int = 1

    def to_body(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}


_REGISTRY: dict[str, type] = {}
_BODY_DECODERS: dict[type, msgspec.msgpack.Decoder] = {}


def register(cls):
    """Register a message type: its schema name, and the decoder of its body (its fields)."""
    _REGISTRY[cls.SCHEMA] = cls
    _BODY_DECODERS[cls] = msgspec.msgpack.Decoder(wire_struct(cls), dec_hook=dec_hook, ext_hook=_ext_hook)
    return cls


def registered_types() -> dict[str, type]:
    """Every registered message type by its schema name (a copy)."""
    return dict(_REGISTRY)


class _Envelope(msgspec.Struct):
    schema: Any = msgspec.UNSET
    version: Any = None
    body: msgspec.Raw = msgspec.UNSET


_ENVELOPE = msgspec.msgpack.Decoder(_Envelope)


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


def _not_msgpack(what: str, exc: Exception) -> MessageError:
    return MessageError(f"{what}: not valid msgpack ({type(exc).__name__}: {exc})")


def decode(payload, expect: type | None = None) -> Message:
    """msgpack bytes -> validated Message. ``expect`` restricts the accepted message type."""
    buf = payload if isinstance(payload, bytes) else bytes(payload)
    try:
        cls, body = _decode_body(buf, expect)
    except MessageError as exc:
        raise _first_error(buf, expect, exc) from None
    msg = object.__new__(cls)
    msg.__dict__.update(msgspec.structs.asdict(body))
    try:
        msg.validate()
    except MessageError:
        raise
    except Exception as exc:   # a validate() that trips on a value it did not foresee
        raise MessageError(f"{cls.__name__}: invalid ({type(exc).__name__}: {exc})") from None
    return msg


def _decode_body(buf: bytes, expect):
    """``(message type, its body as a Struct of its fields)``: the envelope, then the body
    converted strictly to the fields the type declares."""
    what = expect.__name__ if expect else "message"
    try:
        env = _ENVELOPE.decode(buf)
    except msgspec.ValidationError:
        raise MessageError(f"{what}: missing schema envelope") from None
    except Exception as exc:
        raise _not_msgpack(what, exc) from None
    if env.schema is msgspec.UNSET or env.body is msgspec.UNSET:
        raise MessageError(f"{what}: missing schema envelope")
    cls = _REGISTRY.get(env.schema) if isinstance(env.schema, str) else None
    if cls is None:
        raise MessageError(f"message: unknown schema {env.schema!r}")
    if expect is not None and cls is not expect:
        raise MessageError(f"{expect.__name__}: got a {cls.__name__} instead")
    if env.version != cls.VERSION:
        raise MessageError(f"{cls.__name__}.version: expected {cls.VERSION}, got {env.version!r}")
    try:
        return cls, _BODY_DECODERS[cls].decode(env.body)
    except MessageError:
        raise
    except msgspec.ValidationError:
        raise MessageError(_refusal(cls, env.body)) from None
    except Exception as exc:
        raise _not_msgpack(cls.__name__, exc) from None


def _first_error(buf: bytes, expect, exc: MessageError) -> MessageError:
    """What is wrong with a refused payload first: not msgpack at all (anywhere in it, an ndarray
    extension included), else ``exc``."""
    try:
        msgspec.msgpack.decode(buf, ext_hook=_ext_hook)
    except MessageError as first:
        return first
    except Exception as first:
        return _not_msgpack(expect.__name__ if expect else "message", first)
    return exc


def _refusal(cls, raw) -> str:
    """Why ``cls``'s decoder refused the body ``raw``, placed as ``Type.field: why``."""
    try:
        body = msgspec.msgpack.decode(raw, ext_hook=_ext_hook)
    except MessageError as exc:
        return str(exc)
    except Exception as exc:
        return str(_not_msgpack(cls.__name__, exc))
    return refusal(cls.__name__, fields_of(cls), body)
