"""The viewer's numbers: per method its newest pose, error against the truth, rate and latency,
and short time series of them for the plots. No process, no network.

Units: positions mm, angles deg, rates poses/s, latencies ms, times s (monotonic, the caller's).
"""
from __future__ import annotations

import collections
from typing import Optional

import numpy as np

from common import palette
from common.geometry.transforms import pose_error

SERIES = ("pos_err_mm", "rot_err_deg", "rate_hz", "latency_ms", "confidence")


class RateMeter:
    """Events per second over the last ``window_s`` seconds."""

    def __init__(self, window_s: float = 2.0):
        self.window_s = window_s
        self._t: collections.deque = collections.deque()

    def add(self, t: float) -> None:
        self._t.append(t)
        self.rate(t)

    def rate(self, now: float) -> float:
        while self._t and self._t[0] < now - self.window_s:
            self._t.popleft()
        return len(self._t) / self.window_s


class ViewerState:
    """What the page's table and plots show. ``keep_s``: how far back the series go;
    ``every_s``: at most one series point per name and method in that interval."""

    def __init__(self, keep_s: float = 30.0, every_s: float = 0.2):
        self.keep_s, self.every_s = keep_s, every_s
        self.methods: dict = {}
        self.rates: dict = collections.defaultdict(RateMeter)
        self.series: dict = {k: collections.defaultdict(collections.deque) for k in SERIES}
        self.head = ""
        self.final: Optional[str] = None      # the method drawn in full (the legend marks it)

    def add_point(self, name: str, key: str, t: float, value: float) -> None:
        """Append ``value`` at time ``t`` to series ``name`` line ``key`` (thinned to
        ``every_s``; points older than ``keep_s`` dropped)."""
        d = self.series[name][key]
        if d and t - d[-1][0] < self.every_s:
            return
        d.append((round(t, 3), round(float(value), 4)))
        while d and d[0][0] < t - self.keep_s:
            d.popleft()

    def add_pose(self, method: str, seq: int, T_ecm_needle, T_true: Optional[np.ndarray],
                 latency_ms: float, ambiguous: bool, t: float, end_identity: Optional[float] = None) -> dict:
        """Record a method's pose received at ``t``; returns its row (also kept for the table)."""
        self.rates[method].add(t)
        rate = self.rates[method].rate(t)
        row = {"seq": int(seq), "t_mm": " ".join(f"{x:.1f}" for x in np.asarray(T_ecm_needle)[:3, 3] * 1e3),
               "rate_hz": round(rate, 1), "latency_ms": round(float(latency_ms), 1),
               "ambiguous": bool(ambiguous), "pos_err_mm": None, "rot_err_deg": None,
               "tip_p": None if end_identity is None else round(float(end_identity), 2)}
        if T_true is not None:
            dp, dr = pose_error(np.asarray(T_ecm_needle, float), T_true)
            row["pos_err_mm"], row["rot_err_deg"] = round(dp * 1e3, 3), round(float(np.degrees(dr)), 3)
            self.add_point("pos_err_mm", method, t, row["pos_err_mm"])
            self.add_point("rot_err_deg", method, t, row["rot_err_deg"])
        self.add_point("rate_hz", method, t, rate)
        self.add_point("latency_ms", method, t, latency_ms)
        self.methods[method] = row
        return row

    def to_json(self, now: float) -> dict:
        """The page's ``state.json``: head line, the final method, per-method rows, series (t in s
        relative to ``now``, over the last ``keep_s``), the colours (``common.palette``)."""
        for m, row in self.methods.items():
            row["rate_hz"] = round(self.rates[m].rate(now), 1)
        colours = palette.page_colours()
        series = {name: {k: [[round(t - now, 2), v] for t, v in d] for k, d in lines.items() if d}
                  for name, lines in self.series.items()}
        return {"head": self.head, "final": self.final, "methods": dict(sorted(self.methods.items())),
                "series": series, "keep_s": self.keep_s, "colours": colours}
