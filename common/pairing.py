"""Pair per-camera messages of one stereo frame by their frame sequence number."""
from __future__ import annotations


class StereoPairer:
    """Buffers left/right items by ``seq`` and returns a pair once both halves are in.

    Only the newest ``depth`` sequence numbers are kept: an older half whose partner never
    comes (dropped as stale upstream) is discarded and counted in ``dropped``.
    """

    def __init__(self, depth: int = 8):
        self.depth = depth
        self._pending: dict[int, dict] = {}
        self.dropped = 0
        self._last_paired = -1

    def push(self, camera: str, seq: int, item):
        """Add one half; returns ``(left, right)`` when the frame is complete, else None."""
        if camera not in ("left", "right"):
            raise ValueError(f"camera must be 'left' or 'right', got {camera!r}")
        if seq <= self._last_paired:
            self.dropped += 1
            return None
        halves = self._pending.setdefault(seq, {})
        halves[camera] = item
        if len(halves) == 2:
            del self._pending[seq]
            self._last_paired = seq
            for old in [s for s in self._pending if s < seq]:
                del self._pending[old]
                self.dropped += 1
            return halves["left"], halves["right"]
        while len(self._pending) > self.depth:
            del self._pending[min(self._pending)]
            self.dropped += 1
        return None
