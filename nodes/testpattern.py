"""Synthetic stereo camera: publishes ``CameraImage`` pairs (outputs ``left``/``right``,
sharing ``seq``) of a fixed test pattern at ``rate_hz``; ``stamp_ns`` is the wall-clock time
just before encoding, so receivers on this machine can measure latency.

params: ``rate_hz`` (30; 0 = as fast as possible), ``width`` (1920), ``height`` (1080),
``encoding`` (bgr8 | png | jpeg), ``count`` (stop after this many frames; 0 = forever),
``start_delay_s`` (wait before the first frame, so that subscribers are connected; default 0),
``report`` (a JSON path: frames sent and the process's CPU seconds, written at shutdown).
"""
import json
import time
from dataclasses import dataclass

import numpy as np

from common.frames import CAMERAS
from common.runtime.messages import CameraImage
from common.runtime.node import Node, run
from common.runtime.pacing import Pacer


def pattern_image(width: int, height: int, shift: int = 0) -> np.ndarray:
    """An (h, w, 3) uint8 BGR gradient with a grid, shifted ``shift`` px right."""
    x = (np.arange(width) + shift) % 256
    y = np.arange(height) % 256
    img = np.empty((height, width, 3), np.uint8)
    img[..., 0] = x[None, :]
    img[..., 1] = y[:, None]
    img[..., 2] = 128
    img[::64, :, :] = 255
    img[:, ::64, :] = 255
    return img


class TestPattern(Node):
    """Stereo test-pattern source."""

    OUTPUTS = ("left", "right")

    @dataclass
    class Params:
        rate_hz: float = 30.0      # 0: as fast as it goes
        width: int = 1920
        height: int = 1080
        encoding: str = "bgr8"
        count: int = 0
        start_delay_s: float = 0.0
        report: str | None = None

    def setup(self):
        rate = self.p.rate_hz
        self.w, self.h = self.p.width, self.p.height
        self.encoding = self.p.encoding
        self.count_max = self.p.count
        self.images = {"left": pattern_image(self.w, self.h, 0), "right": pattern_image(self.w, self.h, 8)}
        # bgr8 frames are built once as bytes, like a driver handing out its buffer: the
        # transport benchmark then measures the transport, not an array-to-bytes copy
        self.raw = {cam: img.tobytes() for cam, img in self.images.items()} if self.encoding == "bgr8" else None
        self.seq = 0
        self.cpu0 = time.process_time()
        self.pacer = Pacer(rate, start_delay_s=self.p.start_delay_s)

    def step(self):
        if self.count_max and self.seq >= self.count_max:
            return False
        self.pacer.wait()
        for cam in CAMERAS:
            if self.raw is not None:
                msg = CameraImage(cam, self.seq, time.time_ns(), self.w, self.h, "bgr8", self.raw[cam])
            else:
                msg = CameraImage.from_bgr(cam, self.seq, time.time_ns(), self.images[cam], self.encoding)
            self.publish(cam, msg)
        self.seq += 1
        return True

    def teardown(self):
        if self.p.report:
            with open(self.p.report, "w") as f:
                json.dump({"frames": self.seq, "cpu_s": time.process_time() - self.cpu0}, f)


NODE = TestPattern
if __name__ == "__main__":
    run(NODE)
