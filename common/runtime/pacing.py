"""Fixed-rate pacing of a source: what a source promises about when its frames go out.

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
