"""``replay``: plays a dataset folder (``shared/specs/dataset.md``) as a stereo camera source.

Outputs as ``sim``: ``left``/``right`` (``CameraImage`` carrying the PNG/JPEG file bytes as
they are, ``seq`` = frame index, plus ``loop * frames`` when looping), ``joints`` (when the
folder has ``ecm_joints``), ``truth`` (when it has any ground truth), ``calib`` (before the first
frame, then once a second), and ``eos`` (``EndOfStream``) after the last frame when not looping.
``stamp_ns`` is the wall-clock time of publishing (the recorded stamps set the pace).

params: ``path`` (the folder, required), ``rate`` (``recorded``: the folder's own timing;
``max``: as fast as possible; or a number in Hz; default recorded), ``loop`` (false),
``start`` (first frame index, 0), ``count`` (frames to play; 0 = all).
A frame whose image file cannot be read is logged, counted (``image_errors``) and skipped.
"""
import os
import time

import numpy as np

from common.messages import Calibration, CameraImage, EcmJoints, EndOfStream, GroundTruth
from common.camera_source import CameraSourceNode
from common.node import run

CAMS = ("left", "right")


def parse_rate(value) -> float | None:
    """``recorded`` -> None, ``max`` -> 0.0, else a positive rate in Hz."""
    if value is None or str(value).strip().lower() == "recorded":
        return None
    if str(value).strip().lower() == "max":
        return 0.0
    try:
        hz = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"replay: rate must be 'recorded', 'max' or a number in Hz, got {value!r}") from None
    if not hz > 0:
        raise ValueError(f"replay: rate must be positive, got {hz}")
    return hz


def truth_message(fr, seq: int, stamp_ns: int):
    """The frame's ground truth as a GroundTruth message, or None if it has none."""
    if all(getattr(fr, k) is None for k in ("T_world_needle", "keypoints", "visible", "bbox", "T_world_ecm")):
        return None
    return GroundTruth(
        seq=seq, stamp_ns=stamp_ns, sequence=fr.sequence, step=fr.step, ecm_joints=fr.ecm_joints,
        T_world_ecm=fr.T_world_ecm, T_world_needle=fr.T_world_needle,
        keypoints=None if fr.keypoints is None else {c: np.asarray(fr.keypoints[c], float) for c in CAMS},
        visible=None if fr.visible is None else {c: np.asarray(fr.visible[c], bool) for c in CAMS},
        bbox=None if fr.bbox is None else {c: None if fr.bbox[c] is None else np.asarray(fr.bbox[c], float)
                                           for c in CAMS})


class ReplayNode(CameraSourceNode):
    """Dataset folder source."""

    OUTPUTS = ("left", "right", "joints", "truth", "calib", "eos")

    def setup(self):
        from common.dataset import Dataset
        p = self.params
        if not p.get("path"):
            raise ValueError("replay: param 'path' (a dataset folder) is required")
        self.ds = Dataset(str(p["path"]))
        self.rate = parse_rate(p.get("rate", "recorded"))
        self.loop = bool(p.get("loop", False))
        start = int(p.get("start", 0))
        count = int(p.get("count", 0))
        self.frames = self.ds.frames[start:start + count if count > 0 else None]
        if not self.frames:
            raise ValueError(f"replay: {self.ds.path} has no frames to play (start={start}, count={count})")
        meta = self.ds.meta
        self.calib = Calibration(stamp_ns=0, image_size=np.array(meta.image_size), cameras=meta.rig.to_dict(),
                                 needle=meta.needle.to_dict(), ecm=None if meta.arm is None else meta.arm.to_dict(),
                                 source=f"replay {self.ds.path}" + (f" ({meta.source})" if meta.source else ""))
        self.pos = 0
        self.loops = 0
        self.published_frames = 0
        self.last_calib = None
        self.t0_wall = None
        self.t0_rec = None
        self.next_t = None

    def _pace(self, fr) -> None:
        now = time.monotonic()
        if self.rate is None:  # the recorded timing
            if self.t0_wall is None or self.pos == 0:
                self.t0_wall, self.t0_rec = now, fr.stamp_ns
            delay = self.t0_wall + (fr.stamp_ns - self.t0_rec) * 1e-9 - now
        elif self.rate > 0:
            if self.next_t is None:
                self.next_t = now
            delay = self.next_t - now
            self.next_t = max(self.next_t + 1.0 / self.rate, now - 1.0 / self.rate)
        else:
            delay = 0.0
        while delay > 0 and self.running:  # sleep in slices so a stop request is honoured
            time.sleep(min(delay, 0.1))
            self._publish_calib()
            delay -= 0.1

    def step(self):
        if self.pos >= len(self.frames):
            if not self.loop:
                self.publish("eos", EndOfStream(frames=self.published_frames, stamp_ns=time.time_ns()))
                return False
            self.pos = 0
            self.loops += 1
        if self.published_frames == 0 and self.last_calib is None:
            self._publish_calib(force=True)
        fr = self.frames[self.pos]
        self._pace(fr)
        seq = fr.index + self.loops * len(self.ds.frames)
        stamp = time.time_ns()
        w, h = self.ds.meta.image_size
        msgs = []
        try:
            for cam in CAMS:
                rel = fr.image(cam)
                with open(os.path.join(self.ds.path, rel), "rb") as f:
                    data = f.read()
                enc = "png" if rel.lower().endswith(".png") else "jpeg"
                msgs.append(CameraImage(cam, seq, stamp, w, h, enc, data))
        except OSError as exc:
            self.count("image_errors")
            self.log.error("replay: frames.jsonl:%s: cannot read image: %s", fr.line, exc)
            self.pos += 1
            return True
        for cam, msg in zip(CAMS, msgs):
            self.publish(cam, msg)
        if fr.ecm_joints is not None:
            self.publish("joints", EcmJoints(seq, stamp, np.asarray(fr.ecm_joints, float)))
        truth = truth_message(fr, seq, stamp)
        if truth is not None:
            self.publish("truth", truth)
        self.published_frames += 1
        self.pos += 1
        self._publish_calib()
        return True


NODE = ReplayNode
if __name__ == "__main__":
    run(NODE)
