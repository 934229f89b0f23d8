"""Test/demo node standing in for a detector backend: each input frame (any message with a
``seq``) becomes a ``Keypoints`` on ``out`` whose ``detector`` field is ``params.tag``, so a
consumer can tell which implementation produced a frame (used to test hot swap).

params: ``tag`` (default "tagger"), ``fail_every`` (raise in the handler every N-th frame; 0 = never),
``delay_s`` (sleep this long in the handler: a slow backend; default 0).
"""
import time
from dataclasses import dataclass

import numpy as np

from common.runtime.messages import Keypoints
from common.runtime.node import Node, run


class Tagger(Node):
    """Frame seq in, tagged Keypoints out."""

    INPUTS = {"in": None}
    OUTPUTS = ("out",)

    @dataclass
    class Params:
        tag: str = "tagger"
        fail_every: int = 0
        delay_s: float = 0.0

    def setup(self):
        self.tag = self.p.tag
        self.fail_every = self.p.fail_every
        self.delay_s = self.p.delay_s

    def on_in(self, msg):
        seq = int(msg.seq)
        if self.fail_every and seq % self.fail_every == 0:
            raise RuntimeError(f"failing on purpose at seq {seq}")
        if self.delay_s > 0:
            time.sleep(self.delay_s)
        uv = np.full((5, 2), float(seq))
        self.publish("out", Keypoints(camera="left", seq=seq, stamp_ns=int(getattr(msg, "stamp_ns", 0)),
                                      found=True, uv=uv, scores=np.ones(5), confidence=1.0, detector=self.tag))


NODE = Tagger
if __name__ == "__main__":
    run(NODE)
