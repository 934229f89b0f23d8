"""Base of the camera source nodes (``sim``, ``replay``): the calibration beacon."""
from __future__ import annotations

import time

from common.runtime.node import Node


class CameraSourceNode(Node):
    """A camera source publishes ``self.calib`` (a ``Calibration``) on its ``calib`` output
    before its first frame (``force=True``) and then at most once a second."""

    calib = None
    last_calib = None

    def _publish_calib(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or self.last_calib is None or now - self.last_calib >= 1.0:
            self.calib.stamp_ns = time.time_ns()
            self.publish("calib", self.calib)
            self.last_calib = now
