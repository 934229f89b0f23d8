"""Test/demo source: publishes ``EcmJoints`` with seq 0, 1, 2, ... on ``out`` at ``rate_hz``.

params: ``rate_hz`` (default 20), ``count`` (stop after this many; 0 = forever),
``start_seq`` (default 0). ``q[0]`` carries the seq (as a float) so receivers can check payloads.
"""
import time
from dataclasses import dataclass

import numpy as np

from common.constraints import PositiveNumber
from common.runtime.messages import EcmJoints
from common.runtime.node import Node, run
from common.runtime.pacing import Pacer


class Counter(Node):
    """Counts: one ``EcmJoints`` per tick, seq increasing by one."""

    OUTPUTS = ("out",)

    @dataclass
    class Params:
        rate_hz: PositiveNumber = 20.0
        count: int = 0           # 0: forever
        start_seq: int = 0

    def setup(self):
        self.count_max = self.p.count
        self.seq = self.p.start_seq
        self.sent = 0
        self.pacer = Pacer(self.p.rate_hz)

    def step(self):
        if self.count_max and self.sent >= self.count_max:
            return False
        self.pacer.wait()
        q = np.array([float(self.seq), 0.0, 0.0, 0.0])
        self.publish("out", EcmJoints(seq=self.seq, stamp_ns=time.time_ns(), q=q))
        self.seq += 1
        self.sent += 1
        return True


NODE = Counter
if __name__ == "__main__":
    run(NODE)
