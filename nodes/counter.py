"""Test/demo source: publishes ``EcmJoints`` with seq 0, 1, 2, ... on ``out`` at ``rate_hz``.

params: ``rate_hz`` (default 20), ``count`` (stop after this many; 0 = forever),
``start_seq`` (default 0). ``q[0]`` carries the seq (as a float) so receivers can check payloads.
"""
import time

import numpy as np

from common.messages import EcmJoints
from common.node import Node, run


class Counter(Node):
    """Counts: one ``EcmJoints`` per tick, seq increasing by one."""

    OUTPUTS = ("out",)

    def setup(self):
        self.period = 1.0 / float(self.params.get("rate_hz", 20.0))
        self.count_max = int(self.params.get("count", 0))
        self.seq = int(self.params.get("start_seq", 0))
        self.sent = 0
        self.next_t = time.monotonic()

    def step(self):
        if self.count_max and self.sent >= self.count_max:
            return False
        delay = self.next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        self.next_t = max(self.next_t + self.period, time.monotonic() - self.period)
        q = np.array([float(self.seq), 0.0, 0.0, 0.0])
        self.publish("out", EcmJoints(seq=self.seq, stamp_ns=time.time_ns(), q=q))
        self.seq += 1
        self.sent += 1
        return True


NODE = Counter
if __name__ == "__main__":
    run(NODE)
