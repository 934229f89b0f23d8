"""The process that hosts one node (``common.runtime.node.run``, docs/runtime.md):

- one Zenoh session per process, configured from the graph
  (``common.runtime.zenoh_session.zenoh_config``);
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
- the pose invariant (``Node.publish``, ``checks.PUBLISH_CHECKS``): a ``PoseEstimate`` that is
  not rigid and finite, has a covariance that is not symmetric PSD, or lies beyond the graph's
  ``pose_volume_m`` (default 1 m) from the ECM is not published: counted ``invalid_pose`` and
  logged;
- outputs are published ``express`` (not batched: a hop costs less, ``needletrack bench
  transport``); payloads with a
  large field (images) go by Zenoh shared memory; a source may ``prepare`` its next message
  (the copy into shared memory done ahead) and ``wait_for_input`` between steps;
- stats (``NodeStats``) once a second on ``<graph>/@stats/<id>``; a liveliness token
  ``<graph>/@live/<id>`` while the node is up (declared after ``setup``);
- SIGTERM/SIGINT stop the node cleanly (``teardown`` runs, exit status 0);
- hot swap: a process started in standby (``NEEDLETRACK_STANDBY=1``) runs its handlers but holds
  its outputs until the launcher hands over (``common.runtime.swap``). Both
  are honoured only with the process's control token (``NEEDLETRACK_CTL_TOKEN``, given by the
  launcher that started it and sent only in a swap it runs); any other query is refused and
  counted ``ctl_refused``.
"""
from __future__ import annotations

import argparse
import collections
import logging
import os
import signal
import sys
import threading
import time
from typing import Optional

from common.runtime.inputs import InputQueue
from common.runtime.messages import Command, MessageError, NodeStats, decode, encode, encode_parts
from common.runtime.node import POSE_VOLUME_M, Node, NodeError, Prepared, RateLimitedLog, seq_of, node_class
from common.runtime.params import ParamError
from common.runtime.shm import ShmWriter
from common.runtime.swap import STANDBY_BUFFER, SwapControl

STATS_PERIOD_S = 1.0


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


class Runtime(SwapControl):
    """Hosts one node instance on a Zenoh session (one per process)."""

    def __init__(self, graph, node_id: str, standby: bool = False, restarts: int = 0,
                 ctl_token: Optional[str] = None, spare: bool = False):
        self.graph = graph
        self.spec = graph.node(node_id)
        self.node_id = node_id
        self.stats = Stats()
        self.log = logging.getLogger(node_id)
        self.errlog = RateLimitedLog(self.log)
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

        from common.runtime.graph import cmd_key, ctl_key
        from common.runtime.zenoh_session import zenoh_config
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
        seq = seq_of(msg.msg if isinstance(msg, Prepared) else msg)
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
        from common.runtime.zenoh_session import close_session
        close_session(self.session, self._decl)


# ====================================================================== entry point

def _setup_logging(node_id: str) -> None:
    level = os.environ.get("NEEDLETRACK_LOG", "INFO").upper()
    logging.basicConfig(level=getattr(logging, level, logging.INFO), stream=sys.stderr,
                        format="%(levelname)s %(message)s")


def host(node_cls: Optional[type], argv: Optional[list]) -> int:
    """``common.runtime.node.run``: parse ``--graph FILE --node ID``, build the node (its class
    from the graph's ``module`` unless given) and serve it; returns the exit status (0 ok, 1
    failure, 2 bad configuration)."""
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


