"""Joining a node's inputs by frame ``seq``: stereo pairing of per-camera messages
(``StereoPairer``), messages held until the rest of their frame is in (``SeqJoin``), the same
declared input by input (``FrameJoin``, ``Wait``: which inputs a frame waits for, which it
needs, how long), a bounded cache keyed by ``seq`` (``SeqCache``), and the frame clock
(``SeqClock``) that tells a node when its source restarted or a seq is poison."""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable, Iterable

from common.frames import CAMERAS


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
        if camera not in CAMERAS:
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

    def reset(self) -> None:
        """Forget every pending half and the stream position (a new source stream begins)."""
        self.dropped += len(self._pending)
        self._pending.clear()
        self._newest = {"left": -1, "right": -1}
        self._last_paired = -1

    def _discard(self, stale) -> None:
        for s in [s for s in self._pending if stale(s)]:
            del self._pending[s]
            self.dropped += 1

    def __len__(self) -> int:
        """Frames waiting for their other half."""
        return len(self._pending)


class SeqJoin:
    """Messages held until the rest of their frame is in, at most ``max_wait`` frames.

    ``hold(seq, item)`` holds an item of frame ``seq`` (the newest seq held or ``see``n is the
    stream's position); ``due(ready)`` takes out and returns, in ``seq`` order, the items now
    due as ``(item, complete)``: complete when ``ready(seq, item)`` says the frame's other
    inputs are in, else after ``max_wait`` frames behind the newest (go on without them).
    ``in_order``: items leave strictly in ``seq`` order, one not yet due holding back the later
    ones (a fusion over consecutive frames). The caller counts incomplete items as it sees fit.
    """

    def __init__(self, max_wait: int, in_order: bool = False):
        self.max_wait, self.in_order = int(max_wait), in_order
        self._held: list[tuple[int, object]] = []
        self.newest = -1

    def see(self, seq: int) -> None:
        """A frame ``seq`` was seen on another input: the stream has come this far."""
        self.newest = max(self.newest, seq)

    def hold(self, seq: int, item) -> None:
        self.see(seq)
        self._held.append((seq, item))
        self._held.sort(key=lambda e: e[0])

    def due(self, ready) -> list[tuple[object, bool]]:
        out, keep = [], []
        for i, (seq, item) in enumerate(self._held):
            complete = bool(ready(seq, item))
            if complete or self.newest - seq >= self.max_wait:
                out.append((item, complete))
            elif self.in_order:
                keep.extend(self._held[i:])
                break
            else:
                keep.append((seq, item))
        self._held = keep
        return out

    def drop(self, which=lambda seq, item: True) -> list:
        """Take out, unhandled, the items ``which(seq, item)`` selects; returns them."""
        gone = [item for seq, item in self._held if which(seq, item)]
        self._held = [(seq, item) for seq, item in self._held if not which(seq, item)]
        return gone

    def reset(self) -> list:
        """A new stream: every held item is dropped (returned) and the position forgotten."""
        gone = self.drop()
        self.newest = -1
        return gone

    def __len__(self) -> int:
        return len(self._held)

    def __iter__(self):
        return iter(item for _, item in self._held)


@dataclass(frozen=True)
class Wait:
    """One input a held frame waits for: ``is_in(seq, item)`` says whether it is in for frame
    ``seq``. ``needed``: a frame released without it (after ``max_wait``) is dropped, not used;
    ``missing``: the counter a node adds when the frame goes on without it (None: none)."""
    name: str
    is_in: Callable[[int, object], bool]
    needed: bool = False
    missing: str | None = None


@dataclass(frozen=True)
class Released:
    """A held item let go by ``FrameJoin.due``: ``missing`` names the waits not in (empty: the
    frame is complete), ``dropped`` whether one of them was needed, ``counters`` the counters
    its missing inputs declare (of a dropped item: only the needed ones', why it was dropped)."""
    item: object
    missing: tuple[str, ...] = ()
    dropped: bool = False
    counters: tuple[str, ...] = ()

    @property
    def complete(self) -> bool:
        return not self.missing


class FrameJoin:
    """A node's frame join, declared: items (a stereo pair, a pose, a frame's seq) held until
    every input in ``waits`` (``Wait``) is in for their frame, at most ``max_wait`` frames behind
    the stream's newest (then released without them; without a ``needed`` one, dropped).

    ``hold(seq, item)`` holds an item, ``see(seq)`` moves the stream on (a message of frame
    ``seq`` on another input), ``due()`` takes out the items now due, in ``seq`` order, each a
    ``Released``. ``in_order``: one not yet due holds back the later ones. With no waits an item
    is due at once. The same release rule as ``SeqJoin``, with the waits named once."""

    def __init__(self, waits: Iterable[Wait], max_wait: int, in_order: bool = False):
        self.waits = tuple(waits)
        self._join = SeqJoin(max_wait, in_order)

    @property
    def max_wait(self) -> int:
        return self._join.max_wait

    @property
    def newest(self) -> int:
        return self._join.newest

    def see(self, seq: int) -> None:
        self._join.see(seq)

    def hold(self, seq: int, item) -> None:
        self._join.hold(seq, item)

    def _missing(self, seq: int, item) -> tuple[str, ...]:
        return tuple(w.name for w in self.waits if not w.is_in(seq, item))

    def due(self) -> list[Released]:
        found = {}

        def ready(seq, item):
            missing = self._missing(seq, item)
            found[id(item)] = missing
            return not missing

        out = []
        for item, _complete in self._join.due(ready):
            missing = found[id(item)]
            waits = [w for w in self.waits if w.name in missing]
            dropped = any(w.needed for w in waits)
            # a dropped frame counts why (its needed inputs), a used one each input it lacked
            out.append(Released(item, missing, dropped,
                                tuple(w.missing for w in waits if w.missing and (w.needed or not dropped))))
        return out

    def drop(self, which=lambda seq, item: True) -> list:
        """Take out, unhandled, the items ``which(seq, item)`` selects; returns them."""
        return self._join.drop(which)

    def reset(self) -> list:
        """A new stream: every held item is dropped (returned) and the position forgotten."""
        return self._join.reset()

    def __len__(self) -> int:
        return len(self._join)

    def __iter__(self):
        return iter(self._join)


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


class SeqClock:
    """The frame clock of one node: which source stream (``epoch``) and how far (``seq``) it is.

    Every message that carries a frame ``seq`` passes ``observe(seq, epoch)`` before its handler
    (the runtime does this). A source stamps an ``epoch`` (random, per process) on everything it
    publishes and every node passes it on, so a restarted or swapped-in source is a new stream.
    A message is *in stream* when its epoch is the current one (or either is None) and its seq
    lies at most ``window`` frames behind the newest seen (inputs lag one another) and at most
    ``ahead`` frames beyond it (60: 2 s at 30 Hz; a poison seq just ahead of the stream can
    hold the pairers back no longer than that). Anything else is *off stream*: it is held
    as a candidate and dropped ("outlier") unless the next off-stream message confirms it (same
    epoch, a later seq within ``window`` of it: the new stream moves on, as a real source does
    and a repeated poison frame does not); then the node resynchronises at once ("reset": the
    node clears its per-frame state, then handles the candidate and the confirming message).
    So poison (a far-future seq, a foreign epoch, even a stereo pair of it) costs nothing and
    cannot stall the stream, and a restarted source is followed from its second frame. Messages of the epoch
    just replaced are dropped ("stale") while the new one is alive (seen within the last
    ``alive`` messages), so frames in flight from a killed source do not reset the node again.
    """

    def __init__(self, window: int = 1000, alive: int = 16, ahead: int = 60):
        self.window, self.alive, self.ahead = window, alive, ahead
        self.epoch: int | None = None
        self.newest: int | None = None
        self.previous: int | None = None      # the epoch replaced last
        self.candidate: tuple | None = None   # (epoch, seq) of the last off-stream message
        self._since_current = 0               # messages since the current epoch was last seen
        self.resets = 0

    pinned: bool = False

    def pin(self, epoch: int) -> None:
        """Follow only ``epoch`` (a source's own: its acknowledgements); others are outliers."""
        self.reset()
        self.epoch, self.pinned = epoch, True

    def reset(self) -> None:
        self.epoch = self.newest = self.previous = self.candidate = None
        self._since_current = 0
        self.pinned = False

    def _near(self, seq: int, ref: int) -> bool:
        return ref - self.window <= seq <= ref + self.ahead

    def observe(self, seq: int, epoch: int | None = None) -> str:
        """``"ok"``, ``"reset"`` (a new stream begins with the held candidate), ``"outlier"``
        (dropped, held as candidate) or ``"stale"`` (of the replaced epoch; dropped)."""
        same_epoch = epoch is None or self.epoch is None or epoch == self.epoch
        if self.pinned and not same_epoch:
            return "outlier"
        if self.newest is None:
            self.newest, self.epoch, self.candidate = seq, epoch if epoch is not None else self.epoch, None
            self._since_current = 0
            return "ok"
        if same_epoch and self._near(seq, self.newest):
            self.newest = max(self.newest, seq)
            if self.epoch is None:
                self.epoch = epoch
            self.candidate, self._since_current = None, 0
            return "ok"
        self._since_current += 1
        if epoch is not None and epoch == self.previous and self._since_current <= self.alive:
            return "stale"
        cand = self.candidate
        if (cand is not None and (epoch is None or cand[0] is None or cand[0] == epoch)
                and cand[1] < seq <= cand[1] + self.window):
            if epoch is not None and epoch != self.epoch:
                self.previous = self.epoch
            self.epoch = epoch if epoch is not None else cand[0]
            self.newest = max(seq, cand[1])
            self.candidate, self._since_current = None, 0
            self.resets += 1
            return "reset"
        self.candidate = (epoch, seq)
        return "outlier"
