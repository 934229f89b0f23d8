"""Hot swap, both sides: the launcher's (``LauncherSwap.swap``) and the process's
(``SwapControl``, the handover and takeover queries). A process started in
standby (``NEEDLETRACK_STANDBY=1``) runs its handlers but holds its outputs; the launcher asks
the old process to hand over (it stops publishing and replies, per output, the first seq the
successor owns) and the new one to take over (it publishes the held outputs its predecessor did
not, then goes live). A spare (``NEEDLETRACK_SPARE=1``) is set up and idle until a takeover.
Both queries are honoured only with the process's control token (``NEEDLETRACK_CTL_TOKEN``,
given by the launcher that started it and sent only in a swap it runs); any other is refused
and counted ``ctl_refused``."""
from __future__ import annotations

import hmac
import json
import os
import queue
import threading
import time
from typing import TYPE_CHECKING, Iterable, Optional

from common.runtime.graph import GraphError, NodeSpec, ctl_key, graph_from_dict
from common.runtime.node import graph_param_errors

if TYPE_CHECKING:
    from common.runtime.launcher import Proc

STANDBY_BUFFER = 64            # outputs a standby process holds for the takeover
SWAP_READY_TIMEOUT_S = 120.0
SWAP_WARM_TIMEOUT_S = 5.0


class SwapControl:
    """The handover/takeover queries of ``common.runtime.process.Runtime``: its ``state``
    (active | standby | retired | spare), the outputs it holds (``_held``: (output, seq,
    payload)), the cuts it publishes from (``_cuts``), the last seq per output (``_last_seq``)
    and ``_pub_lock`` that guards them."""

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


class LauncherSwap:
    """``Launcher.swap`` and the ``<graph>/@launcher/swap`` queries it answers (from a thread of
    its own, ``_swap_loop``): the launcher's side of a swap. Uses the launcher's ``slots``,
    ``graph``, ``session``, ``_spawn``, ``_terminate`` and ``_lock``."""

    def _q_swap(self, query) -> None:
        self._swaps.put(query)   # answered from the swap thread: never block a Zenoh callback

    def _ctl(self, node_id: str, proc: Proc, op: str, payload: Optional[dict] = None, timeout: float = 2.0):
        """A control query to one process; handover and takeover carry its token."""
        kw = {"timeout": timeout}
        if op in ("handover", "takeover"):
            payload = {**(payload or {}), "token": proc.token}
        if payload is not None:
            kw["payload"] = json.dumps(payload).encode()
        for reply in self.session.get(ctl_key(self.graph.name, node_id, proc.pid, op), **kw):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes().decode())
        return None

    def _covers(self, node_id: str, old: Optional[Proc], status: dict) -> bool:
        """Whether the standby process holds outputs from the frame after the old process's last
        output on: a lagging old process (a slow backend) may not have reached the standby's
        first frame yet, and handing over then would lose the frames in between."""
        first = status.get("held_first") or {}
        if old is None or old.popen.poll() is not None or not first:
            return True
        ans = self._ctl(node_id, old, "status", timeout=0.5) or {}
        last = ans.get("last_seq") or {}
        return all(out not in last or last[out] + 1 >= seq for out, seq in first.items())

    def swap(self, node_id: str, module: Optional[str] = None, params: Optional[dict] = None,
             unset: Iterable[str] = ()) -> dict:
        """Replace a running node by a new process (another module and/or params), make-before-break.
        ``params`` are set over the node's own, then the names in ``unset`` are removed; the new
        spec is checked like a launched graph's (its params against the node's ``Params``).

        1. the new process starts in standby: it runs its handlers but holds its outputs;
        2. once it is up and has produced an output, and its held outputs reach back to the frame
           after the old process's last output (or ``SWAP_WARM_TIMEOUT_S`` passed), the old
           process is told to hand over: it stops publishing at once and answers, per output, the
           sequence number after the last one it published (the cut);
        3. the new process publishes its held outputs with seq >= cut and goes live, dropping any
           later output with seq < cut; so no frame seq is published by both;
        4. the old process is stopped. Returns a summary; raises ValueError/RuntimeError.
        """
        with self._lock:
            slot = self.slots.get(node_id)
            if slot is None:
                raise ValueError(f"no node {node_id!r} in this launcher (nodes: {', '.join(self.slots)})")
            old = slot.proc
            new_spec = NodeSpec(**{**slot.spec.__dict__})
            new_spec.params = {k: v for k, v in {**slot.spec.params, **(params or {})}.items() if k not in set(unset)}
            if module:
                new_spec.module, new_spec.command = module, None
            data = self.graph.to_dict()
            data["nodes"] = [new_spec.to_dict() if n["id"] == node_id else n for n in data["nodes"]]
            new_graph = graph_from_dict(data)       # raises GraphError with every problem
            index = [n.id for n in new_graph.nodes].index(node_id)
            errors = [e for e in graph_param_errors(new_graph) if e.startswith(f"nodes[{index}].")]
            if errors:
                raise GraphError(errors, f"swap {node_id}")
            # a node process reads its spec from the graph file: a refused swap must restore it,
            # or a later restart of the old node would run the refused spec
            old_graph, old_graph_file = self.graph, self.graph_file
            self.graph = new_graph
            self.graph_file = self._write_graph()
            new_spec = new_graph.node(node_id)
            t0 = time.monotonic()
            new = self._spawn(new_spec, restarts=slot.restarts, standby=True)
            self._swapping.add(node_id)
        handed = None
        self.say(f"swap {node_id}: standby pid {new.pid} ({new_spec.module}, params {new_spec.params})")
        try:
            status = None
            deadline = time.monotonic() + SWAP_READY_TIMEOUT_S
            warm_deadline = None
            while time.monotonic() < deadline:
                if new.popen.poll() is not None:
                    from common.runtime.launcher import describe_status
                    raise RuntimeError(f"new {node_id} process exited with {describe_status(new.popen.returncode)} "
                                       f"before taking over")
                if new_spec.module:
                    status = self._ctl(node_id, new, "status", timeout=0.5)
                    if status and status.get("ready"):
                        if not new_spec.outputs or (status.get("produced") and self._covers(node_id, old, status)):
                            break
                        warm_deadline = warm_deadline or time.monotonic() + SWAP_WARM_TIMEOUT_S
                        if time.monotonic() > warm_deadline:
                            break
                elif time.monotonic() - t0 > 2.0:    # a command node: no handover protocol
                    break
                time.sleep(0.05)
            else:
                raise RuntimeError(f"new {node_id} process not ready after {SWAP_READY_TIMEOUT_S:.0f} s")
            ready_s = time.monotonic() - t0
            cuts = {}
            if old is not None and old.popen.poll() is None:
                handed = self._ctl(node_id, old, "handover")
                if handed is not None and handed.get("ok") is False:
                    raise RuntimeError(f"{node_id} (pid {old.pid}) refused the handover: {handed.get('error')}")
                cuts = (handed or {}).get("cuts", {})
            taken = self._ctl(node_id, new, "takeover", {"cuts": cuts}) if new_spec.module else {}
            if new_spec.module and not (taken or {}).get("ok"):
                raise RuntimeError(f"new {node_id} process did not take over: {taken}")
        except Exception:
            self._terminate([new], grace=2.0)
            if handed is not None and old is not None and old.popen.poll() is None:
                self._ctl(node_id, old, "takeover", {"cuts": {}})     # the old one goes on publishing
            with self._lock:
                self.graph, self.graph_file = old_graph, old_graph_file
                self._swapping.discard(node_id)
            raise
        with self._lock:
            new.role = "active"
            slot.spec, slot.proc = new_spec, new
            slot.done, slot.restart_at = False, None
            if old is not None:
                old.role = "retired"
                self._retired.append(old)
            if slot.spare is not None:             # set up with the old spec: a new one follows
                old_spare, slot.spare = slot.spare, None
                self._retired.append(old_spare)
                threading.Thread(target=self._terminate, args=([old_spare], 2.0), daemon=True).start()
            self._swapping.discard(node_id)
        if old is not None:
            threading.Thread(target=self._terminate, args=([old],), daemon=True).start()
        summary = {"ok": True, "node": node_id, "module": new_spec.module, "params": new_spec.params,
                   "old_pid": old.pid if old else None, "new_pid": new.pid, "cuts": cuts,
                   "flushed": (taken or {}).get("flushed", 0), "ready_s": round(ready_s, 3)}
        self.say(f"swap {node_id}: pid {summary['old_pid']} -> {new.pid} at cuts {cuts} "
                 f"(ready in {ready_s:.2f} s)")
        return summary

    def _swap_loop(self) -> None:
        while not self._stop.is_set():
            try:
                query = self._swaps.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                req = json.loads(query.payload.to_bytes().decode()) if query.payload else {}
                ans = self.swap(req["node"], req.get("module"), req.get("params") or {}, req.get("unset") or ())
            except GraphError as exc:
                ans = {"ok": False, "error": "the swapped graph is invalid", "errors": exc.errors}
            except Exception as exc:
                ans = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
            if not ans.get("ok"):
                self.say(f"swap failed: {ans.get('error')} {ans.get('errors', '')}")
            try:
                query.reply(query.key_expr, json.dumps(ans).encode())
            except Exception as exc:
                self.say(f"swap reply not sent: {exc}")
            del query
