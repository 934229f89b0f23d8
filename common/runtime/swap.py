"""Hot swap, the process's side (``common.runtime.launcher`` runs it): a process started in
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
from typing import Optional

STANDBY_BUFFER = 64            # outputs a standby process holds for the takeover


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
