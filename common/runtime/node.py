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

A node can also be used with no process and no network (unit tests)::

    node = EpnpNode.offline(params={...}, wired=["left", "right", "calib"])
    node.on_calib(calib); node.on_left(kp)
    node.published   # [(output, message), ...]

``run`` hosts a node in a process (``common.runtime.process``: the session, the inputs, the
stats; docs/runtime.md); the launcher starts every module node as ``python -m
common.runtime.node --graph FILE --node ID``. Shared memory: ``shm``; hot swap: ``swap``.
"""
from __future__ import annotations

import collections
import importlib
import logging
import os
import sys
import time
from typing import TYPE_CHECKING, Iterable, Optional

from common.errors import NeedletrackError
from common.runtime.checks import publish_check_error
from common.runtime.messages import Command, Message
from common.runtime.pairing import SeqClock
from common.runtime.params import param_errors, parse_params

if TYPE_CHECKING:
    from common.runtime.process import Runtime

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
        self._badlog = RateLimitedLog(self.log)

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
        seq = seq_of(msg)
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
        ``output``. Frame messages get the stream's ``epoch``; a message that fails its type's
        check before publishing (``checks.publish_check_error``: a ``PoseEstimate``'s invariant
        within ``pose_volume_m``) is counted (``invalid_pose``), logged and not published."""
        if output not in self.OUTPUTS:
            raise NodeError(f"{type(self).__name__}.publish: {output!r} is not in OUTPUTS {self.OUTPUTS}")
        inner = msg.msg if isinstance(msg, Prepared) else msg
        self._stamp(inner)
        bad = publish_check_error(inner, self.pose_volume_m)
        if bad:
            counter, err = bad
            self.count(counter)
            self._badlog.error(counter, f"{output}: seq {getattr(inner, 'seq', None)}: not published: {err}")
            return
        if self._runtime is None:
            self.published.append((output, msg.msg if isinstance(msg, Prepared) else msg))
        else:
            self._runtime.publish(output, msg)

    def publish_all(self, out) -> None:
        """Publish each ``(output, message)`` of ``out`` in turn (what a library frame step
        returns, e.g. ``common.pose``)."""
        for output, msg in out:
            self.publish(output, msg)

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


class RateLimitedLog:
    """Logs the first error of a kind at once, then at most one summary per ``period`` seconds
    (the nodes' handlers, the runtime, library threads such as the viewer's page)."""

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



def seq_of(msg) -> Optional[int]:
    """A message's integer ``seq`` (its frame), or None when it has none."""
    seq = getattr(msg, "seq", None)
    return seq if isinstance(seq, int) else None


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


def run(node_cls: Optional[type] = None, argv: Optional[list] = None) -> int:
    """Host a node: ``python -m common.runtime.node --graph FILE --node ID`` or a node module's
    ``run(NODE)``. Exits the process with the node's status (0 ok, 1 failure, 2 bad config)."""
    from common.runtime.process import host
    sys.exit(host(node_cls, argv))


if __name__ == "__main__":
    # Run through the canonical module so that nodes subclass the same Node class.
    from common.runtime.node import run as _canonical_run
    _canonical_run()
