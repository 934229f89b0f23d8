"""The node runtime: a ``Node`` base class and ``run`` that hosts one node in one process.

A node module in ``nodes/`` defines a ``Node`` subclass and exports it as ``NODE``::

    class Relay(Node):
        INPUTS = {"in": None}          # input name -> message type (None: any message type)
        OUTPUTS = ("out",)
        KEEP_ALL = ("in",)             # inputs that see every message; others get the newest only
        def setup(self): self.gain = self.params.get("gain", 1.0)
        def on_in(self, msg): self.publish("out", msg)

    NODE = Relay
    if __name__ == "__main__":
        run(NODE)

The launcher starts every module node as ``python -m common.runtime.node --graph FILE --node ID``.
Runtime behaviour (see README "Runtime"):

- one Zenoh session per process, configured from the graph (``common.runtime.graph.zenoh_config``);
- inputs are subscribed on ``<graph>/<src node>/<output>``; payloads are decoded on the worker
  thread, handlers run one at a time there; a newest-only input that is not yet handled when a
  newer message comes drops the older (counted ``dropped``); a ``KEEP_ALL`` input queues all;
- undecodable payloads and raising handlers are logged (rate limited) with the key and counted
  (``decode_errors``, ``handler_errors``); the node keeps running; ``decode`` validates every
  field (finite, bounded, shaped: see ``messages``), so a handler sees only well-formed messages;
- source epochs: a source stamps a random ``epoch`` (per process) on every frame message it
  publishes and every other node stamps its input's epoch on what it publishes; each node's
  ``SeqClock`` (``Node.frame_clock``) sees every message's ``(epoch, seq)`` before its handler:
  a restarted source is a new stream (``on_stream_reset`` clears the node's per-frame state,
  counted ``stream_resets``), a lone far-off seq or foreign epoch is dropped (``seq_outlier``);
- the pose invariant: a ``PoseEstimate`` that is not rigid and finite, has a covariance that is
  not symmetric PSD, or lies beyond the graph's ``pose_volume_m`` (default 1 m) from the ECM is
  not published: counted ``invalid_pose`` and logged;
- outputs are published ``express`` (not batched: a hop costs ~2 ms less); payloads with a
  large field (images) go by Zenoh shared memory; a source may ``prepare`` its next message
  (the copy into shared memory done ahead) and ``wait_for_input`` between steps;
- stats (``NodeStats``) once a second on ``<graph>/@stats/<id>``; a liveliness token
  ``<graph>/@live/<id>`` while the node is up (declared after ``setup``);
- SIGTERM/SIGINT stop the node cleanly (``teardown`` runs, exit status 0);
- hot swap: a process started in standby (``NEEDLETRACK_STANDBY=1``) runs its handlers but holds
  its outputs until the launcher hands over; see ``Runtime._q_handover``/``_q_takeover``. Both
  are honoured only with the process's control token (``NEEDLETRACK_CTL_TOKEN``, given by the
  launcher that started it and sent only in a swap it runs); any other query is refused and
  counted ``ctl_refused``.

A node can also be used with no process and no network (unit tests)::

    node = EpnpNode.offline(params={...}, wired=["left", "right", "calib"])
    node.on_calib(calib); node.on_left(kp)
    node.published   # [(output, message), ...]
"""
from __future__ import annotations

import argparse
import collections
import hmac
import importlib
import json
import logging
import os
import signal
import sys
import threading
import time
from typing import Any, Iterable, Optional

from common.errors import NeedletrackError
from common.runtime.messages import (
    Command,
    Message,
    MessageError,
    NodeStats,
    PoseEstimate,
    decode,
    encode,
    encode_parts,
    pose_invariant_error,
)
from common.runtime.pairing import SeqClock
from common.runtime.params import ParamError, param_errors, parse_params

STATS_PERIOD_S = 1.0
KEEP_ALL_LIMIT = 1000          # a KEEP_ALL input queues at most this many (then drops the oldest)
STANDBY_BUFFER = 64            # outputs a standby process holds for the takeover
POSE_VOLUME_M = 1.0            # default working volume: a published needle pose is this close to the ECM (m)


class NodeError(NeedletrackError, ValueError):
    """A node that cannot run as configured (bad wiring, missing handler, bad params, an
    unreadable model file): the process exits with status 2 and is not restarted."""


class Prepared:
    """A message whose large field already sits in a shared-memory buffer (``Node.prepare``):
    publishing it writes only the small header, so a source can copy its next frame while it
    waits and stamp it when it sends. Change only small fields (``stamp_ns``) in between."""

    def __init__(self, msg, buf=None, head_len: int = 0):
        self.msg, self.buf, self.head_len = msg, buf, head_len


class Node:
    """Base of every node. Override ``setup``, ``on_<input>``, ``step`` (sources),
    ``on_command`` and ``teardown`` as needed; see the module docstring."""

    INPUTS: dict = {}
    OUTPUTS: tuple = ()
    KEEP_ALL: tuple = ()
    FEEDBACK: tuple = ()
    """Inputs that close a declared cycle (acknowledgements): ``validate`` does not report it."""
    Params: Optional[type] = None
    """The node's params as a dataclass (``common.runtime.params``); ``self.p`` is its instance."""

    def __init__(self, node_id: str = "node", params: Optional[dict] = None,
                 wired: Optional[Iterable[str]] = None, runtime: Optional["Runtime"] = None):
        self.node_id = node_id
        self.params = dict(params or {})
        schema = self.param_schema(self.params)
        self.p = None if schema is None else parse_params(schema, self.params, f"{node_id}.params")
        self._wired = set(self.INPUTS if wired is None else wired)
        self._runtime = runtime
        self.running = True
        self.log = logging.getLogger(node_id)
        self.published: list = []      # (output, msg) when there is no runtime (offline use)
        self.counters: collections.Counter = collections.Counter()
        self.frame_clock = SeqClock()
        self.source_epoch = int.from_bytes(os.urandom(7), "big")   # this process's stream, if a source
        if self.is_source() and self.FEEDBACK:
            self.frame_clock.pin(self.source_epoch)     # a source's feedback: acks of its own stream
        self.pose_volume_m = POSE_VOLUME_M if runtime is None else runtime.pose_volume_m
        self._candidate = None                                     # (input, msg) held by the clock
        self._badlog = _RateLimitedLog(self.log)

    @classmethod
    def offline(cls, params: Optional[dict] = None, wired: Optional[Iterable[str]] = None,
                node_id: str = "test") -> "Node":
        """A node with no process and no network: ``setup()`` has run; ``publish`` appends
        ``(output, msg)`` to ``self.published``; ``count`` adds to ``self.counters``."""
        node = cls(node_id, params, wired)
        node.setup()
        return node

    @classmethod
    def param_schema(cls, raw: dict) -> Optional[type]:
        """The params dataclass for these raw params (``Params``; a node whose params depend on
        one of them, e.g. the detector's backend, overrides this)."""
        return cls.Params

    # ---------------------------------------------------------------- for subclasses
    def setup(self) -> None:
        """Called once before any handler; read ``self.p`` (typed params) here. Raise
        ``NodeError`` for a configuration that cannot work."""

    def teardown(self) -> None:
        """Called once when the node stops."""

    def step(self):
        """Sources override this: called in a loop; pace yourself; return False when done; raise
        ``NodeError`` when the input cannot go on (a corrupt file): the process exits with
        status 2, is not restarted, and the launcher stops the graph."""
        raise NotImplementedError

    def on_stream_reset(self) -> None:
        """The source restarted (a new epoch) or jumped: forget per-frame state (pairers, caches
        keyed by ``seq``, frames waiting); the new stream's first messages follow at once."""

    def on_command(self, msg: Command) -> None:
        """A ``Command`` sent to ``<graph>/<node id>/cmd``."""
        self.log.warning("command %r ignored: node %s has no on_command", msg.name, type(self).__name__)
        self.count("commands_ignored")

    # ---------------------------------------------------------------- services
    def deliver(self, name: str, msg) -> bool:
        """Hand a decoded message to its handler (``name``: an input, or ``@cmd``) through the
        frame clock (see ``SeqClock``); returns False if the clock dropped it. The runtime calls
        this for every message; offline tests and the fuzzer may too."""
        handler = self.on_command if name == "@cmd" else getattr(self, f"on_{name}")
        seq = _seq_of(msg)
        if seq is not None:
            verdict = self.frame_clock.observe(seq, getattr(msg, "epoch", None))
            if verdict in ("outlier", "stale"):
                self.count(f"seq_{verdict}")
                if verdict == "outlier":
                    held = self.frame_clock.candidate == (getattr(msg, "epoch", None), seq)
                    self._candidate = (name, msg) if held else None
                    self._badlog.error("seq", f"{name}: seq {seq} epoch {getattr(msg, 'epoch', None)} off the "
                                       f"stream (newest {self.frame_clock.newest}); dropped unless confirmed")
                return False
            if verdict == "reset":
                self.count("stream_resets")
                self.log.warning("%s: a new source stream (epoch %s, seq %d): resynchronising", name,
                                 self.frame_clock.epoch, seq)
                self.on_stream_reset()
                cand, self._candidate = self._candidate, None
                if cand is not None:
                    (self.on_command if cand[0] == "@cmd" else getattr(self, f"on_{cand[0]}"))(cand[1])
            else:
                self._candidate = None
        handler(msg)
        return True

    def _stamp(self, msg) -> None:
        """Give an outgoing frame message without an ``epoch`` this stream's epoch."""
        if isinstance(msg, Message) and getattr(msg, "epoch", 0) is None:
            msg.epoch = self.source_epoch if self.is_source() else self.frame_clock.epoch

    def publish(self, output: str, msg) -> None:
        """Encode ``msg`` (a Message, already encoded bytes, or ``Prepared``) and publish it on
        ``output``. Frame messages get the stream's ``epoch``; a ``PoseEstimate`` that breaks the
        pose invariant (``checks.pose_invariant_error`` within ``pose_volume_m``) is counted
        (``invalid_pose``), logged and not published."""
        if output not in self.OUTPUTS:
            raise NodeError(f"{type(self).__name__}.publish: {output!r} is not in OUTPUTS {self.OUTPUTS}")
        inner = msg.msg if isinstance(msg, Prepared) else msg
        self._stamp(inner)
        if isinstance(inner, PoseEstimate):
            err = pose_invariant_error(inner, self.pose_volume_m)
            if err:
                self.count("invalid_pose")
                self._badlog.error("invalid_pose", f"{output}: seq {inner.seq} {inner.method}: pose not "
                                   f"published: {err}")
                return
        if self._runtime is None:
            self.published.append((output, msg.msg if isinstance(msg, Prepared) else msg))
        else:
            self._runtime.publish(output, msg)

    def prepare(self, msg) -> Prepared:
        """``msg`` ready to ``publish`` later, its large field (an image) copied now into shared
        memory when the transport uses it (offline: nothing to copy)."""
        self._stamp(msg)
        return Prepared(msg) if self._runtime is None else self._runtime.prepare(msg)

    def count(self, name: str, n: int = 1) -> None:
        """Add ``n`` to a custom counter reported in the node's stats."""
        if self._runtime is None:
            self.counters[name] += n
        else:
            self._runtime.stats.add(name, n)

    def wait_for_input(self, timeout: float) -> None:
        """Sources, between steps: block until an input message arrives (and handle it) or
        ``timeout`` seconds pass, instead of polling (offline: sleep)."""
        if self._runtime is None:
            time.sleep(timeout)
        else:
            self._runtime.wait_for_input(timeout)

    def wired(self, input_name: str) -> bool:
        """Whether the graph connects this input."""
        return input_name in self._wired

    def stop(self) -> None:
        """Ask the runtime to stop this node (exit status 0) after the current handler."""
        self.running = False
        if self._runtime is not None:
            self._runtime.request_stop()

    @classmethod
    def is_source(cls) -> bool:
        return cls.step is not Node.step


# ====================================================================== runtime pieces

class InputQueue:
    """Pending input messages of one node, in arrival order.

    A newest-only input holds at most one pending payload: a newer one replaces it (``dropped``
    counts the replaced ones). A keep-all input queues every payload (up to ``limit``).
    """

    def __init__(self, keep_all: Iterable[str] = (), limit: int = KEEP_ALL_LIMIT):
        self.keep_all = set(keep_all)
        self.limit = limit
        self._cv = threading.Condition()
        self._order: collections.deque = collections.deque()     # input names, FIFO
        self._latest: dict[str, Any] = {}
        self._queues: dict[str, collections.deque] = collections.defaultdict(collections.deque)
        self.dropped: collections.Counter = collections.Counter()
        self.closed = False

    def put(self, name: str, item) -> None:
        with self._cv:
            if name in self.keep_all:
                q = self._queues[name]
                if len(q) >= self.limit:
                    q.popleft()
                    self._order.remove(name)
                    self.dropped[name] += 1
                q.append(item)
                self._order.append(name)
            else:
                if name in self._latest:
                    self.dropped[name] += 1
                else:
                    self._order.append(name)
                self._latest[name] = item
            self._cv.notify()

    def get(self, timeout: Optional[float] = None):
        """The next ``(name, item)``, or None on timeout or when closed."""
        with self._cv:
            if not self._order and not self.closed:
                self._cv.wait(timeout)
            if not self._order:
                return None
            name = self._order.popleft()
            if name in self.keep_all:
                return name, self._queues[name].popleft()
            return name, self._latest.pop(name)

    def __len__(self):
        with self._cv:
            return len(self._order)

    def close(self) -> None:
        with self._cv:
            self.closed = True
            self._cv.notify_all()


class Stats:
    """Counters (thread-safe), per-period rates and handler times of one node.

    Handler times are those of the handlers that published something (the frame's work: a
    detector's image, not its calibration or ground truth); a node whose handlers never publish
    (a sink) reports all of them."""

    def __init__(self, window: int = 1000):
        self._lock = threading.Lock()
        self.counters: collections.Counter = collections.Counter()
        self._last: dict = {}
        self._last_t = time.monotonic()
        self.proc_ms: collections.deque = collections.deque(maxlen=window)       # publishing handlers
        self.any_proc_ms: collections.deque = collections.deque(maxlen=window)   # every handler

    def add(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counters[name] += n

    def proc(self, ms: float, published: bool = True) -> None:
        self.any_proc_ms.append(ms)
        if published:
            self.proc_ms.append(ms)

    def snapshot(self) -> tuple:
        """(counters, rates_hz of ``in.*``/``out.*`` since the last snapshot, p50 ms, p99 ms)."""
        with self._lock:
            counters = dict(self.counters)
        now = time.monotonic()
        dt = max(now - self._last_t, 1e-6)
        rates = {k: round((v - self._last.get(k, 0)) / dt, 2) for k, v in counters.items()
                 if k.startswith(("in.", "out."))}
        self._last, self._last_t = counters, now
        p50 = p99 = 0.0
        vals = sorted(self.proc_ms or self.any_proc_ms)
        if vals:
            p50 = vals[min(len(vals) - 1, int(0.50 * len(vals)))]
            p99 = vals[min(len(vals) - 1, int(0.99 * len(vals)))]
        return counters, rates, round(p50, 3), round(p99, 3)


class _RateLimitedLog:
    """Logs the first error of a kind at once, then at most one summary per ``period`` seconds."""

    def __init__(self, log: logging.Logger, period: float = 2.0, level: int = logging.ERROR):
        self.log, self.period, self.level = log, period, level
        self._last: dict = {}
        self._suppressed: collections.Counter = collections.Counter()

    def error(self, kind: str, text: str, exc_info: bool = False) -> None:
        now = time.monotonic()
        if now - self._last.get(kind, -1e9) >= self.period:
            n = self._suppressed.pop(kind, 0)
            more = f" (+{n} more like it)" if n else ""
            self.log.log(self.level, "%s%s", text, more, exc_info=exc_info)
            self._last[kind] = now
        else:
            self._suppressed[kind] += 1


RateLimitedLog = _RateLimitedLog    # public: for library threads outside the handlers (the viewer's page)


class ShmWriter:
    """Puts large payloads into Zenoh shared memory: the receiving processes on this machine
    map them instead of reading them from a socket (remote peers get a copy, transparently).
    Returns None (send normally) when the pool is full, so a slow consumer never blocks us."""

    MIN_BYTES = 1 << 16

    def __init__(self, pool_bytes: int):
        from zenoh import shm
        self._shm = shm
        self.provider = shm.ShmProvider.default_backend(pool_bytes)
        self.failures = 0

    def payload(self, head: bytes, tail):
        buf = self.reserve(len(head), tail)
        return None if buf is None else self.seal(buf, head)

    def reserve(self, head_len: int, tail):
        """A buffer with ``tail`` copied in after ``head_len`` free bytes (None: pool full)."""
        import zenoh
        n = head_len + len(tail)
        try:
            buf = self.provider.alloc(n, self._shm.GarbageCollect())
        except zenoh.ZError:
            self.failures += 1
            return None
        buf[head_len:n] = tail if isinstance(tail, (bytes, bytearray)) else bytes(tail)
        return buf

    @staticmethod
    def seal(buf, head: bytes):
        """The payload of a ``reserve``d buffer once its head is written (the buffer is used up)."""
        import zenoh
        buf[0:len(head)] = head
        return zenoh.ZBytes(buf)


def _seq_of(msg) -> Optional[int]:
    seq = getattr(msg, "seq", None)
    return seq if isinstance(seq, int) else None


class Runtime:
    """Hosts one node instance on a Zenoh session (one per process)."""

    def __init__(self, graph, node_id: str, standby: bool = False, restarts: int = 0,
                 ctl_token: Optional[str] = None, spare: bool = False):
        from common.runtime.graph import cmd_key, ctl_key, live_key, stats_key  # noqa: F401 (used below)
        self.graph = graph
        self.spec = graph.node(node_id)
        self.node_id = node_id
        self.stats = Stats()
        self.log = logging.getLogger(node_id)
        self.errlog = _RateLimitedLog(self.log)
        self._stop = threading.Event()
        self._pub_lock = threading.Lock()
        self.state = "spare" if spare else "standby" if standby else "active"   # active | standby | retired | spare
        self._activated = threading.Event()                   # a spare's takeover
        self._held: collections.deque = collections.deque(maxlen=STANDBY_BUFFER)   # (output, seq, payload)
        self._produced = False
        self._publishes = 0
        self._last_seq: dict[str, int] = {}
        self._cuts: dict[str, int] = {}
        self._restarts = restarts
        self._t0 = time.monotonic()
        self.session = None
        self.node: Optional[Node] = None
        self.queue: Optional[InputQueue] = None
        self._decl: list = []
        self._pubs: dict = {}
        self.exit_status = 0
        self._ready = threading.Event()
        self._shm: Optional[ShmWriter] = None
        self.pose_volume_m = float(getattr(graph, "pose_volume_m", None) or POSE_VOLUME_M)
        self._ctl_token = ctl_token              # handover/takeover need it (None: refused)

    # ---------------------------------------------------------------- setup
    def build(self, cls: type) -> Node:
        spec = self.spec
        if not (isinstance(cls, type) and issubclass(cls, Node)):
            raise NodeError(f"module {spec.module!r}: NODE is not a common.runtime.node.Node subclass")
        errors = []
        for name in spec.inputs:
            if name not in cls.INPUTS:
                errors.append(f"input {name!r} is wired but {cls.__name__}.INPUTS has only "
                              f"{', '.join(cls.INPUTS) or 'nothing'}")
            elif not callable(getattr(cls, f"on_{name}", None)):
                errors.append(f"input {name!r} is wired but {cls.__name__} has no on_{name}(msg)")
        for out in spec.outputs:
            if out not in cls.OUTPUTS:
                errors.append(f"output {out!r} is listed but {cls.__name__}.OUTPUTS has only "
                              f"{', '.join(cls.OUTPUTS) or 'nothing'}")
        if errors:
            raise NodeError("; ".join(errors))
        try:
            self.node = cls(self.node_id, spec.params, wired=spec.inputs.keys(), runtime=self)
        except ParamError as exc:
            raise NodeError(str(exc)) from None
        for name in ["decode_errors", "handler_errors"] + [f"in.{i}" for i in spec.inputs] + \
                [f"out.{o}" for o in cls.OUTPUTS]:
            self.stats.add(name, 0)
        self.queue = InputQueue(keep_all=set(cls.KEEP_ALL) | {"@cmd"})
        return self.node

    def open(self) -> None:
        import zenoh

        from common.runtime.graph import cmd_key, ctl_key, zenoh_config
        g, nid = self.graph.name, self.node_id
        t0 = time.monotonic()
        self.session = zenoh.open(zenoh_config(self.graph, role="node", identity=self.node_id))
        self._open_s = time.monotonic() - t0
        for out in self.node.OUTPUTS:
            self._pubs[out] = self.session.declare_publisher(
                self.graph.output_key(nid, out), congestion_control=zenoh.CongestionControl.BLOCK,
                express=True)
        for name in self.spec.inputs:
            key = self.graph.input_key(self.spec, name)
            self._decl.append(self.session.declare_subscriber(key, self._make_cb(name)))
        self._decl.append(self.session.declare_subscriber(cmd_key(g, nid), self._make_cb("@cmd")))
        pid = os.getpid()
        for op, fn in (("status", self._q_status), ("handover", self._q_handover), ("takeover", self._q_takeover)):
            self._decl.append(self.session.declare_queryable(ctl_key(g, nid, pid, op), fn))
        self._stats_pub = self.session.declare_publisher(f"{g}/@stats/{nid}")

    def _make_cb(self, name: str):
        q = self.queue

        def cb(sample):
            q.put(name, (str(sample.key_expr), sample.payload, time.monotonic()))
        return cb

    # ---------------------------------------------------------------- publishing and swap
    def _shm_writer(self, nbytes: int) -> Optional[ShmWriter]:
        """The shared-memory writer for a payload tail of ``nbytes``, or None (socket)."""
        if nbytes < ShmWriter.MIN_BYTES or self.graph.zenoh.shm_pool_mb <= 0:
            return None
        if self._shm is None:
            try:
                self._shm = ShmWriter(self.graph.zenoh.shm_pool_mb << 20)
            except Exception as exc:  # no shared memory on this system: use the socket
                self.log.warning("no Zenoh shared memory (%s); large payloads go by socket", exc)
                self.graph.zenoh.shm_pool_mb = 0
        return self._shm

    def prepare(self, msg) -> Prepared:
        head, tail = encode_parts(msg)
        writer = None if tail is None else self._shm_writer(len(tail))
        buf = None if writer is None else writer.reserve(len(head), tail)
        return Prepared(msg, buf, len(head))

    def _payload(self, msg, shm: bool):
        if isinstance(msg, (bytes, bytearray, memoryview)):
            return bytes(msg)
        if isinstance(msg, Prepared):
            buf, msg.buf = msg.buf, None              # a buffer is sent once
            if shm and buf is not None:
                head, _ = encode_parts(msg.msg)
                if len(head) == msg.head_len:
                    self.stats.add("out_shm")
                    self.stats.add("out_shm_prepared")
                    return ShmWriter.seal(buf, head)
            msg = msg.msg                             # a header of another length: copy again
        head, tail = encode_parts(msg)
        if tail is None:
            return head
        writer = self._shm_writer(len(tail)) if shm else None
        if writer is not None:
            zb = writer.payload(head, tail)
            if zb is not None:
                self.stats.add("out_shm")
                return zb
            self.stats.add("shm_pool_full")
        return b"".join((head, tail))

    def publish(self, output: str, msg) -> None:
        seq = _seq_of(msg.msg if isinstance(msg, Prepared) else msg)
        self._publishes += 1
        with self._pub_lock:
            self._produced = True
            if self.state == "standby":
                payload = self._payload(msg, shm=False)
                self._held.append((output, seq, payload))
                self.stats.add("held")
                return
            if self.state == "retired":
                self.stats.add("retired_suppressed")
                return
            cut = self._cuts.get(output)
            if cut is not None and seq is not None and seq < cut:
                self.stats.add("swap_suppressed")
                return
            self._put(output, self._payload(msg, shm=True), seq)

    def _put(self, output, payload, seq):
        self._pubs[output].put(payload)
        if seq is not None:
            self._last_seq[output] = seq
        self.stats.add(f"out.{output}")

    def _reply(self, query, obj) -> None:
        query.reply(query.key_expr, json.dumps(obj).encode())

    def _q_status(self, query) -> None:
        with self._pub_lock:
            obj = {"state": self.state, "produced": self._produced, "pid": os.getpid(),
                   "ready": self._ready.is_set(),
                   "last_seq": dict(self._last_seq),
                   "held_seq": [s for _, s, _ in self._held][-4:],
                   "held_first": self._held_first()}
        self._reply(query, obj)

    def _held_first(self) -> dict:
        """Per output, the oldest seq a standby process holds (call with ``_pub_lock`` held)."""
        first: dict = {}
        for out, seq, _ in self._held:
            if seq is not None and seq < first.get(out, seq + 1):
                first[out] = seq
        return first

    def _ctl_request(self, query, op: str) -> Optional[dict]:
        """The JSON payload of a handover/takeover query if it carries this process's control
        token; otherwise replies a refusal, counts ``ctl_refused``, logs it and returns None."""
        try:
            req = json.loads(bytes(query.payload.to_bytes()).decode()) if query.payload else {}
        except (ValueError, AttributeError, UnicodeDecodeError):
            req = None
        token = req.get("token") if isinstance(req, dict) else None
        if (self._ctl_token and isinstance(token, str)
                and hmac.compare_digest(token.encode(), self._ctl_token.encode())):
            return req
        self.stats.add("ctl_refused")
        self.errlog.error(f"ctl:{op}", f"{op} refused: the query does not carry this process's control "
                          f"token (only a swap run by its launcher may {op})")
        self._reply(query, {"ok": False, "error": f"{op} refused: no valid control token"})
        return None

    def _q_handover(self, query) -> None:
        """Old process: stop publishing now; reply, per output, the first seq the successor owns."""
        if self._ctl_request(query, "handover") is None:
            return
        with self._pub_lock:
            self.state = "retired"
            cuts = {out: seq + 1 for out, seq in self._last_seq.items()}
        self.log.info("handing over (cuts %s)", cuts)
        self._reply(query, {"ok": True, "cuts": cuts})

    def _q_takeover(self, query) -> None:
        """New process (or an old one whose swap failed after its handover): publish the held
        outputs the predecessor did not, then go live."""
        req = self._ctl_request(query, "takeover")
        if req is None:
            return
        if self.state == "spare":            # the node's process exited: this one goes on at once
            if isinstance(req.get("restarts"), int):
                self._restarts = req["restarts"]
            self.state = "active"
            self._activated.set()
            self._reply(query, {"ok": True, "flushed": 0})
            return
        cuts = req.get("cuts") if isinstance(req.get("cuts"), dict) else {}
        flushed = 0
        if self.node is not None and self.node.is_source():
            cuts = {}      # a new source starts its own sequence: nothing to line up with
        with self._pub_lock:
            self._cuts = {k: v for k, v in cuts.items() if isinstance(v, int) and not isinstance(v, bool)}
            newest = {}
            for out, seq, _ in self._held:
                if seq is not None:
                    newest[out] = max(newest.get(out, seq), seq)
            for out, seq, payload in self._held:
                if seq is None:
                    continue
                cut = self._cuts.get(out)
                # a held output is sent if the predecessor never reached it; with no cut known,
                # only the newest held frame (an older one would be stale)
                if (cut is not None and seq >= cut) or (cut is None and seq == newest.get(out)):
                    self._put(out, payload, seq)
                    flushed += 1
            self._held.clear()
            self.state = "active"
        self.log.info("took over (cuts %s, %d held outputs sent)", cuts, flushed)
        self._reply(query, {"ok": True, "flushed": flushed})

    # ---------------------------------------------------------------- running
    def request_stop(self) -> None:
        self._stop.set()
        if self.node is not None:
            self.node.running = False
        if self.queue is not None:
            self.queue.close()

    def wait_for_input(self, timeout: float) -> None:
        item = self.queue.get(timeout)
        if item is not None:
            self._dispatch(*item)

    def _dispatch(self, name: str, item) -> None:
        key, payload, _t = item
        node = self.node
        if name == "@cmd":
            expect, counter = Command, "in.cmd"
        else:
            expect, counter = node.INPUTS[name], f"in.{name}"
        self.stats.add(counter)
        try:
            msg = decode(payload.to_bytes() if hasattr(payload, "to_bytes") else payload, expect)
        except MessageError as exc:
            self.stats.add("decode_errors")
            self.errlog.error(f"decode:{name}", f"{key}: cannot decode payload: {exc}")
            return
        t0, n0 = time.perf_counter(), self._publishes
        try:
            node.deliver(name, msg)
        except Exception as exc:  # a handler bug must not kill the node
            self.stats.add("handler_errors")
            self.errlog.error(f"handler:{name}", f"{key}: on_{name.lstrip('@')} raised "
                              f"{type(exc).__name__}: {exc}", exc_info=True)
        finally:
            self.stats.proc((time.perf_counter() - t0) * 1e3, self._publishes > n0)

    def _publish_stats(self) -> None:
        counters, rates, p50, p99 = self.stats.snapshot()
        for name, n in self.queue.dropped.items():
            counters[f"dropped.{name}"] = n
        counters["dropped"] = sum(self.queue.dropped.values())
        counters["restarts"] = self._restarts
        for k, v in self.node.counters.items():
            counters[k] = counters.get(k, 0) + v
        counters["state"] = self.state
        msg = NodeStats(node=self.node_id, module=self.spec.module or " ".join(self.spec.command or []),
                        pid=os.getpid(), stamp_ns=time.time_ns(), uptime_s=round(time.monotonic() - self._t0, 3),
                        counters=counters, rates_hz=rates, proc_ms_p50=p50, proc_ms_p99=p99)
        try:
            self._stats_pub.put(encode(msg))
        except Exception as exc:  # session closing
            self.log.debug("stats not sent: %s", exc)

    def _stats_loop(self) -> None:
        while not self._stop.wait(STATS_PERIOD_S):
            self._publish_stats()

    def serve(self) -> int:
        """Run setup, the handler/step loop and teardown; returns the exit status."""
        node = self.node
        t_setup = time.monotonic()
        try:
            node.setup()
        except NodeError as exc:
            self.log.error("bad configuration: %s", exc)
            return 2
        except Exception as exc:
            self.log.error("setup failed: %s: %s", type(exc).__name__, exc, exc_info=True)
            return 1
        from common.runtime.graph import live_key
        setup_s = time.monotonic() - t_setup
        if self.state == "spare":
            # set up and idle, unseen (no liveliness token, no stats) until the launcher's takeover
            self._ready.set()
            self.log.info("spare ready (pid %d; setup %.2f s)", os.getpid(), setup_s)
            while not self._stop.is_set() and not self._activated.wait(0.2):
                pass
            if not self._activated.is_set():
                self._teardown()
                return self.exit_status
            while self.queue.get(0) is not None:         # what came while idle is stale (commands too)
                pass
            self.log.info("spare took over (pid %d)", os.getpid())
            self._t0 = time.monotonic() - setup_s
        self._decl.append(self.session.liveliness().declare_token(live_key(self.graph.name, self.node_id)))
        self._ready.set()
        stats_thread = threading.Thread(target=self._stats_loop, name="stats", daemon=True)
        stats_thread.start()
        source = node.is_source()
        self.log.info("up (pid %d%s; started %.2f s ago: session %.2f s, setup %.2f s)", os.getpid(),
                      ", standby" if self.state == "standby" else "", time.monotonic() - self._t0,
                      getattr(self, "_open_s", 0.0), setup_s)
        q = self.queue
        step_failures = 0
        while not self._stop.is_set() and node.running:
            if source:
                try:
                    more = node.step()
                    step_failures = 0
                except NodeError as exc:     # a source whose input cannot go on: stop, not restarted
                    self.log.error("source stopped: %s", exc)
                    self.exit_status = 2
                    break
                except Exception as exc:
                    self.stats.add("step_errors")
                    step_failures += 1
                    self.errlog.error("step", f"step raised {type(exc).__name__}: {exc}", exc_info=True)
                    more = True
                    time.sleep(min(1.0, 0.05 * step_failures))
                if more is False:
                    self.log.info("source finished")
                    break
                for _ in range(len(q)):
                    item = q.get(0)
                    if item is None:
                        break
                    self._dispatch(*item)
            else:
                item = q.get(0.2)
                if item is not None:
                    self._dispatch(*item)
        self._stop.set()
        self._teardown()
        self._publish_stats()
        return self.exit_status

    def _teardown(self) -> None:
        try:
            self.node.teardown()
        except Exception as exc:
            self.log.error("teardown failed: %s: %s", type(exc).__name__, exc, exc_info=True)

    def close(self) -> None:
        from common.runtime.graph import close_session
        close_session(self.session, self._decl)


def node_class(module: str) -> type:
    """The class ``nodes/<module>.py`` exports as ``NODE`` (a graph node's ``module``): how the
    runtime, ``describe``, the evaluation and the fuzz load a node; the library never imports
    ``nodes/``. Raises ``ImportError`` (and what the module raises) or ``AttributeError`` (no
    ``NODE``)."""
    return importlib.import_module(f"nodes.{module}").NODE


def graph_param_errors(graph) -> list[str]:
    """Every node's params checked against its class's ``Params`` (imports ``nodes.<module>``,
    not the heavy libraries a node loads in ``setup``); errors carry their place, e.g.
    ``nodes[2].params.threads: expected int, got 'five'``."""
    errors = []
    for i, spec in enumerate(graph.nodes):
        if not spec.module:
            continue
        try:
            cls = node_class(spec.module)
        except Exception as exc:        # a node module that cannot load is a graph error too
            errors.append(f"nodes[{i}].module: cannot import nodes.{spec.module}: {type(exc).__name__}: {exc}")
            continue
        schema = cls.param_schema(spec.params) if isinstance(cls, type) and issubclass(cls, Node) else None
        if schema is not None:
            errors += param_errors(schema, spec.params, f"nodes[{i}].params")
    return errors


# ====================================================================== entry points

def _setup_logging(node_id: str) -> None:
    level = os.environ.get("NEEDLETRACK_LOG", "INFO").upper()
    logging.basicConfig(level=getattr(logging, level, logging.INFO), stream=sys.stderr,
                        format="%(levelname)s %(message)s")


def run(node_cls: Optional[type] = None, argv: Optional[list] = None) -> int:
    """Host a node: ``python -m common.runtime.node --graph FILE --node ID`` or a node module's
    ``run(NODE)``. Exits the process with the node's status (0 ok, 1 failure, 2 bad config)."""
    sys.exit(_run(node_cls, argv))


def _run(node_cls: Optional[type], argv: Optional[list]) -> int:
    from common.runtime.graph import GraphError, load_graph
    ap = argparse.ArgumentParser(prog="node", description="Run one node of a dataflow graph.")
    ap.add_argument("--graph", required=True, help="graph YAML file")
    ap.add_argument("--node", required=True, help="node id in the graph")
    args = ap.parse_args(argv)
    _setup_logging(args.node)
    log = logging.getLogger(args.node)
    try:
        graph = load_graph(args.graph)
        spec = graph.node(args.node)
    except (GraphError, KeyError) as exc:
        log.error("%s", exc)
        return 2
    if node_cls is None:
        if not spec.module:
            log.error("node %r has no module", spec.id)
            return 2
        try:
            node_cls = node_class(spec.module)
        except AttributeError:
            log.error("nodes/%s.py defines no NODE", spec.module)
            return 2
        except Exception as exc:
            log.error("cannot import nodes.%s: %s: %s", spec.module, type(exc).__name__, exc, exc_info=True)
            return 1
    rt = Runtime(graph, args.node, standby=os.environ.get("NEEDLETRACK_STANDBY") == "1",
                 restarts=int(os.environ.get("NEEDLETRACK_RESTARTS", "0") or 0),
                 ctl_token=os.environ.pop("NEEDLETRACK_CTL_TOKEN", None),
                 spare=os.environ.get("NEEDLETRACK_SPARE") == "1")
    try:
        rt.build(node_cls)
    except NodeError as exc:
        log.error("node %r (%s): %s", spec.id, spec.module, exc)
        return 2

    signals_seen = []

    def on_signal(signum, _frame):
        signals_seen.append(signum)
        if len(signals_seen) > 1:
            os._exit(128 + signum)
        rt.request_stop()
    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        try:
            rt.open()
        except GraphError as exc:       # a TLS file missing: bad configuration, not restarted
            log.error("%s", exc)
            return 2
        return rt.serve()
    finally:
        rt.close()


if __name__ == "__main__":
    # Run through the canonical module so that nodes subclass the same Node class.
    from common.runtime.node import run as _canonical_run
    _canonical_run()
