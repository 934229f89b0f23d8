"""Keypoint detector node: camera images -> Keypoints A..E per camera, by a pluggable backend
(common/keypoint_backends.py).

Inputs: ``left``, ``right`` (CameraImage), ``truth`` (GroundTruth, for the oracle), ``calib``
(Calibration). Outputs: ``left``, ``right`` (Keypoints with the image's ``seq``/``stamp_ns``).

Params: ``backend`` (default ``oracle``); every other param goes to the backend (oracle:
``noise_px``, ``missing_prob``, ``outlier_prob``, ``outlier_px``, ``seed``).

A backend that needs no image (the oracle) never decodes one; with ``left``/``right`` not wired
it runs on ``truth`` alone, both cameras per frame. A backend that needs the ground truth holds
an image until the truth of its frame arrives (at most ``max_wait`` frames, default 30, then
``Keypoints.not_found``). A corrupt image gives ``Keypoints.not_found`` and counts
``bad_image``; frames before the first calibration count ``no_calibration``.
"""
from __future__ import annotations

from common.keypoint_backends import load_backend
from common.messages import CameraImage, Calibration, GroundTruth, Keypoints, MessageError
from common.node import Node, run
from common.pose_node import SeqCache


class DetectorNode(Node):
    """Runs a keypoint backend on each camera image (or on the ground truth alone)."""

    INPUTS = {"left": CameraImage, "right": CameraImage, "truth": GroundTruth, "calib": Calibration}
    OUTPUTS = ("left", "right")
    KEEP_ALL = ("truth", "calib")

    def setup(self):
        params = dict(self.params)
        self.backend_name = str(params.pop("backend", "oracle"))
        self.max_wait = int(params.pop("max_wait", 30))
        self.backend = load_backend(self.backend_name, params)
        self.calib: Calibration | None = None
        self.truths = SeqCache()
        self.waiting: list[CameraImage] = []         # images waiting for their frame's truth
        self.newest_seq = -1
        self.log.info("detector backend %s", self.backend_name)

    def on_calib(self, msg: Calibration):
        self.calib = msg

    def on_truth(self, msg: GroundTruth):
        self.truths.put(msg.seq, msg)
        if not (self.wired("left") or self.wired("right")):
            for cam in ("left", "right"):
                self._detect(cam, msg.seq, msg.stamp_ns, None)
            return
        self._release()

    def on_left(self, msg: CameraImage):
        self._image(msg)

    def on_right(self, msg: CameraImage):
        self._image(msg)

    # ---------------------------------------------------------------- internals
    def _image(self, msg: CameraImage):
        self.newest_seq = max(self.newest_seq, msg.seq)
        if self.backend.needs_truth and self.wired("truth") and msg.seq not in self.truths:
            self.waiting.append(msg)
        else:
            self._run(msg)
        self._release()

    def _release(self):
        keep = []
        for img in self.waiting:
            if img.seq in self.truths or self.newest_seq - img.seq >= self.max_wait:
                self._run(img)
            else:
                keep.append(img)
        self.waiting = keep

    def _run(self, msg: CameraImage):
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
        self.publish(camera, kp)


NODE = DetectorNode
if __name__ == "__main__":
    run(NODE)
