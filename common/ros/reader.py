"""Reading one bag's messages in order, for ``BagStereo`` (``common/ros/bag.py``): rosbags'
ROS 1 and ROS 2 readers, with

- types resolved per topic: a topic whose type the bag cannot define (a definition that does not
  parse, a dependency it lacks, a hash that does not match) is listed in ``unresolved`` with why,
  and only a topic the conversion uses makes the bag unreadable (rosbags' ``AnyReader`` refuses
  the whole bag, naming no topic);
- reader errors while iterating (a truncated record, a corrupt chunk, a CRC mismatch, an absurd
  length) raised as ``BagError`` naming the file and the position (messages read, the last
  topic and log time);
- an unfinished MCAP file (no summary and footer: a recorder killed, a full disk) read up to its
  last complete chunk with the ``mcap`` library's streaming reader (``UnfinishedMcap``);
  ``recovered`` says how much.

Readers expose ``connections`` (``.topic``, ``.msgtype``, ``.msgcount``), ``messages(connections)``
yielding ``(connection, log_time_ns, raw)``, ``deserialize(raw, msgtype)`` and ``close()``.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from common.ros.bag import BagError

MCAP_MAGIC = b"\x89MCAP0\r\n"
MAX_CHUNK_BYTES = 2 << 30      # an unfinished file's chunk claiming more is corrupt (chunks are ~1 MB)


def _types(defs, default):
    """A typestore of ``defs`` ([(topic, msgtype, format 'msg'|'idl'|None, text, digest, hash_of)]),
    types the bag does not define taken from ``default``; returns (store, {topic: why})."""
    from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
    typs, bad, digests = {}, {}, {}
    for topic, msgtype, fmt, text, digest, _ in defs:
        if fmt is None:
            continue
        try:
            if fmt == "msg":
                typs.update(get_types_from_msg(text, msgtype))
            else:
                sep = "=" * 80 + "\n"
                for part in (text.split(sep)[1:] if text.startswith(f"{sep}IDL: ") else [text]):
                    typs.update(get_types_from_idl(part.split("\n", 1)[1] if part.startswith("IDL: ") else part))
        except Exception as exc:
            bad[topic] = f"its definition of {msgtype} does not parse: {exc}"
            continue
        if digest:
            digests.setdefault(msgtype, []).append((topic, digest))
    for name, fields in default.fielddefs.items():
        typs.setdefault(name, fields)
    store = get_typestore(Stores.EMPTY)
    store.register(typs)
    for topic, msgtype, *_, hash_of in defs:
        if topic in bad:
            continue
        try:
            have = hash_of(store, msgtype)
        except Exception as exc:       # a field of a type neither the bag nor the default store defines
            bad[topic] = f"type {msgtype} cannot be resolved: {exc}"
            continue
        for t, digest in digests.get(msgtype, ()):
            if t == topic and have and digest != have:
                bad[topic] = f"type {msgtype}: the bag's hash {digest} does not match its definition's {have}"
    return store, bad


def _ros1_hash(store, msgtype):
    return store.generate_msgdef(msgtype)[1]


def _ros2_hash(store, msgtype):
    return store.hash_rihs01(msgtype)


class _Positioned:
    """Iteration with reader errors raised as BagError naming the file and the position."""

    def _iterate(self, source):
        n, last = 0, None
        try:
            for conn, t, raw in source:
                n, last = n + 1, (conn.topic, t)
                yield conn, t, raw
        except BagError:
            raise
        except Exception as exc:    # rosbags, mcap, zstd/lz4, struct and OS errors alike
            where = (f"after {n} messages (the last on {last[0]}, log time {last[1] / 1e9:.6f} s)" if last
                     else "before its first message")
            raise BagError(f"{self.path}: unreadable {where}: {type(exc).__name__}: {exc}") from None


class BagReader(_Positioned):
    """A ROS 1 ``.bag``, or a ROS 2 bag folder or ``.db3``/``.mcap`` file, read with rosbags."""

    def __init__(self, path):
        from rosbags.interfaces import MessageDefinitionFormat as F
        from rosbags.rosbag1 import Reader as Reader1
        from rosbags.rosbag2 import Reader as Reader2

        from common.ros.types import typestore
        self.path = Path(path)
        self.is2 = self.path.suffix != ".bag"
        self.recovered = None
        self.reader = (Reader2 if self.is2 else Reader1)(self.path)
        self.reader.open()
        try:
            self.connections = list(self.reader.connections)
            fmt = {F.MSG: "msg", F.IDL: "idl"}
            hash_of = _ros2_hash if self.is2 else _ros1_hash
            defs = [(c.topic, c.msgtype, fmt.get(c.msgdef.format), c.msgdef.data, c.digest, hash_of)
                    for c in self.connections]
            self.store, self.unresolved = _types(defs, typestore(2 if self.is2 else 1))
        except BaseException:
            self.reader.close()
            raise

    def messages(self, connections=()):
        return self._iterate(self.reader.messages(connections=list(connections)))

    def deserialize(self, raw, msgtype: str):
        """The message in ``raw`` with the bag's types (``common.ros.cdr.decode``: CDR with the
        padding real ROS 2 writes, or ROS 1); ``CdrError`` when it is not one."""
        from common.ros.cdr import decode
        return decode(raw, msgtype, self.store, 2 if self.is2 else 1)

    def close(self) -> None:
        self.reader.close()


@dataclass(frozen=True)
class McapConnection:
    """A channel of an unfinished MCAP file (the fields BagStereo reads of a rosbags Connection)."""

    id: int
    topic: str
    msgtype: str
    msgcount: int


def is_mcap(path) -> bool:
    """Whether ``path`` is a file that starts with the MCAP magic."""
    p = Path(path)
    if not p.is_file():
        return False
    with open(p, "rb") as f:
        return f.read(8) == MCAP_MAGIC


def is_unfinished_mcap(path) -> bool:
    """Whether ``path`` is an MCAP file that does not end in the MCAP magic (no footer)."""
    p = Path(path)
    if not p.is_file():
        return False
    with open(p, "rb") as f:
        if f.read(8) != MCAP_MAGIC:
            return False
        if p.stat().st_size < 16:
            return True
        f.seek(-8, os.SEEK_END)
        return f.read(8) != MCAP_MAGIC


class UnfinishedMcap(_Positioned):
    """An MCAP file without its summary and footer, read up to its last complete chunk (and any
    messages outside chunks before it): the records are streamed with ``mcap``'s
    ``StreamReader``; a chunk whose CRC or decompression fails, a truncated record or the end of
    the file ends the readable part. ``recovered`` says how many messages that gave."""

    def __init__(self, path, why: str = "an unfinished recording"):
        from common.ros.types import typestore
        self.path = Path(path)
        self.size = self.path.stat().st_size
        self.schemas, self.channels, self.counts = {}, {}, {}
        self.stop = None
        self.n_messages = sum(1 for _ in self._records(count=True))
        chunks, total = self._chunks, self.n_messages
        if total == 0:
            raise BagError(f"{self.path}: {why} with no complete chunk: nothing to recover ({self.stop})")
        self.recovered = (f"recovered {total} messages from the {chunks} complete chunks of {why} "
                          f"(no summary or footer; after them: {self.stop})")
        self.connections = []
        defs = []
        for cid, ch in self.channels.items():
            sch = self.schemas.get(ch.schema_id)
            name = sch.name if sch is not None else ""
            self.connections.append(McapConnection(cid, ch.topic, name, self.counts.get(cid, 0)))
            enc = getattr(sch, "encoding", "")
            fmt = {"ros2msg": "msg", "ros2idl": "idl"}.get(enc)
            defs.append((ch.topic, name, fmt, sch.data.decode(errors="replace") if fmt else "", "", _ros2_hash))
        self.store, self.unresolved = _types(defs, typestore(2))

    def _records(self, count: bool = False):
        """Messages (as (channel id, log time, data)) of the readable part, in file order; sets
        ``self.stop`` to why reading ended (``count``: the first pass, counting per channel)."""
        from mcap.exceptions import EndOfFile, RecordLengthLimitExceeded
        from mcap.records import Channel, Chunk, DataEnd, Footer, Message, Schema
        from mcap.stream_reader import StreamReader, breakup_chunk
        self._chunks = 0
        with open(self.path, "rb") as f:
            reader = StreamReader(f, emit_chunks=True, record_size_limit=self.size)
            it = reader.records
            while True:
                at = f.tell()
                try:
                    rec = next(it)
                except StopIteration:
                    self.stop = "the end of the file"
                    return
                except EndOfFile:
                    self.stop = ("the file ends there" if at >= self.size else
                                 f"a record cut short at byte {at} of {self.size}")
                    return
                except RecordLengthLimitExceeded as exc:
                    self.stop = f"a record at byte {at} runs past the end of the file ({self.size} bytes): {exc}"
                    return
                except Exception as exc:   # bad bytes
                    self.stop = f"{type(exc).__name__} {exc}".strip() + f" at byte {at} of {self.size}"
                    return
                inner = [rec]
                if isinstance(rec, Chunk):
                    if rec.uncompressed_size > MAX_CHUNK_BYTES:
                        self.stop = (f"chunk {self._chunks + 1} claims {rec.uncompressed_size} bytes uncompressed "
                                     f"(at most {MAX_CHUNK_BYTES} read)")
                        return
                    try:
                        inner = breakup_chunk(rec, validate_crc=True)
                    except Exception as exc:
                        self.stop = f"chunk {self._chunks + 1} unreadable: {type(exc).__name__}: {exc}"
                        return
                    self._chunks += 1
                for r in inner:
                    if isinstance(r, Schema):
                        self.schemas[r.id] = r
                    elif isinstance(r, Channel):
                        self.channels[r.id] = r
                    elif isinstance(r, Message):
                        if r.channel_id in self.channels:
                            if count:
                                self.counts[r.channel_id] = self.counts.get(r.channel_id, 0) + 1
                            yield r.channel_id, r.log_time, r.data
                    elif isinstance(r, (DataEnd, Footer)):
                        self.stop = "its data end"
                        return

    def messages(self, connections=()):
        want = {c.id: c for c in connections} if connections else {c.id: c for c in self.connections}

        def gen():       # a file still growing (a recording in progress) is read as far as the first pass
            for i, (cid, t, data) in enumerate(self._records()):
                if i >= self.n_messages:
                    break
                if cid in want:
                    yield want[cid], t, data
        return self._iterate(gen())

    def deserialize(self, raw, msgtype: str):
        from common.ros.cdr import decode
        return decode(raw, msgtype, self.store)

    def close(self) -> None:
        pass
