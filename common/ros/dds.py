"""ROS 2 on its default middleware, DDS, spoken directly with Eclipse Cyclone DDS's Python binding
(``cyclonedds``): no ROS installation, no bridge.

What ROS 2 puts on DDS (its rmw layer, rmw_fastrtps_cpp or rmw_cyclonedds_cpp):

- topic ``/a/b`` is the DDS topic ``rt/a/b``; the DDS type name of ``pkg/msg/Type`` is
  ``pkg::msg::dds_::Type_`` (``common.ros.live.dds_type_name``), and every nested type too;
- a sample is the message's plain CDR (XCDR1, little endian: encapsulation ``00 01 00 00``), the
  same bytes as in a ROS 2 bag; a ROS 2 (Fast DDS) writer may append up to 7 bytes of
  alignment slack after the last field (e.g. a JointState with empty ``velocity``/``effort``);
- QoS: what rclpy calls the default profile is reliable, volatile, keep last 10 (a driver may
  publish images with the sensor-data profile: best effort, keep last 5).

One codec path: the samples travel as raw CDR bytes, encoded and decoded by the project's CDR
code (``common.ros.cdr.encode``/``decode``, rosbags), so a DDS sample gets the same decoding and
checks as a Zenoh one. ``cyclonedds`` only carries them; the Cyclone IDL type of each message
(built here from the same rosbags type definitions) gives the DDS topic its type name and
XTypes type information.

Reading subscribes best effort (matches reliable and best-effort publishers alike), volatile,
keep last ``depth``; writing is the ROS default (reliable, volatile, keep last 10), which a
subscriber of either reliability matches. Discovery is Cyclone's: SPDP multicast on the chosen
interface unless ``config`` (Cyclone XML, or ``CYCLONEDDS_URI``) says otherwise (docs/ros.md).
"""
from __future__ import annotations

import threading
from functools import lru_cache

from common.errors import NeedletrackError
from common.ros.live import dds_type_name, type_hash
from common.ros.types import normalise_type, typestore

DEFAULT_DEPTH = 10          # rclpy's default history depth
# Cyclone's defaults send 1344-byte fragments and ask the OS for a 1 MB receive buffer: a 1080p
# image (6.2 MB) is then ~4600 fragments and best effort loses nearly every one. These fit
# Fast DDS's defaults (64 KB datagrams) and ask for 8 MB (the OS caps it: net.core.rmem_max).
# The user's config (``config``, or CYCLONEDDS_URI) comes after and overrides.
TUNING = ("<CycloneDDS><Domain><General><MaxMessageSize>65500B</MaxMessageSize>"
          "<FragmentSize>62000B</FragmentSize></General>"
          "<Internal><SocketReceiveBufferSize max=\"8MB\"/></Internal></Domain></CycloneDDS>")


def dds_topic_name(topic: str) -> str:
    """ROS 2 topic ``/a/b`` -> DDS topic ``rt/a/b``."""
    name = topic.strip("/")
    if not name or "//" in name:
        raise ValueError(f"bad ROS topic name {topic!r}")
    return "rt/" + name


class DdsError(NeedletrackError, RuntimeError):
    """A DDS entity could not be made (bad config, no such type)."""


def _base_type(name: str):
    from cyclonedds.idl import types as t
    table = {"bool": bool, "byte": t.byte, "char": t.uint8, "int8": t.int8, "uint8": t.uint8,
             "int16": t.int16, "uint16": t.uint16, "int32": t.int32, "uint32": t.uint32,
             "int64": t.int64, "uint64": t.uint64, "float32": t.float32, "float64": t.float64,
             "string": str}
    if name not in table:
        raise DdsError(f"no DDS type for the ROS base type {name!r}")
    return table[name]


def _field_type(node):
    from cyclonedds.idl import types as t
    kind, desc = node
    k = int(kind)
    if k == 1:                                   # BASE (name, string bound)
        name, bound = desc
        if name == "string" and bound:
            return t.bounded_str[bound]
        return _base_type(name)
    if k == 2:                                   # NAME: a nested message
        return idl_type(desc)
    sub, n = desc
    if k == 3:                                   # ARRAY (fixed length)
        return t.array[_field_type(sub), n]
    return t.sequence[_field_type(sub), n] if n else t.sequence[_field_type(sub)]   # SEQUENCE


def _raw_serialize(self, *args, **kwargs) -> bytes:
    return self.cdr


def _raw_deserialize(cls, data, *args, **kwargs):
    obj = object.__new__(cls)
    obj.cdr = bytes(data)
    return obj


@lru_cache(maxsize=None)
def idl_type(msgtype: str, raw: bool = False):
    """The Cyclone IDL struct of ROS 2 message type ``msgtype`` (type name
    ``pkg::msg::dds_::Type_``, fields as the rosbags definition, final extensibility, as rmw
    writes it). ``raw``: the same type whose samples are their CDR bytes (``sample.cdr``, with
    the 4-byte encapsulation header): cyclonedds's own (de)serialisation is bypassed."""
    from cyclonedds.idl import make_idl_struct
    name = normalise_type(msgtype)
    st = typestore(2)
    if name not in st.fielddefs:
        raise DdsError(f"unknown ROS 2 message type {msgtype!r}")
    fields = {fname: _field_type(node) for fname, node in st.fielddefs[name][1]}
    cls_name = name.replace("/", "_") + ("_raw" if raw else "")
    cls = make_idl_struct(cls_name, dds_type_name(name), fields)
    if raw:
        cls.serialize = _raw_serialize
        cls.deserialize = classmethod(_raw_deserialize)
    return cls


def reader_qos(depth: int = DEFAULT_DEPTH, reliable: bool = False):
    """Best effort, volatile, keep last ``depth``: matches every ROS 2 publisher. ``reliable``:
    matches reliable publishers only (ROS's default profile), and their lost fragments are sent
    again (a large image over best effort is lost with any one of its fragments)."""
    from cyclonedds.qos import Policy, Qos
    from cyclonedds.util import duration
    rel = Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100)) if reliable else \
        Policy.Reliability.BestEffort
    return Qos(rel, Policy.Durability.Volatile, Policy.History.KeepLast(max(1, depth)),
               Policy.DataRepresentation(use_cdrv0_representation=True))


def writer_qos(msgtype: str, depth: int = DEFAULT_DEPTH):
    """ROS 2's default profile (reliable, volatile, keep last ``depth``), and the type hash in
    USER_DATA as rmw writes it (``typehash=RIHS01_...;``) for ``ros2 topic info -v``."""
    from cyclonedds.qos import Policy, Qos
    from cyclonedds.util import duration
    return Qos(Policy.Reliability.Reliable(max_blocking_time=duration(milliseconds=100)),
               Policy.Durability.Volatile, Policy.History.KeepLast(max(1, depth)),
               Policy.DataRepresentation(use_cdrv0_representation=True),
               Policy.Userdata(data=f"typehash={type_hash(msgtype)};".encode()))


class DdsLink:
    """One DDS domain participant for a node: ``subscribe`` and ``publisher`` on ROS 2 topics,
    CDR bytes in and out. ``config``: Cyclone XML text or a file URI (else ``CYCLONEDDS_URI``),
    applied over ``TUNING``."""

    def __init__(self, domain_id: int = 0, config: str | None = None):
        import os

        from cyclonedds.domain import Domain, DomainParticipant
        self.domain_id = int(domain_id)
        user = config or os.environ.get("CYCLONEDDS_URI", "")
        try:
            self.domain = Domain(self.domain_id, TUNING + ("," + user if user else ""))
            self.participant = DomainParticipant(self.domain_id)
        except Exception as exc:           # cyclonedds raises DDSException for a bad config
            where = f" with config {user[:200]!r}" if user else ""
            raise DdsError(f"cannot join DDS domain {self.domain_id}{where}: {exc} (Cyclone's reason is in "
                           "its log line before this)") from None
        self._entities: list = []
        self._readers: list = []
        self._lock = threading.Lock()
        self._waitset = None
        self._closing = threading.Event()
        self.callback_errors = 0            # exceptions raised by subscribe callbacks (last_error: the newest)
        self.last_error = ""

    def _topic(self, topic: str, msgtype: str):
        from cyclonedds.topic import Topic
        return Topic(self.participant, dds_topic_name(topic), idl_type(normalise_type(msgtype), raw=True))

    def subscribe(self, topic: str, msgtype: str, callback, depth: int = DEFAULT_DEPTH, reliable: bool = False):
        """Call ``callback(cdr_bytes, source_timestamp_ns)`` for each sample of ``topic``
        (``reliable``: see ``reader_qos``), on this link's reading thread: Cyclone's receive
        thread only queues the samples (``depth`` per topic), it never waits for Python."""
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState
        from cyclonedds.sub import DataReader
        reader = DataReader(self.participant, self._topic(topic, msgtype), qos=reader_qos(depth, reliable))
        cond = ReadCondition(reader, SampleState.Any | ViewState.Any | InstanceState.Any)
        with self._lock:
            if self._waitset is None:
                self._start_reading()
            self._waitset.attach(cond)
            self._readers.append((reader, cond, callback))
        self._entities += [reader, cond]
        return reader

    def _start_reading(self) -> None:
        from cyclonedds.core import GuardCondition, WaitSet
        self._waitset = WaitSet(self.participant)
        self._wake = GuardCondition(self.participant)
        self._waitset.attach(self._wake)
        self._thread = threading.Thread(target=self._read_loop, name="dds-read", daemon=True)
        self._thread.start()

    def _read_loop(self) -> None:
        from cyclonedds.core import DDSException
        try:
            self._read_until_closed()
        except DDSException as exc:          # the entities went (process exit) or a take failed
            if not self._closing.is_set():
                self.last_error = f"reading stopped: {exc}"

    def _read_until_closed(self) -> None:
        from cyclonedds.util import duration
        while not self._closing.is_set():
            self._waitset.wait(duration(milliseconds=200))     # releases the GIL (ctypes)
            if self._closing.is_set():
                return
            with self._lock:
                readers = list(self._readers)
            for reader, _cond, callback in readers:
                while not self._closing.is_set():
                    samples = reader.take(N=16)
                    if not samples:
                        break
                    for s in samples:
                        info = getattr(s, "sample_info", None)
                        if info is None or not info.valid_data:
                            continue
                        try:
                            callback(s.cdr, int(info.source_timestamp))
                        except Exception as exc:      # a callback's bug must not stop the reading
                            self.callback_errors += 1
                            self.last_error = f"{type(exc).__name__}: {exc}"

    def publisher(self, topic: str, msgtype: str, depth: int = DEFAULT_DEPTH) -> "DdsPublisher":
        from cyclonedds.pub import DataWriter
        msgtype = normalise_type(msgtype)
        writer = DataWriter(self.participant, self._topic(topic, msgtype), qos=writer_qos(msgtype, depth))
        self._entities.append(writer)
        return DdsPublisher(writer, idl_type(msgtype, raw=True))

    def close(self) -> None:
        """Delete the readers, writers and the participant (the peers see them go). cyclonedds
        deletes an entity when its Python object goes; ``__del__`` does it now, and once."""
        self._closing.set()
        if self._waitset is not None:
            self._wake.set(True)
            self._thread.join(5)
            self._entities += [self._wake, self._waitset]
        self._readers.clear()
        for e in reversed(self._entities):
            e.__del__()
        self._entities.clear()
        if self.participant is not None:
            self.participant.__del__()
            self.participant = None


class DdsPublisher:
    """Writes CDR bytes (``common.ros.cdr.encode`` of a message) on one ROS 2 topic."""

    def __init__(self, writer, sample_type):
        self.writer, self.sample_type = writer, sample_type

    def put(self, cdr: bytes) -> None:
        s = object.__new__(self.sample_type)
        s.cdr = bytes(cdr)
        self.writer.write(s)

    def matched(self) -> int:
        """How many subscriptions this writer has matched."""
        return len(self.writer.get_matched_subscriptions())
