"""``replay``: plays a dataset folder (``docs/dataset.md``) as a stereo camera source.

Outputs as ``sim``: ``left``/``right`` (``CameraImage`` carrying the PNG/JPEG file bytes as
they are, ``seq`` = frame index, plus ``loop * frames`` when looping), ``joints`` (when the
folder has ``ecm_joints``), ``measured`` (``EcmPose`` of a frame with ``T_world_ecm`` but no
joints, e.g. a converted bag: wire it to the ``ecm`` node's ``measured`` input), ``truth`` (when it has any ground truth),
``instruments`` (``InstrumentState`` per instrument of a frame that lists ``instruments``), ``calib`` (before the first
frame, then once a second), and ``eos`` (``EndOfStream``) after the last frame when not looping.
``stamp_ns`` is the wall-clock time of publishing (the recorded stamps set the pace), or with
``stamps: recorded`` the frame's recorded time, shifted so that the first frame is stamped when it
is published: the takes' own timing whatever the pace, so that what keeps time from the stamps
(the tracker's motion models) sees 1/30 s between frames of a 30 Hz take replayed at 10 Hz
(``needletrack eval``); each loop goes on from the last, one frame interval later.

params: ``path`` (the folder, required), ``rate`` (``recorded``: the folder's own timing;
``max``: as fast as possible; ``paced``: as fast as the graph takes frames, closed loop: at
most ``in_flight`` frames (1) are out that not every wired ``ack``/``ack2`` input has answered
with a message of that ``seq`` or later (e.g. both cameras' keypoints: with 1 the detectors
never queue a frame, with 2 the next frame waits a whole detection at each detector: more
latency for the same rate, ``needletrack bench graph``); a frame unanswered for
``ack_timeout`` s (1.0) stops counting (``ack_timeouts``); or a number in Hz; default
recorded), ``loop`` (false),
``start`` (first frame index, 0), ``count`` (frames to play; 0 = all), ``decode`` (false:
send the files' bytes; true: decode every frame once at start-up, hold the images in memory
(6.2 MB per 1080p image) and send them raw (``bgr8``), as a live capture card delivers them:
the consumers then pay no image decoding, which is the storage format's cost, not the
pipeline's; at most ``MAX_DECODED_BYTES``, use ``count`` for longer folders).
A frame whose image file cannot be read (or decoded) is logged, counted (``image_errors``)
and skipped. ``withhold`` (``left`` or ``right``; default none) with ``withhold_share`` (0.3)
and ``withhold_seed``: that camera's image is sent black in one window of each take
(``common.data.withhold``: a lens covered by an instrument), counted ``withheld``; the truth is
sent as it is.
"""
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from common.data.dataset import DatasetError
from common.data.withhold import withheld_frames
from common.frames import CAMERAS
from common.constraints import required
from common.runtime.camera_source import CameraSourceNode
from common.runtime.messages import (
    Calibration,
    CameraImage,
    EcmJoints,
    EcmPose,
    EndOfStream,
    GroundTruth,
    InstrumentState,
)
from common.runtime.node import NodeError, Prepared, run
from common.runtime.pacing import PACED, AckWindow, SourceClock, parse_rate, sleep_in_slices

ACKS = ("ack", "ack2")
MAX_DECODED_BYTES = 8 << 30   # decode=true holds every image in memory: refuse more than 8 GiB


class ReplayNode(CameraSourceNode):
    """Dataset folder source."""

    OUTPUTS = ("left", "right", "joints", "measured", "truth", "instruments", "calib", "eos")
    INPUTS = {"ack": None, "ack2": None}     # any message with a ``seq`` (``rate: paced``)
    FEEDBACK = ("ack", "ack2")               # acknowledgements from downstream: a declared cycle
    KEEP_ALL = ACKS

    @dataclass
    class Params:
        path: required("a dataset folder") = ""
        rate: float | Literal["recorded", "max", "paced"] = "recorded"
        loop: bool = False
        start: int = 0
        count: int = 0                        # 0: to the end
        decode: bool = False
        ack_timeout: float = 1.0
        in_flight: int = 1
        withhold: Literal["left", "right"] | None = None   # this camera's images sent black ...
        withhold_share: float = 0.3                        # ... for this share of each take
        withhold_seed: int = 0
        stamps: Literal["wall", "recorded"] = "wall"       # the time of publishing, or the recorded one

    def setup(self):
        from common.data.dataset import Dataset, DatasetError
        p = self.p
        try:
            self.ds = Dataset(p.path)
            self.rate = parse_rate(p.rate)
        except (DatasetError, ValueError) as exc:
            raise NodeError(str(exc)) from None
        self.loop = p.loop
        start = p.start
        count = p.count
        self.frames = self.ds.frames[start:start + count if count > 0 else None]
        if not self.frames:
            raise NodeError(f"replay: {self.ds.path} has no frames to play (start={start}, count={count})")
        meta = self.ds.meta
        self.calib = Calibration(stamp_ns=0, image_size=np.array(meta.image_size), cameras=meta.rig.to_dict(),
                                 needle=meta.needle.to_dict(), ecm=None if meta.arm is None else meta.arm.to_dict(),
                                 source=f"replay {self.ds.path}" + (f" ({meta.source})" if meta.source else ""))
        try:
            self.withheld = (withheld_frames([fr.sequence for fr in self.frames], p.withhold_share, p.withhold_seed)
                             if p.withhold else None)
        except ValueError as exc:
            raise NodeError(f"replay: params.withhold_share: {exc}") from None
        self._black = None                 # the withheld camera's black image, encoded once
        self.decoded = self._decode_all() if p.decode else None
        self.pos = 0
        self.loops = 0
        self.next_images = None          # (seq, [Prepared left, right]): the next frame, copied
        self.published_frames = 0
        self.last_calib = None
        self.clock = SourceClock(self.rate)
        self.stamp_origin = None           # stamps: recorded: wall-clock time of the first frame less its stamp
        recorded = [fr.stamp_ns for fr in self.frames]
        self.loop_ns = (recorded[-1] - recorded[0]) + (int(np.median(np.diff(recorded))) if len(recorded) > 1 else 0)
        self.acks = AckWindow([name for name in ACKS if self.wired(name)], p.in_flight, p.ack_timeout)
        if self.rate == PACED and not self.acks.acked:
            raise NodeError("replay: rate 'paced' needs an 'ack' input wired (e.g. a detector's keypoints)")

    def on_ack(self, msg):
        self.acks.ack("ack", int(getattr(msg, "seq", -1)))

    def on_ack2(self, msg):
        self.acks.ack("ack2", int(getattr(msg, "seq", -1)))

    def _waiting_for_ack(self) -> bool:
        """``rate: paced``: ``in_flight`` frames are out and not yet acknowledged."""
        if self.rate != PACED:
            return False
        timeouts = self.acks.timeouts
        full = self.acks.full()
        if self.acks.timeouts > timeouts:
            self.count("ack_timeouts", self.acks.timeouts - timeouts)
        return full

    def _decode_all(self) -> list:
        """Per frame: {camera: raw bgr8 bytes}, or None for a frame whose images fail."""
        w, h = self.ds.meta.image_size
        need = len(self.frames) * len(CAMERAS) * w * h * 3
        if need > MAX_DECODED_BYTES:
            raise NodeError(f"replay: decode=true would hold {need / 2**30:.1f} GiB of images "
                             f"({len(self.frames)} frames); play fewer with 'count'")
        out = []
        for fr in self.frames:
            imgs = {}
            for cam in CAMERAS:
                try:
                    img = self.ds.image(fr, cam)      # size and header checked before decoding
                except DatasetError:
                    img = None
                if img is None or img.shape[:2] != (h, w):
                    self.count("image_errors")
                    self.log.error("replay: frames.jsonl:%s: cannot decode the %s image (or not %dx%d)",
                                   fr.line, cam, w, h)
                    imgs = None
                    break
                imgs[cam] = img.tobytes()
            out.append(imgs)
        self.log.info("replay: %d frames decoded into memory", sum(d is not None for d in out))
        return out

    def _images(self, pos: int, seq: int, stamp: int) -> list | None:
        """Frame ``pos``'s two CameraImage messages, or None when its images cannot be read."""
        w, h = self.ds.meta.image_size
        fr = self.frames[pos]
        if self.decoded is not None:
            raw = self.decoded[pos]
            return None if raw is None else [CameraImage(c, seq, stamp, w, h, "bgr8", raw[c]) for c in CAMERAS]
        msgs = []
        for cam in CAMERAS:
            rel = fr.image(cam)
            try:
                data = self.ds.image_bytes(fr, cam)     # size and header checked, not decoded
            except (OSError, DatasetError) as exc:
                self.count("image_errors")
                self.log.error("replay: cannot read image: %s", exc)
                return None
            enc = "png" if rel.lower().endswith(".png") else "jpeg"
            msgs.append(CameraImage(cam, seq, stamp, w, h, enc, data))
        return msgs

    def _pace(self, fr) -> None:
        if self.pos == 0:
            self.clock.restart()          # the recorded timing starts again with each pass
        sleep_in_slices(self.clock.delay(fr.stamp_ns), lambda: self.running, self._publish_calib)

    def _frame_stamp(self, fr) -> int:
        """The frame's ``stamp_ns`` (``stamps``: module docstring)."""
        now = time.time_ns()
        if self.p.stamps == "wall":
            return now
        if self.stamp_origin is None:
            self.stamp_origin = now - fr.stamp_ns
        return int(fr.stamp_ns + self.stamp_origin + self.loops * self.loop_ns)

    def step(self):
        if self.pos >= len(self.frames):
            if not self.loop:
                self.publish("eos", EndOfStream(frames=self.published_frames, stamp_ns=time.time_ns()))
                return False
            self.pos = 0
            self.loops += 1
        if self.published_frames == 0 and self.last_calib is None:
            self._publish_calib(force=True)
        if self._waiting_for_ack():
            self.wait_for_input(0.005)   # the next ack (what this wait costs: needletrack bench graph, CPU per frame)
            self._publish_calib()
            return True
        fr = self.frames[self.pos]
        self._pace(fr)
        seq = self._seq(self.pos, self.loops)
        stamp = self._frame_stamp(fr)
        ready, self.next_images = self.next_images, None
        msgs = ready[1] if ready is not None and ready[0] == seq else self._images(self.pos, seq, stamp)
        if msgs is None:     # counted and logged
            self.pos += 1
            return True
        if self.withheld is not None and self.withheld[self.pos]:
            msgs = [self._blacked(seq, stamp) if cam == self.p.withhold else m for cam, m in zip(CAMERAS, msgs)]
            self.count("withheld")
        for cam, msg in zip(CAMERAS, msgs):
            if isinstance(msg, Prepared):
                msg.msg.stamp_ns = stamp
            self.publish(cam, msg)
        if fr.ecm_joints is not None:
            self.publish("joints", EcmJoints(seq, stamp, np.asarray(fr.ecm_joints, float)))
        elif fr.T_world_ecm is not None:
            self.publish("measured", EcmPose(seq, stamp, np.asarray(fr.T_world_ecm, float)))
        truth = GroundTruth.from_frame(fr, seq, stamp)
        if truth is not None:
            self.publish("truth", truth)
        for name, pose in (fr.instruments or {}).items():
            self.publish("instruments", InstrumentState.from_pose(name, pose, seq, stamp))
        self.published_frames += 1
        if self.rate == PACED:
            self.acks.sent(seq)
        self.pos += 1
        self._publish_calib()
        self._prepare_next()
        return True

    def _blacked(self, seq: int, stamp: int) -> CameraImage:
        """The withheld camera's image: black, the frame's size (a PNG of a few kB)."""
        if self._black is None:
            w, h = self.ds.meta.image_size
            self._black = CameraImage.from_bgr(self.p.withhold, 0, 0, np.zeros((h, w, 3), np.uint8), "png")
        return CameraImage(self.p.withhold, seq, stamp, self._black.width, self._black.height, "png", self._black.data)

    def _seq(self, pos: int, loops: int) -> int:
        """``seq`` of frame ``pos`` on pass ``loops`` over the folder."""
        return self.frames[pos].index + loops * len(self.ds.frames)

    def _prepare_next(self) -> None:
        """Copy the next frame's images into shared memory now, while the graph works on this
        one (as a capture card fills its next buffer): sending it then costs only the headers,
        ~3.5 ms less between the decision to send and the detectors' start."""
        pos, loops = self.pos, self.loops
        if pos >= len(self.frames):
            if not self.loop:
                return
            pos, loops = 0, loops + 1
        seq = self._seq(pos, loops)
        # stamped when sent; a placeholder of the same encoded size keeps the header length
        msgs = self._images(pos, seq, time.time_ns())   # None (counted and logged once) is kept too
        self.next_images = (seq, None if msgs is None else [self.prepare(m) for m in msgs])


NODE = ReplayNode
if __name__ == "__main__":
    run(NODE)
