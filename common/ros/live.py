"""ROS 2 over Zenoh without ROS: the key expressions, attachments and liveliness tokens of the two
ways ROS 2 data travels on Zenoh, with CDR payloads (de)serialised by ``rosbags``.

- ``bridge`` (zenoh-bridge-ros2dds): topic ``/a/b`` is the key ``a/b``, under the bridge's
  optional namespace (``ns/a/b``); the payload is the DDS sample's CDR bytes (with their 4-byte
  encapsulation header) and nothing else.
- ``rmw_zenoh`` (ROS 2's Zenoh middleware, rmw_zenoh_cpp as released for Jazzy): data on
  ``<domain_id>/<topic without its leading />/<type>/<type hash>``, the type mangled as
  ``geometry_msgs::msg::dds_::PoseStamped_`` and the hash ``RIHS01_<sha256 hex>`` (REP 2011; a
  subscriber here matches any hash: ``*``); each sample carries an attachment (zenoh-ext
  serialisation of ``"sequence_number"`` int64, ``"source_timestamp"`` int64 ns,
  ``"source_gid"`` 16 bytes); graph discovery by liveliness tokens
  ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS>/<enclave>/<namespace>/<node>
  [/<topic>/<type>/<hash>/<qos>]`` with ``/`` in names mangled to ``%`` and an empty name ``%``.
"""
from __future__ import annotations

import struct

from common.ros.types import normalise_type, typestore

KEY_MODES = ("bridge", "rmw_zenoh")
LIVELINESS_PREFIX = "@ros2_lv"
DEFAULT_QOS = "::,10:,:,:,,"      # rmw_zenoh's key form of the default QoS (reliable, volatile, keep last 10)


def dds_type_name(msgtype: str) -> str:
    """``geometry_msgs/msg/PoseStamped`` -> ``geometry_msgs::msg::dds_::PoseStamped_``."""
    pkg, kind, name = normalise_type(msgtype).split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def msgtype_of_dds(name: str) -> str:
    """The inverse of ``dds_type_name``."""
    parts = name.split("::")
    if len(parts) != 4 or parts[2] != "dds_" or not parts[3].endswith("_"):
        raise ValueError(f"not a ROS 2 DDS type name: {name!r}")
    return f"{parts[0]}/{parts[1]}/{parts[3][:-1]}"


def type_hash(msgtype: str) -> str:
    """REP 2011 type hash ``RIHS01_<hex>`` of a ROS 2 message type."""
    return typestore(2).hash_rihs01(normalise_type(msgtype))


def topic_key(topic: str, msgtype: str | None, mode: str, domain_id: int = 0, namespace: str = "",
              wildcard_type: bool = False) -> str:
    """The Zenoh key of ``topic`` in ``mode``; ``wildcard_type`` (rmw_zenoh, for subscribing)
    matches any type and hash: ``<domain>/<topic>/*/*``."""
    name = topic.strip("/")
    if not name:
        raise ValueError(f"bad topic name {topic!r}")
    if mode == "bridge":
        ns = namespace.strip("/")
        return f"{ns}/{name}" if ns else name
    if mode != "rmw_zenoh":
        raise ValueError(f"keys must be one of {', '.join(KEY_MODES)}, got {mode!r}")
    if wildcard_type:
        return f"{int(domain_id)}/{name}/*/*"
    return f"{int(domain_id)}/{name}/{dds_type_name(msgtype)}/{type_hash(msgtype)}"


def topic_of_key(key: str, mode: str, namespace: str = "") -> tuple[str, str | None]:
    """(ROS topic, msgtype or None) of a received sample's key."""
    if mode == "bridge":
        ns = namespace.strip("/")
        if ns and key.startswith(ns + "/"):
            key = key[len(ns) + 1:]
        return "/" + key, None
    parts = key.split("/")
    if len(parts) < 4:
        raise ValueError(f"not an rmw_zenoh data key: {key!r}")
    try:
        msgtype = msgtype_of_dds(parts[-2])
    except ValueError:
        msgtype = None
    return "/" + "/".join(parts[1:-2]), msgtype


def mangle(name: str) -> str:
    """rmw_zenoh's name mangling: ``/`` -> ``%``; empty -> ``%``."""
    return name.replace("/", "%") if name and name != "/" else "%"


def liveliness_token(kind: str, zid: str, node_name: str, *, domain_id: int = 0, namespace: str = "/",
                     enclave: str = "/", node_id: int = 0, entity_id: int = 0, topic: str | None = None,
                     msgtype: str | None = None, qos: str = DEFAULT_QOS) -> str:
    """The liveliness key of a node (``NN``), publisher (``MP``) or subscription (``MS``)."""
    if kind not in ("NN", "MP", "MS"):
        raise ValueError(f"entity kind must be NN, MP or MS, got {kind!r}")
    key = (f"{LIVELINESS_PREFIX}/{int(domain_id)}/{zid}/{int(node_id)}/{int(entity_id)}/{kind}/"
           f"{mangle(enclave)}/{mangle(namespace)}/{node_name}")
    if kind != "NN":
        key += f"/{mangle(topic)}/{dds_type_name(msgtype)}/{type_hash(msgtype)}/{qos}"
    return key


# ---------------------------------------------------------------- attachments (zenoh-ext serialisation)

def _leb128(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def _read_leb128(data: bytes, p: int) -> tuple[int, int]:
    n = shift = 0
    while True:
        if p >= len(data):
            raise ValueError("attachment: truncated length")
        b = data[p]
        p += 1
        n |= (b & 0x7F) << shift
        shift += 7
        if not b & 0x80:
            return n, p


def attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's per-sample attachment."""
    if len(gid) != 16:
        raise ValueError("gid must be 16 bytes")
    out = bytearray()
    for key, val in (("sequence_number", struct.pack("<q", sequence_number)),
                     ("source_timestamp", struct.pack("<q", source_timestamp_ns))):
        k = key.encode()
        out += _leb128(len(k)) + k + val
    k = b"source_gid"
    out += _leb128(len(k)) + k + _leb128(16) + bytes(gid)
    return bytes(out)


def parse_attachment(data: bytes) -> dict:
    """The fields of an rmw_zenoh attachment; ValueError when it is not one."""
    out, p = {}, 0
    for key, kind in (("sequence_number", "q"), ("source_timestamp", "q"), ("source_gid", "b")):
        n, p = _read_leb128(data, p)
        if data[p:p + n].decode("utf-8", "replace") != key:
            raise ValueError(f"attachment: expected key {key!r}")
        p += n
        if kind == "q":
            out[key] = struct.unpack_from("<q", data, p)[0]
            p += 8
        else:
            n, p = _read_leb128(data, p)
            out[key] = bytes(data[p:p + n])
            p += n
    return out
