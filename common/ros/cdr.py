"""ROS message bytes <-> messages: the one place a ROS 1 or CDR (ROS 2) payload becomes a message
(bags, live ROS 2 on Zenoh, recordings), with ``rosbags``' typestores.

CDR as real ROS 2 writes it. rmw_fastrtps (ROS 2's default middleware, and so ``rclpy``'s
``serialize_message`` and ``ros2 bag record``) sizes a sample by its type support's
``get_serialized_size`` and sends that many bytes; the estimate aligns an empty sequence of 8-byte
numbers to 8 although the serializer writes no alignment for it. A ``sensor_msgs/JointState``
with positions only (empty velocity and effort) is therefore 8 bytes longer (124) than the CDR
it holds (116), the tail never written. ``rosbags`` refuses more than 3 bytes after a message's
end ("CDR message size mismatch"). ``decode`` accepts the tail exactly as far as a CDR writer
may leave one: up to the next 4-byte boundary (RTPS's end padding), or up to the size that
Fast-CDR's estimate (``fastcdr_estimate``) gives for the decoded message; a longer tail is
refused (``CdrError``), so garbage after a message is never taken silently.
"""
from __future__ import annotations

import struct

from rosbags.serde import SerdeError

from common.errors import NeedletrackError
from common.ros.types import normalise_type, typestore

# what rosbags' generated (de)serialisers raise on bytes that are not the type
_DECODE_ERRORS = (SerdeError, struct.error, UnicodeDecodeError, ValueError, IndexError, TypeError, KeyError,
                  AttributeError, OverflowError, MemoryError)
_SIZES = {"bool": 1, "int8": 1, "uint8": 1, "byte": 1, "char": 1, "int16": 2, "uint16": 2, "int32": 4,
          "uint32": 4, "float32": 4, "int64": 8, "uint64": 8, "float64": 8}


class CdrError(NeedletrackError, ValueError):
    """Bytes that are not a message of the type; the text says what is wrong."""


def _align(pos: int, size: int) -> int:
    """Fast-CDR's ``Cdr::alignment``: the padding that takes ``pos`` to a multiple of ``size``."""
    return (size - pos % size) & (size - 1)


def _estimate_value(store, node, value, pos: int) -> int:
    """``pos`` after ``value`` of field ``node`` in Fast-CDR's size estimate."""
    kind, desc = node
    k = int(kind)
    if k == 1:                                                # BASE
        name = desc[0]
        if name in ("string", "wstring"):
            n = len(value.encode("utf-8")) if name == "string" else 4 * len(value)
            return pos + 4 + _align(pos, 4) + n + (1 if name == "string" else 4)
        size = _SIZES[name]
        return pos + size + _align(pos, size)
    if k == 2:                                                # NAME: a nested message
        return _estimate_message(store, desc, value, pos)
    sub, _n = desc
    if k == 4:                                                # SEQUENCE: its length first
        pos += 4 + _align(pos, 4)
    if int(sub[0]) == 1 and sub[1][0] not in ("string", "wstring"):
        size = _SIZES[sub[1][0]]
        return pos + len(value) * size + _align(pos, size)   # aligned even when empty
    for item in value:
        pos = _estimate_value(store, sub, item, pos)
    return pos


def _estimate_message(store, typename: str, msg, pos: int) -> int:
    for name, node in store.fielddefs[typename][1]:
        pos = _estimate_value(store, node, getattr(msg, name), pos)
    return pos


def fastcdr_estimate(msg, msgtype: str, store=None) -> int:
    """Bytes after the encapsulation header that rmw_fastrtps sends for ``msg``
    (``get_serialized_size`` of rosidl_typesupport_fastrtps, from offset 0)."""
    store = store or typestore(2)
    return _estimate_message(store, normalise_type(msgtype), msg, 0)


def decode(data, msgtype: str, store=None, ros: int = 2):
    """The message of type ``msgtype`` in ``data``: CDR with its 4-byte encapsulation header
    (``ros=2``) or ROS 1 serialisation (``ros=1``), with ``store`` (default: the project's
    typestore of that ROS version). Raises ``CdrError`` naming the type and what is wrong."""
    msgtype = normalise_type(msgtype)
    store = store or typestore(ros)
    raw = memoryview(bytes(data)) if not isinstance(data, (bytes, memoryview)) else memoryview(data)
    try:
        msgdef = store.get_msgdef(msgtype)
    except Exception as exc:   # rosbags raises its own TypesysError for an unknown type
        raise CdrError(f"{msgtype}: unknown message type ({exc})") from None
    if ros == 1:
        try:
            msg, pos = msgdef.deserialize_ros1(raw, 0, msgdef.cls, store)
        except _DECODE_ERRORS as exc:
            raise CdrError(f"{msgtype}: not a ROS 1 message of this type ({len(raw)} bytes): {exc}") from None
        if pos != len(raw):
            raise CdrError(f"{msgtype}: {len(raw) - pos} bytes after the message's end ({len(raw)} bytes)")
        return msg
    if len(raw) < 4 or bytes(raw[:2]) not in (b"\x00\x00", b"\x00\x01"):
        raise CdrError(f"{msgtype}: not CDR: the encapsulation header is {bytes(raw[:4]).hex() or 'missing'} "
                       f"(plain CDR big or little endian: 0000 or 0001)")
    func = msgdef.deserialize_cdr_le if raw[1] else msgdef.deserialize_cdr_be
    body = raw[4:]
    try:
        msg, pos = func(body, 0, msgdef.cls, store)
    except _DECODE_ERRORS as exc:
        raise CdrError(f"{msgtype}: not a CDR message of this type ({len(raw)} bytes): "
                       f"{type(exc).__name__}: {exc}") from None
    if pos > len(body):
        raise CdrError(f"{msgtype}: truncated: the message needs {pos + 4} bytes, got {len(raw)}")
    tail = len(body) - pos
    if tail > 3:
        allowed = fastcdr_estimate(msg, msgtype, store)
        if len(body) > allowed + _align(allowed, 4):
            raise CdrError(f"{msgtype}: {tail} bytes after the message's end ({len(raw)} bytes; a writer "
                           f"pads to {max(allowed, pos + _align(pos, 4)) + 4} at most)")
    return msg


def encode(msg) -> bytes:
    """CDR bytes (with the encapsulation header) of a rosbags ROS 2 message."""
    return bytes(typestore(2).serialize_cdr(msg, msg.__msgtype__))
