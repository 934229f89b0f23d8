"""A graph run waited on while its replay's frames are shown as a bar: ``needletrack eval``'s and
``needletrack adapt``'s wait for their evaluator or recorder.
"""
from __future__ import annotations

import threading

from common.progress import progress_bar


def wait_with_progress(run, n_frames: int, timeout: float, show: bool = True, until=("evaluator",)) -> None:
    """Wait up to ``timeout`` s for the ``until`` nodes of ``run`` (a ``GraphRun``) to end, showing
    the frames replayed (from the replay's stats) as a bar when ``show``; re-raises what the wait
    raised (``GraphRunError``)."""
    done = threading.Event()
    err: list = []

    def waiter():
        try:
            run.wait(list(until), timeout)
        except Exception as exc:
            err.append(exc)
        done.set()
    threading.Thread(target=waiter, daemon=True).start()
    bar = progress_bar(total=n_frames, desc="eval", unit="frame") if show else None
    sub = None
    if bar is not None:
        from common.runtime.graph import stats_key
        from common.runtime.messages import NodeStats, decode
        state = {"n": 0}

        def on_stats(sample):
            try:
                st = decode(sample.payload.to_bytes(), NodeStats)
            except Exception:
                return
            if st.node == "replay":
                state["n"] = int(st.counters.get("out.left", 0))
        try:
            sub = run.client_session().declare_subscriber(stats_key(run.graph.name, "replay"), on_stats)
        except Exception:
            sub = None
    while not done.wait(0.25):
        if bar is not None and sub is not None and min(n_frames, state["n"]) != bar.n:
            bar.n = min(n_frames, state["n"])
            bar.refresh()
    if bar is not None:
        if not err:
            bar.n = n_frames
        bar.close()
    if sub is not None:
        sub.undeclare()
    if err:
        raise err[0]
