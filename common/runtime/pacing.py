"""Pacing of a source: what a source promises about when its frames go out (``Pacer``), and a
recorded source's ``rate`` (``parse_rate``, ``SourceClock``, ``AckWindow``).

Frame k has a slot on a schedule one period apart. A frame never goes out before its slot; one
that is late (the machine was busy) goes out at once, and the schedule keeps its phase. After
a stall longer than a period the schedule is moved up to the present, so the source sends one
extra frame at once instead of bursting out the whole backlog. Slots are therefore always at
least one period apart, but the moments frames are sent are not: a frame sent late is followed
by one sent on time, or at once after a stall. A consumer may rely on the long-run rate and on
never being sent more than two frames within one period; it may not rely on the gap between two
given frames.
"""
from __future__ import annotations

import time
from collections import deque
from typing import Callable


class Pacer:
    """Slots ``1 / rate_hz`` apart starting at the first ``wait``; ``rate_hz <= 0``: no pacing."""

    def __init__(self, rate_hz: float, clock: Callable[[], float] = time.monotonic, start_delay_s: float = 0.0):
        self.period = 1.0 / rate_hz if rate_hz > 0 else 0.0
        self.clock = clock
        self.start_delay_s = start_delay_s
        self.next_slot: float | None = None

    def delay(self) -> float:
        """Seconds until the next frame's slot (<= 0: send now); advances the schedule by one."""
        now = self.clock()
        if self.next_slot is None:
            self.next_slot = now + self.start_delay_s
        slot = self.next_slot
        self.next_slot = max(slot + self.period, now)
        return slot - now

    def wait(self, sleep: Callable[[float], None] = time.sleep) -> None:
        """Sleep until the next frame's slot."""
        d = self.delay()
        if d > 0:
            sleep(d)


PACED = -1.0
"""``parse_rate``'s value for ``paced``: a frame goes out once the last ones are acknowledged."""


def parse_rate(value, node: str = "replay") -> float | None:
    """A recorded source's ``rate`` param: ``recorded`` -> None (the recorded timing), ``max``
    -> 0.0 (at once), ``paced`` -> ``PACED``, else a positive rate in Hz. ``node`` names the
    node in the error."""
    word = None if value is None else str(value).strip().lower()
    if word is None or word == "recorded":
        return None
    if word == "paced":
        return PACED
    if word == "max":
        return 0.0
    try:
        hz = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{node}: rate must be 'recorded', 'max' or a number in Hz, got {value!r}") from None
    if not hz > 0:
        raise ValueError(f"{node}: rate must be positive, got {hz}")
    return hz


class SourceClock:
    """When a recorded source sends its next frame, by ``parse_rate``'s value: at the recorded
    timing (None: the first frame, and the first after ``restart``, at once; each later one its
    recorded stamp's offset after it), at a fixed rate (``Pacer``), or at once (0 or ``PACED``:
    acknowledgements pace it, ``AckWindow``)."""

    def __init__(self, rate: float | None, clock: Callable[[], float] = time.monotonic):
        self.rate, self.clock = rate, clock
        self.pacer = Pacer(rate if rate is not None and rate > 0 else 0.0, clock)
        self._t0: tuple[float, int] | None = None    # (wall, recorded stamp) of the first frame

    def restart(self) -> None:
        """The recording starts again (a loop): the recorded timing starts from the next frame."""
        self._t0 = None

    def delay(self, stamp_ns: int) -> float:
        """Seconds until the frame recorded at ``stamp_ns`` is due (<= 0: now)."""
        now = self.clock()
        if self.rate is None:
            if self._t0 is None:
                self._t0 = (now, stamp_ns)
            return self._t0[0] + (stamp_ns - self._t0[1]) * 1e-9 - now
        if self.rate > 0:
            return self.pacer.delay()
        return 0.0


def sleep_in_slices(delay_s: float, keep_going: Callable[[], bool], between: Callable[[], None],
                    slice_s: float = 0.1, sleep: Callable[[float], None] = time.sleep) -> None:
    """Sleep ``delay_s`` in slices of ``slice_s``, calling ``between()`` after each, stopping
    early once ``keep_going()`` is false (a stop request is honoured within a slice)."""
    while delay_s > 0 and keep_going():
        sleep(min(delay_s, slice_s))
        between()
        delay_s -= slice_s


class AckWindow:
    """``rate: paced``: at most ``in_flight`` frames out and not yet acknowledged on every one
    of the ``inputs`` (an acknowledgement is any message carrying the frame's ``seq``); a frame
    not acknowledged within ``timeout_s`` counts as acknowledged (``timeouts``)."""

    def __init__(self, inputs, in_flight: int = 1, timeout_s: float = 1.0,
                 clock: Callable[[], float] = time.monotonic):
        self.acked = {name: -1 for name in inputs}
        self.in_flight, self.timeout_s, self.clock = max(1, int(in_flight)), timeout_s, clock
        self._out: deque = deque()          # (seq, time sent) of frames not yet acknowledged
        self.timeouts = 0

    def ack(self, name: str, seq: int) -> None:
        self.acked[name] = max(self.acked.get(name, -1), int(seq))

    def sent(self, seq: int) -> None:
        self._out.append((seq, self.clock()))

    def full(self) -> bool:
        """Whether the next frame must wait for an acknowledgement."""
        done = min(self.acked.values()) if self.acked else float("inf")
        now = self.clock()
        while self._out and (self._out[0][0] <= done or now - self._out[0][1] > self.timeout_s):
            if self._out[0][0] > done:
                self.timeouts += 1
            self._out.popleft()
        return len(self._out) >= self.in_flight
