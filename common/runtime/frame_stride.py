"""Which frames a detector that cannot keep up with the camera should take.

Two detector processes (one per camera) that each take the newest image when free drift apart
and detect different frames, which never pair. ``FrameStride`` makes them agree without talking:
take only frames whose ``seq`` is a multiple of ``stride``, a power of two just large enough
that one detection fits in ``stride`` frame intervals. Powers of two nest, so a faster
detector's frames include a slower one's.
"""
from __future__ import annotations

from collections import deque

import numpy as np


class FrameStride:
    """Power-of-two frame stride from the frame interval (running mean) and the median of the last
    ``window`` detection times (a cold detection or a scheduler hiccup is not a trend); the
    stride halves only when that median would fit in ``halve_at`` of the smaller stride, a
    hysteresis against flapping. ``adaptive`` False keeps the given stride."""

    MAX = 64

    def __init__(self, stride: int = 1, adaptive: bool = False, window: int = 15, halve_at: float = 0.75):
        if stride < 1 or stride & (stride - 1):
            raise ValueError(f"stride must be a power of two, got {stride!r}")
        self.stride, self.adaptive = int(stride), bool(adaptive)
        self.halve_at = float(halve_at)
        self._last_frame = None           # (seq, stamp_ns) of the newest frame seen
        self._period_s = None             # frame interval, s
        self._busy_s = deque(maxlen=int(window))   # wall times of the last detections, s

    def takes(self, seq: int) -> bool:
        return seq % self.stride == 0

    def frame(self, seq: int, stamp_ns: int) -> None:
        """A frame arrived (whether taken or not): updates the frame interval."""
        last, self._last_frame = self._last_frame, (seq, stamp_ns)
        if last is not None and seq > last[0] and stamp_ns > last[1]:
            p = (stamp_ns - last[1]) * 1e-9 / (seq - last[0])
            self._period_s = p if self._period_s is None else 0.9 * self._period_s + 0.1 * p

    def reset(self) -> None:
        """A new source stream: forget the last frame (its seq and stamp are of the old stream)."""
        self._last_frame = None

    def detected(self, busy_s: float) -> None:
        """A detection took ``busy_s`` seconds: adapts the stride (when adaptive)."""
        if not self.adaptive:
            return
        self._busy_s.append(float(busy_s))
        if not self._period_s:
            return
        need = float(np.median(self._busy_s)) / self._period_s     # frame intervals per detection
        while self.stride < self.MAX and need > self.stride:
            self.stride *= 2
        while self.stride > 1 and need < self.halve_at * (self.stride // 2):
            self.stride //= 2
