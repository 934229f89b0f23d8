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

import numpy as np

from common.messages import CameraImage
from common.node import Node, run


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

    def setup(self):
        rate = float(self.params.get("rate_hz", 30.0))
        self.period = 1.0 / rate if rate > 0 else 0.0
        self.w, self.h = int(self.params.get("width", 1920)), int(self.params.get("height", 1080))
        self.encoding = str(self.params.get("encoding", "bgr8"))
        self.count_max = int(self.params.get("count", 0))
        self.images = {"left": pattern_image(self.w, self.h, 0), "right": pattern_image(self.w, self.h, 8)}
        # bgr8 frames are built once as bytes, like a driver handing out its buffer: the
        # transport benchmark then measures the transport, not an array-to-bytes copy
        self.raw = {cam: img.tobytes() for cam, img in self.images.items()} if self.encoding == "bgr8" else None
        self.seq = 0
        self.cpu0 = time.process_time()
        self.next_t = time.monotonic() + float(self.params.get("start_delay_s", 0.0))

    def step(self):
        if self.count_max and self.seq >= self.count_max:
            return False
        if self.period or self.seq == 0:
            delay = self.next_t - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            self.next_t = max(self.next_t + self.period, time.monotonic() - self.period)
        for cam in ("left", "right"):
            if self.raw is not None:
                msg = CameraImage(cam, self.seq, time.time_ns(), self.w, self.h, "bgr8", self.raw[cam])
            else:
                msg = CameraImage.from_bgr(cam, self.seq, time.time_ns(), self.images[cam], self.encoding)
            self.publish(cam, msg)
        self.seq += 1
        return True

    def teardown(self):
        if self.params.get("report"):
            with open(self.params["report"], "w") as f:
                json.dump({"frames": self.seq, "cpu_s": time.process_time() - self.cpu0}, f)


NODE = TestPattern
if __name__ == "__main__":
    run(NODE)
