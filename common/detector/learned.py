"""The detector node's ``learned`` backend: the keypoint network (``KeypointDetector``) behind the
backend interface (``common.detector.backends``), with the calibration's lens distortion."""
from __future__ import annotations

import numpy as np

from common.detector.backends import BackendError, KeypointBackend
from common.detector.config import DetectorConfig
from common.detector.inference import KeypointDetector
from common.detector.weights import ModelFileError
from common.runtime.messages import Keypoints
from common.runtime.params import config_from


class LearnedBackend(KeypointBackend):
    """Backend ``learned`` of the detector node. Params: ``weights`` (default
    models/keypoint/model.pt), ``device`` (auto | cpu | cuda), ``threshold`` (null: the weights' fitted
    presence gate, ``presence_gate.json`` beside them, else 0.5), ``tracking``
    (true), ``threads`` (torch threads, default 1: in a graph the other nodes share the cores, and
    torch's threads then wait on each other; run one detector per camera for parallelism),
    ``refine`` (true), ``centreline`` (true), ``subpixel`` (true: the centreline refined in the
    full-resolution image), ``min_extent_px`` (10: keypoints closer together are "no needle"),
    ``max_ellipse_px`` (0.25: a sub-pixel centreline farther from one ellipse is "no needle"; 0: off),
    ``keypoints_only_ellipse_px`` (1.5: up to this far, the keypoints are stated without the centreline),
    ``arc_bcd`` (true), ``along_arc`` (false), ``proposals`` (stage-1 proposals tried, 3),
    ``proposal_threshold`` (0.2), ``ridge_ends`` (true: A and E from the centreline's ends when their heatmaps collapse on one),
    ``retry_hues`` (null: ``RETRY_HUES_DEG``; a cold frame where nothing passes is searched again with its hues turned)."""

    name = "learned"
    needs_image = True

    def __init__(self, params=None):
        super().__init__(params)
        p = self.p
        try:
            self.detector = KeypointDetector(p.weights, device=p.device, threads=p.threads,
                                             config=config_from(DetectorConfig, p))
        except (ModelFileError, ValueError, TypeError) as exc:
            raise BackendError(f"learned backend: {exc}") from exc

    def detect(self, image, camera, truth, calib, *, seq=0, stamp_ns=0) -> Keypoints:
        return self.detector.detect(image, camera, seq, stamp_ns, undistort=_undistorter(calib, camera))

    def reset(self) -> None:
        self.detector.reset()

    def reject(self, camera: str, bbox=None) -> None:
        self.detector.reject(camera, bbox)

    def last_notes(self) -> dict[str, str]:
        turn = self.detector.last_turn
        if not turn:
            return {}
        return {"found_turned": f"the needle was found only with the image's hues turned ({turn:g} deg): "
                                f"a look unlike the training renders (tissue of another colour); its "
                                f"keypoints and tip are less sure there, `needletrack adapt` fits the "
                                f"detector to such a scene (docs/adapt.md)"}


def _undistorter(calib, camera: str):
    """pixels -> ideal pixels of ``camera`` from a Calibration, or None without distortion."""
    cam = None if calib is None else calib.cameras.get(camera)
    if not cam or cam.get("dist") is None or not np.any(np.asarray(cam["dist"], float)):
        return None
    from common.geometry.camera import undistort_pixels
    K, dist = np.asarray(cam["K"], float), np.asarray(cam["dist"], float)
    return lambda uv: undistort_pixels(K, dist, uv)
