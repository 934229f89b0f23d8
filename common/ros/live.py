"""ROS 2 over Zenoh without ROS: the key expressions, attachments and liveliness tokens of the two
ways ROS 2 data travels on Zenoh, with CDR payloads (de)serialised by ``rosbags``.

- ``bridge`` (zenoh-bridge-ros2dds): topic ``/a/b`` is the key ``a/b``, under the bridge's
  optional namespace (``ns/a/b``); the payload is the DDS sample's CDR bytes (with their 4-byte
  encapsulation header) and nothing else.
- ``rmw_zenoh`` (ROS 2's Zenoh middleware, rmw_zenoh_cpp): data on
  ``<domain_id>/<topic without its leading />/<type>/<type hash>``, the type mangled as
  ``geometry_msgs::msg::dds_::PoseStamped_`` and the hash ``RIHS01_<sha256 hex>`` (REP 2011) from
  Jazzy on, the constant ``TypeHashNotSupported`` on Humble (``distro``; a subscriber here
  matches any hash: ``*``); graph discovery by liveliness tokens
  ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS>/<enclave>/<namespace>/<node>
  [/<topic>/<type>/<hash>/<qos>]`` with ``/`` in names mangled to ``%`` and an empty name ``%``
  (the same form on every distribution, the hash aside); an entity's GID is the XXH3-128 of its
  token key (low 64 bits then high 64, little endian). Each sample carries an attachment in
  zenoh-ext serialisation (``attachment``): ``positional`` (rmw_zenoh 0.1.2+ on Humble, 0.2.4+
  on Jazzy, 0.6+ on Kilted and Rolling: int64 sequence number, int64 source timestamp in ns,
  the 16-byte GID as a sequence: 33 bytes) or ``keyed`` (0.1.0-0.1.1, 0.2.0-0.2.3, 0.3-0.5:
  each value after its name, ``"sequence_number"``, ``"source_timestamp"``, ``"source_gid"``:
  77 bytes). Checked against rmw_zenoh's sources (``attachment_helpers.cpp``,
  ``liveliness_utils.cpp``, ``rmw_publisher_data.cpp`` of each release).
"""
from __future__ import annotations

import struct

from common.ros.types import normalise_type, typestore

KEY_MODES = ("bridge", "rmw_zenoh")
DISTROS = ("humble", "jazzy", "kilted", "rolling")
ATTACHMENT_FORMS = ("positional", "keyed")
HUMBLE_TYPE_HASH = "TypeHashNotSupported"      # rmw_zenoh on Humble: no type hashes
GID_SIZE = 16
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


def check_distro(distro: str) -> str:
    if distro not in DISTROS:
        raise ValueError(f"distro must be one of {', '.join(DISTROS)}, got {distro!r}")
    return distro


def type_hash(msgtype: str, distro: str = "jazzy") -> str:
    """The type hash rmw_zenoh puts in keys and tokens: REP 2011's ``RIHS01_<hex>`` of the type,
    or ``TypeHashNotSupported`` on Humble."""
    if check_distro(distro) == "humble":
        return HUMBLE_TYPE_HASH
    return typestore(2).hash_rihs01(normalise_type(msgtype))


def topic_key(topic: str, msgtype: str | None, mode: str, domain_id: int = 0, namespace: str = "",
              wildcard_type: bool = False, distro: str = "jazzy") -> str:
    """The Zenoh key of ``topic`` in ``mode``; ``wildcard_type`` (rmw_zenoh, for subscribing)
    matches any type and hash: ``<domain>/<topic>/*/*``. Bridge keys are the same on every
    distribution."""
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
    return f"{int(domain_id)}/{name}/{dds_type_name(msgtype)}/{type_hash(msgtype, distro)}"


def distro_of_key(key: str) -> str | None:
    """``humble`` for an rmw_zenoh data key with Humble's type hash, ``jazzy`` (or later) for a
    REP 2011 hash, None for anything else."""
    last = key.rsplit("/", 1)[-1]
    if last == HUMBLE_TYPE_HASH:
        return "humble"
    return "jazzy" if last.startswith("RIHS01_") else None


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
                     msgtype: str | None = None, qos: str = DEFAULT_QOS, distro: str = "jazzy") -> str:
    """The liveliness key of a node (``NN``), publisher (``MP``) or subscription (``MS``)."""
    if kind not in ("NN", "MP", "MS"):
        raise ValueError(f"entity kind must be NN, MP or MS, got {kind!r}")
    key = (f"{LIVELINESS_PREFIX}/{int(domain_id)}/{zid}/{int(node_id)}/{int(entity_id)}/{kind}/"
           f"{mangle(enclave)}/{mangle(namespace)}/{node_name}")
    if kind != "NN":
        key += f"/{mangle(topic)}/{dds_type_name(msgtype)}/{type_hash(msgtype, distro)}/{qos}"
    return key


def entity_gid(token_key: str) -> bytes:
    """rmw_zenoh's GID of the entity whose liveliness key is ``token_key``: XXH3-128 of the key,
    the low 64 bits then the high 64, each little endian (``liveliness_utils.cpp``)."""
    import xxhash
    h = xxhash.xxh3_128_intdigest(token_key.encode("utf-8"))
    return (h & 0xFFFF_FFFF_FFFF_FFFF).to_bytes(8, "little") + (h >> 64).to_bytes(8, "little")


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


def attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes, form: str = "positional") -> bytes:
    """rmw_zenoh's per-sample attachment in ``form`` (``positional``: 33 bytes; ``keyed``: 77)."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"gid must be {GID_SIZE} bytes, got {len(gid)}")
    if form not in ATTACHMENT_FORMS:
        raise ValueError(f"attachment must be one of {', '.join(ATTACHMENT_FORMS)}, got {form!r}")
    seq, ts = struct.pack("<q", sequence_number), struct.pack("<q", source_timestamp_ns)
    gid_seq = _leb128(GID_SIZE) + bytes(gid)
    if form == "positional":
        return seq + ts + gid_seq
    out = bytearray()
    for key, val in ((b"sequence_number", seq), (b"source_timestamp", ts), (b"source_gid", gid_seq)):
        out += _leb128(len(key)) + key + val
    return bytes(out)


def parse_attachment(data: bytes) -> dict:
    """The fields of an rmw_zenoh attachment in either form (``form`` says which); ValueError
    when it is neither."""
    data = bytes(data)
    if len(data) == 33 and data[16] == GID_SIZE:
        seq, ts = struct.unpack_from("<qq", data)
        return {"form": "positional", "sequence_number": seq, "source_timestamp": ts, "source_gid": data[17:]}
    out, p = {"form": "keyed"}, 0
    for key, kind in (("sequence_number", "q"), ("source_timestamp", "q"), ("source_gid", "b")):
        n, p = _read_leb128(data, p)
        if data[p:p + n].decode("utf-8", "replace") != key:
            raise ValueError(f"attachment: neither rmw_zenoh form ({len(data)} bytes; expected 33, or the key {key!r})")
        p += n
        if kind == "q":
            if p + 8 > len(data):
                raise ValueError("attachment: truncated")
            out[key] = struct.unpack_from("<q", data, p)[0]
            p += 8
        else:
            n, p = _read_leb128(data, p)
            if n != GID_SIZE or p + n != len(data):
                raise ValueError(f"attachment: source_gid of {n} bytes, {len(data) - p - n} bytes left over")
            out[key] = data[p:p + n]
            p += n
    return out
