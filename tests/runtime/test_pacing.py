"""Fixed-rate pacing of the sources (common/runtime/pacing.py) on a clock of the test's own."""
from common.runtime.pacing import Pacer


class FakeClock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t

    def sleep(self, s):
        self.t += s


def sent_times(pacer, clock, work):
    """When each frame goes out, with ``work[k]`` seconds spent after sending frame k."""
    out = []
    for w in work:
        pacer.wait(clock.sleep)
        out.append(clock.t)
        clock.t += w
    return out


def test_an_idle_source_sends_one_frame_per_period():
    clock = FakeClock()
    t = sent_times(Pacer(20, clock), clock, [0.001] * 10)
    assert [round(b - a, 9) for a, b in zip(t, t[1:])] == [0.05] * 9


def test_a_late_frame_keeps_the_phase_and_the_next_goes_on_time():
    clock = FakeClock()
    t = sent_times(Pacer(20, clock), clock, [0.001, 0.07, 0.001, 0.001, 0.001])
    # frame 1 went at +0.05 and took 70 ms: frame 2, due at +0.10, goes 20 ms late
    assert round(t[2] - t[0], 9) == 0.12
    assert round(t[3] - t[0], 9) == 0.15         # back on the schedule: the gap 2->3 is 30 ms
    assert round(t[4] - t[0], 9) == 0.20


def test_after_a_stall_the_source_catches_up_by_one_frame_not_the_backlog():
    clock = FakeClock()
    t = sent_times(Pacer(20, clock), clock, [0.001, 1.0] + [0.001] * 6)
    after = [round(x - t[2], 9) for x in t[2:]]
    assert after[:2] == [0.0, 0.001]             # one extra frame at once ...
    assert after[2] == 0.05                      # ... then one per period again
    # never more than two frames inside one period
    assert all(t[k + 2] - t[k] >= 0.05 - 1e-9 for k in range(len(t) - 2))


def test_no_rate_means_no_waiting_but_a_start_delay():
    clock = FakeClock()
    t = sent_times(Pacer(0, clock, start_delay_s=0.5), clock, [0.0] * 3)
    assert t == [100.5, 100.5, 100.5]


def test_source_clock_recorded_timing_restarts_with_each_pass():
    from common.runtime.pacing import SourceClock
    t = [100.0]
    clock = SourceClock(None, clock=lambda: t[0])
    assert clock.delay(5_000_000_000) == 0.0            # the first frame: at once
    assert abs(clock.delay(5_500_000_000) - 0.5) < 1e-9   # 0.5 s of recording later
    t[0] = 100.7
    assert abs(clock.delay(6_000_000_000) - 0.3) < 1e-9
    clock.restart()
    assert clock.delay(5_000_000_000) == 0.0
    assert SourceClock(0.0).delay(0) == 0.0 and SourceClock(-1.0).delay(0) == 0.0


def test_ack_window_waits_for_every_input_and_times_out():
    from common.runtime.pacing import AckWindow
    t = [0.0]
    w = AckWindow(["ack", "ack2"], in_flight=2, timeout_s=1.0, clock=lambda: t[0])
    w.sent(0)
    assert not w.full()
    w.sent(1)
    assert w.full()
    w.ack("ack", 0)
    assert w.full()                      # ack2 has not seen frame 0
    w.ack("ack2", 0)
    assert not w.full()
    w.sent(2)
    t[0] = 1.5                           # frames 1 and 2 were never acknowledged
    assert not w.full() and w.timeouts == 2


def test_parse_rate_names_the_node():
    import pytest
    from common.runtime.pacing import PACED, parse_rate
    assert parse_rate("paced") == PACED and parse_rate(" MAX ") == 0.0 and parse_rate(None) is None
    with pytest.raises(ValueError, match="rosbag: rate must be positive"):
        parse_rate(-2, "rosbag")
