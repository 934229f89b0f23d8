"""``rosbag``: plays a ROS 1 ``.bag`` or ROS 2 ``.db3``/``.mcap`` bag as a stereo camera source.

The bag is read with ``common.ros.bag.BagStereo`` (presets ``ambf``/``dvrk``, a topic map;
docs/ros.md): stereo pairs by header stamp, intrinsics, camera poses, ECM pose and the needle's
ground truth, in the project's frames and metres.

Outputs (as ``replay``): ``left``/``right`` (``CameraImage``, ``encoding`` param: ``bgr8`` raw
as a capture card, or ``jpeg``/``png``; ``seq`` = the stereo frame's index in the bag, plus
``loop * frames`` when looping; ``stamp_ns`` the image header stamp), ``measured`` (``EcmPose``
with the bag's ``T_world_ecm`` and joints: wire it to the ``ecm`` node's ``measured`` input),
``truth`` (``GroundTruth`` when the bag has the needle's pose: keypoints projected through the
rig, ``sequence``/``step`` from the needle at rest), ``instruments`` (``InstrumentState`` per
arm of the topic map whose pose and jaw the bag has: ``/PSM1/measured_cp`` and
``/PSM1/jaw/measured_js`` in the dvrk preset), ``calib`` (from the first pair, then once a
second, and at once when the bag's camera_info changes), ``eos`` after the last pair when not
looping.

params: ``path`` (required), ``preset`` (ambf | dvrk | none), ``topics`` (a topic map file or
mapping), ``rate`` (``recorded``: the header stamps' timing; ``max``; or Hz), ``loop``,
``count`` (pairs to play; 0 all), ``encoding`` (bgr8).

A message that does not decode (common/ros/cdr.py) or cannot serve its topic's role (non-finite
calibration or pose, oversized arrays, an image that cannot be decoded) is skipped: counted
``refused_messages``, logged once per topic with its reason; the playback goes on. A bag that
fails part way (a reader error, a frame that cannot be assembled, a value not finite) stops the
source: ``NodeError``, exit status 2, and the launcher says why and stops the graph. An
unfinished MCAP recording plays up to its last complete chunk, with a warning.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

from common.constraints import required
from common.runtime.camera_source import CameraSourceNode
from common.runtime.messages import EndOfStream
from common.runtime.node import NodeError, run
from common.runtime.pacing import SourceClock, parse_rate, sleep_in_slices



class RosbagNode(CameraSourceNode):
    """ROS bag source."""

    OUTPUTS = ("left", "right", "measured", "truth", "instruments", "calib", "eos")

    @dataclass
    class Params:
        path: required("a ROS 1 .bag or ROS 2 .db3/.mcap bag") = ""
        preset: Literal["ambf", "dvrk"] | None = None
        topics: str | dict | None = None
        rate: float | Literal["recorded", "max"] = "recorded"
        loop: bool = False
        count: int = 0
        encoding: Literal["bgr8", "jpeg", "png"] = "bgr8"

    def setup(self):
        from common.ros.bag import BagError
        p = self.p
        try:
            self.rate = parse_rate(p.rate, "rosbag")
            self._open()
            self.first = next(self.it, None)
        except (BagError, ValueError) as exc:
            raise NodeError(str(exc)) from None
        if self.first is None:
            raise NodeError(f"rosbag: {p.path}: no stereo pair in the bag (unpaired: {self.bag.counts})")
        self.log.info("rosbag: %s: topics %s, unit %s", p.path, self.bag.info["topics"], self.bag.info.get("unit"))
        if self.bag.info.get("recovered"):
            self.log.warning("rosbag: %s: %s", p.path, self.bag.info["recovered"])
        from common.ros.source import SamplePublisher
        self.out = SamplePublisher(self, self.bag.needle_model(), f"rosbag {p.path}", self.bag.map.get("ecm"),
                                   p.encoding)
        self.out.rig_key = None
        self.pending = self.first
        self.loops = 0
        self.n_frames = None           # pairs in one pass, known after the first
        self.played = 0
        self.clock = SourceClock(self.rate)

    def _open(self):
        from common.ros.bag import BagStereo
        from common.ros.source import topics_param
        self.bag = BagStereo(self.p.path, self.p.preset, topics_param(self.p.topics), report=self._refused)
        self.it = iter(self.bag)

    def _refused(self, topic: str, reason: str) -> None:
        self.count("refused_messages")
        logged = self.__dict__.setdefault("refused_logged", set())
        if topic not in logged:                 # once per topic, whatever the passes of a loop
            logged.add(topic)
            self.log.warning("rosbag: %s: %s: message skipped (further ones on this topic counted, not logged): %s",
                             self.p.path, topic, reason)

    def _next(self):
        """The next stereo sample (None at the end); NodeError when the bag fails part way (a
        truncated or corrupt record, a frame that cannot be assembled, a value not finite)."""
        from common.ros.bag import BagError
        from common.ros.convert import sample_fault
        s, self.pending = self.pending, None
        try:
            if s is None:
                s = next(self.it, None)
            if s is None and self.p.loop:
                self.n_frames = self.n_frames or self.played
                self.bag.close()
                self._open()
                self.loops += 1
                self.clock.restart()
                s = next(self.it, None)
        except (BagError, ValueError) as exc:
            self.count("bag_errors")
            raise NodeError(f"rosbag: {exc} ({self.played} frames published)") from None
        fault = None if s is None else sample_fault(s, self.bag.info["topics"])
        if fault:
            self.count("bag_errors")
            raise NodeError(f"rosbag: {self.p.path}: frame {s.index} (stamp {s.stamp_ns}): {fault} "
                            f"({self.played} frames published)")
        return s

    def _pace(self, s) -> None:
        sleep_in_slices(self.clock.delay(s.stamp_ns), lambda: self.running, self._publish_calib)

    def step(self):
        from common.ros.convert import RestGroups
        if self.p.count and self.played >= self.p.count:
            s = None
        else:
            s = self._next()     # NodeError: the source stops with exit status 2
        if s is None:
            self.publish("eos", EndOfStream(frames=self.played, stamp_ns=time.time_ns()))
            return False
        if s.index == 0:
            self.out.groups = RestGroups()      # a new pass over the bag
        self.out.calibrate(s)                 # before the first frame, and when camera_info changes
        self._pace(s)
        seq = s.index + self.loops * (self.n_frames or 0)
        self.out.publish(s, seq, s.stamp_ns, 1_000_000 * self.loops)
        self.played += 1
        return True

    def teardown(self):
        bag = getattr(self, "bag", None)
        if bag is not None:
            bag.close()


NODE = RosbagNode
if __name__ == "__main__":
    run(NODE)
