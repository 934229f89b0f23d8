"""Keypoint detector node: camera images -> Keypoints A..E per camera, by a pluggable backend
(common/detector/backends.py).

Inputs, outputs and params: ``needletrack describe detector`` (docs/nodes.md); ``truth`` is for
the oracle, each output carries its image's ``seq``/``stamp_ns``; every param but ``backend``,
``stride`` (below) and ``max_wait`` goes to the backend.

One detector process per camera (only ``left`` or only ``right`` wired) runs the two images of a
frame in parallel, but two processes that each take the newest image when they are free drift
apart and detect different frames, which then never pair (``needletrack bench graph`` counts
the stereo frames/s that do). So such a detector detects only frames
whose ``seq`` is a multiple of its stride, a power of two (``stride: auto``, the default there)
just large enough that a detection fits in ``stride`` frame intervals (the median of the last 15
detection times, the frame stamps, with hysteresis): both cameras' detectors then pick the same
frames whatever their own speed (powers of two nest), and a detector waits for its next frame
instead of starting on a stale one. The other frames count ``stride_skipped``. A number fixes the stride; a
detector with both cameras wired, or whose image inputs keep every message, uses 1.

A backend that needs no image (the oracle) never decodes one; with ``left``/``right`` not wired
it runs on ``truth`` alone, both cameras per frame. A backend that needs the ground truth holds
an image until the truth of its frame arrives (at most ``max_wait`` frames, default 30, then
``Keypoints.not_found``). Images (and, with no image wired, ground truths) that come before
the first calibration wait for it, within the same ``max_wait`` frames (a detector that joins a
running graph hears the source's beacon within a second); when the image input keeps only the
newest message, so does the wait (the older image is dropped and counted ``superseded``); after
that they count ``no_calibration``. A corrupt image gives ``Keypoints.not_found`` and counts
``bad_image``. A ``LockRejected`` on ``lock`` (a feedback input: the refine node's ``lock``, when
the other camera and the track disagree with a camera's detections) makes the backend drop that
camera's tracked crop and search it cold, away from the rejected box first (counted
``lock_rejected.<camera>``; a camera the node does not detect is ignored). What a backend notes of a detection is counted and said once (``last_notes``:
the learned backend's ``found_turned``, a needle found only with the image's hues turned).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, fields, make_dataclass
from typing import Literal

from common.detector.backends import BACKEND_PARAMS, BackendError, load_backend
from common.frames import CAMERAS
from common.runtime.frame_stride import FrameStride
from common.runtime.messages import (
    Calibration,
    CameraImage,
    GroundTruth,
    Keypoints,
    LockRejected,
    MessageError,
)
from common.runtime.node import Node, NodeError, run
from common.runtime.pairing import SeqCache, SeqJoin
from common.runtime.params import merge_schemas


class DetectorNode(Node):
    """Runs a keypoint backend on each camera image (or on the ground truth alone)."""

    INPUTS = {"left": CameraImage, "right": CameraImage, "truth": GroundTruth, "calib": Calibration,
              "lock": LockRejected}
    OUTPUTS = ("left", "right")
    KEEP_ALL = ("truth", "calib", "lock")
    FEEDBACK = ("lock",)

    @dataclass
    class Params:
        backend: str = "oracle"
        max_wait: int = 30
        stride: int | Literal["auto"] = "auto"

    @classmethod
    def param_schema(cls, raw: dict) -> type:
        """The node's own params and those of its backend (``BACKEND_PARAMS``)."""
        name = raw.get("backend", "oracle")
        if name not in BACKEND_PARAMS:
            known = make_dataclass("Backend", [("backend", Literal[tuple(sorted(BACKEND_PARAMS))], "oracle")])
            return merge_schemas("DetectorParams", cls.Params, known)
        return merge_schemas("DetectorParams", BACKEND_PARAMS[name], cls.Params)

    def setup(self):
        theirs = {f.name for f in fields(BACKEND_PARAMS[self.p.backend])}
        params = {k: v for k, v in self.params.items() if k in theirs}
        self.backend_name = self.p.backend
        self.max_wait = self.p.max_wait
        stride = self.p.stride
        one_camera = self.wired("left") != self.wired("right")
        try:
            self.frames = FrameStride(1 if stride == "auto" else int(stride), adaptive=stride == "auto"
                                      and one_camera and not set(self.KEEP_ALL) & {"left", "right"})
        except ValueError:
            raise NodeError(f"params.stride must be 'auto' or a power of two, got {stride!r}") from None
        self.clock = time.perf_counter
        self._noted: set[str] = set()        # the backend's notes said so far (last_notes)
        try:
            self.backend = load_backend(self.backend_name, params)
        except BackendError as exc:
            raise NodeError(str(exc)) from None
        self.calib: Calibration | None = None
        self.truths = SeqCache()
        self.waiting = SeqJoin(self.max_wait)           # images waiting for calibration or truth
        self.waiting_truths = SeqJoin(self.max_wait)    # truth-only: frames waiting for calibration
        self.log.info("detector backend %s", self.backend_name)

    def on_stream_reset(self):
        """A new source stream: truths and waiting frames are of the old one."""
        self.truths.clear()
        self.waiting.reset()
        self.waiting_truths.reset()
        self.frames.reset()
        reset = getattr(self.backend, "reset", None)
        if callable(reset):
            reset()                       # tracking state is of the old stream

    def on_calib(self, msg: Calibration):
        self.calib = msg
        self._release()

    def on_truth(self, msg: GroundTruth):
        self.truths.put(msg.seq, msg)
        if not (self.wired("left") or self.wired("right")):
            self.waiting_truths.hold(msg.seq, msg.seq)
        self._release()

    def on_lock(self, msg: LockRejected):
        """A pose node rejects a camera's detections (the other camera and the track disagree
        with them): the backend drops that camera's tracked crop (``KeypointBackend.reject``).
        A camera this node does not detect is not its business."""
        if not self.wired(msg.camera) and (self.wired("left") or self.wired("right")):
            return
        self.count(f"lock_rejected.{msg.camera}")
        self.backend.reject(msg.camera, msg.bbox)

    def on_left(self, msg: CameraImage):
        self._image(msg)

    def on_right(self, msg: CameraImage):
        self._image(msg)

    # ---------------------------------------------------------------- internals
    def _image(self, msg: CameraImage):
        self.waiting.see(msg.seq)
        self.frames.frame(msg.seq, msg.stamp_ns)
        if not self.frames.takes(msg.seq):
            self.count("stride_skipped")
            return
        if self.calib is None and msg.camera not in self.KEEP_ALL:
            # waiting for the calibration, a newest-only input keeps only its newest image
            self.count("superseded", len(self.waiting.drop(lambda _, w: w.camera == msg.camera)))
        self.waiting.hold(msg.seq, msg)
        self._release()

    def _ready(self, seq: int) -> bool:
        return self.calib is not None and (not self.backend.needs_truth or not self.wired("truth")
                                           or seq in self.truths)

    def _release(self):
        # the lists are cut before anything runs: a frame whose detection raises is gone, not
        # retried (and raising again) on every later message
        due = self.waiting.due(lambda seq, _: self._ready(seq))
        due_truths = self.waiting_truths.due(lambda seq, _: self.calib is not None)
        for img, _ in due:
            self._run(img)
        for seq, _ in due_truths:
            truth = self.truths.get(seq)
            for cam in CAMERAS:
                self._detect(cam, seq, truth.stamp_ns if truth else 0, None)

    @property
    def stride(self) -> int:
        return self.frames.stride

    @property
    def auto_stride(self) -> bool:
        return self.frames.adaptive

    def _run(self, msg: CameraImage):
        if self.calib is None:
            self.count("no_calibration")
            return
        t0 = self.clock()
        self._detect_image(msg)
        self.frames.detected(self.clock() - t0)

    def _detect_image(self, msg: CameraImage):
        image = None
        if self.backend.needs_image:
            try:
                image = msg.to_bgr()
            except MessageError as exc:
                self.count("bad_image")
                self.log.warning("seq %d %s: %s", msg.seq, msg.camera, exc)
                self.publish(msg.camera, Keypoints.not_found(msg.camera, msg.seq, msg.stamp_ns,
                                                             self.backend_name, f"bad image: {exc}"))
                return
        self._detect(msg.camera, msg.seq, msg.stamp_ns, image)

    def _detect(self, camera: str, seq: int, stamp_ns: int, image):
        if self.calib is None:
            self.count("no_calibration")
            return
        kp = self.backend.detect(image, camera, self.truths.get(seq), self.calib, seq=seq, stamp_ns=stamp_ns)
        if not kp.found:
            self.count("not_found")
        for name, sentence in self.backend.last_notes().items():
            if name not in self._noted:               # said once, counted every time
                self._noted.add(name)
                self.log.info("camera %s seq %d: %s", camera, seq, sentence)
            self.count(name)
        self.publish(camera, kp)


NODE = DetectorNode
if __name__ == "__main__":
    run(NODE)
