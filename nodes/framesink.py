"""Stereo frame sink that measures transport: pairs ``left``/``right`` ``CameraImage`` by seq,
views the pixels, and records the latency of each stereo frame (arrival of its second half,
decoded, minus the sender's ``stamp_ns``; same machine clock).

params: ``report`` (a JSON path written at shutdown: latencies, frames, missing seqs),
``log_every_s`` (periodic summary in the log; default 5, 0 = off).
"""
import json
import time
from dataclasses import dataclass

import numpy as np

from common.frames import CAMERAS
from common.runtime.messages import CameraImage
from common.runtime.node import Node, run
from common.runtime.pairing import StereoPairer


class FrameSink(Node):
    """Consumes stereo frames; reports rate and latency."""

    INPUTS = {"left": CameraImage, "right": CameraImage}
    KEEP_ALL = CAMERAS

    @dataclass
    class Params:
        report: str | None = None    # JSON file written at the end
        log_every_s: float = 5.0

    def on_stream_reset(self):
        self.pairer.reset()

    def setup(self):
        self.pairer = StereoPairer(depth=16)
        self.lat_ms: list = []
        self.arrivals: list = []
        self.seqs: list = []
        self.report = self.p.report
        self.log_every = self.p.log_every_s
        self.last_log = time.monotonic()
        self.cpu0 = time.process_time()

    def _half(self, msg: CameraImage):
        img = msg.to_bgr()          # a view of the payload: proves the pixels are usable
        pair = self.pairer.push(msg.camera, msg.seq, (msg, img))
        if pair is None:
            return
        now = time.time_ns()
        (lm, _), (rm, _) = pair
        self.lat_ms.append((now - min(lm.stamp_ns, rm.stamp_ns)) / 1e6)
        self.arrivals.append(time.monotonic())
        self.seqs.append(lm.seq)
        self.count("frames")
        if self.log_every and time.monotonic() - self.last_log > self.log_every:
            self.last_log = time.monotonic()
            lat = np.asarray(self.lat_ms[-300:])
            self.log.info("%d frames; latency p50 %.1f ms p99 %.1f ms", len(self.lat_ms),
                          np.percentile(lat, 50), np.percentile(lat, 99))

    on_left = _half
    on_right = _half

    def teardown(self):
        if not self.report:
            return
        seqs = sorted(self.seqs)
        missing = (seqs[-1] - seqs[0] + 1 - len(seqs)) if seqs else 0
        with open(self.report, "w") as f:
            json.dump({"latency_ms": self.lat_ms, "arrival_s": self.arrivals, "seqs": self.seqs,
                       "frames": len(self.seqs), "missing": missing, "unpaired": self.pairer.dropped,
                       "cpu_s": time.process_time() - self.cpu0}, f)


NODE = FrameSink
if __name__ == "__main__":
    run(NODE)
