"""Stereo pairing of per-camera messages by frame ``seq``, and a bounded cache keyed by ``seq``."""
from __future__ import annotations

from collections import OrderedDict


class StereoPairer:
    """Buffers left/right items by ``seq`` and returns a pair once both halves are in.

    Each camera's stream is assumed to arrive in increasing ``seq`` (one publisher per camera),
    so a half waits exactly as long as its partner can still come: it is discarded (counted in
    ``dropped``) once the other camera has delivered a later frame, or once a later frame has
    been paired. A camera that lags at start-up therefore loses no frame. ``depth`` only bounds
    the memory when the other camera stops altogether: at most ``depth`` frames wait, the
    oldest going first.
    """

    def __init__(self, depth: int = 64):
        self.depth = depth
        self._pending: dict[int, dict] = {}
        self._newest = {"left": -1, "right": -1}
        self.dropped = 0
        self._last_paired = -1

    def push(self, camera: str, seq: int, item):
        """Add one half; returns ``(left, right)`` when the frame is complete, else None."""
        if camera not in ("left", "right"):
            raise ValueError(f"camera must be 'left' or 'right', got {camera!r}")
        other = "right" if camera == "left" else "left"
        if seq <= self._last_paired or (seq < self._newest[other] and seq not in self._pending):
            self.dropped += 1          # a later frame is paired, or the other camera skipped this one
            return None
        self._newest[camera] = max(self._newest[camera], seq)
        halves = self._pending.setdefault(seq, {})
        halves[camera] = item
        if len(halves) == 2:
            del self._pending[seq]
            self._last_paired = seq
            self._discard(lambda s: s < seq)
            return halves["left"], halves["right"]
        # halves of this camera's earlier frames stay; the other camera's earlier ones never pair
        self._discard(lambda s: s < seq and other in self._pending[s])
        while len(self._pending) > self.depth:
            del self._pending[min(self._pending)]
            self.dropped += 1
        return None

    def _discard(self, stale) -> None:
        for s in [s for s in self._pending if stale(s)]:
            del self._pending[s]
            self.dropped += 1

    def __len__(self) -> int:
        """Frames waiting for their other half."""
        return len(self._pending)


class SeqCache(OrderedDict):
    """A dict keyed by frame ``seq`` that keeps only the newest ``size`` entries."""

    def __init__(self, size: int = 256):
        super().__init__()
        self.size = size

    def put(self, seq: int, value) -> None:
        self[seq] = value
        self.move_to_end(seq)
        while len(self) > self.size:
            self.popitem(last=False)
