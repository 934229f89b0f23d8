"""Test/demo source: publishes one fixed ``PoseEstimate`` per tick on ``pose`` (seq 0, 1, 2, ...).

The needle lies ``distance_mm`` in front of the ECM (on its optical axis), unrotated: a pose
stream for fusion and the consumers of poses without cameras or detectors (e.g. the two-host
TLS test). params: ``rate_hz`` (20), ``count`` (stop after this many; 0 = forever),
``distance_mm`` (100), ``method`` ("posesource").
"""
import time
from dataclasses import dataclass

import numpy as np

from common.constraints import PositiveNumber
from common.runtime.messages import PoseEstimate
from common.runtime.node import Node, run
from common.runtime.pacing import Pacer


class PoseSource(Node):
    """One fixed pose estimate per tick."""

    OUTPUTS = ("pose",)

    @dataclass
    class Params:
        rate_hz: PositiveNumber = 20.0
        count: int = 0           # 0: forever
        distance_mm: float = 100.0
        method: str = "posesource"

    def setup(self):
        self.T = np.eye(4)
        self.T[2, 3] = self.p.distance_mm * 1e-3
        self.seq = 0
        self.pacer = Pacer(self.p.rate_hz)

    def step(self):
        if self.p.count and self.seq >= self.p.count:
            return False
        self.pacer.wait()
        self.publish("pose", PoseEstimate(self.seq, time.time_ns(), self.p.method, self.T.copy(),
                                          residual=0.0, residual_unit="m"))
        self.seq += 1
        return True


NODE = PoseSource
if __name__ == "__main__":
    run(NODE)
