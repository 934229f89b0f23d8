"""Keypoint detector backends: the interface the ``detector`` node runs, and a lazy registry.

A backend turns one camera image into a ``Keypoints`` message::

    backend = load_backend("oracle", {"noise_px": 0.5})
    kp = backend.detect(image, "left", truth, calib, seq=7, stamp_ns=...)

``image`` is an (h, w, 3) uint8 BGR array, or None for a backend with ``needs_image = False``
(the node then skips decoding); ``truth`` is the frame's ``GroundTruth`` or None; ``calib`` the
current ``Calibration``. A backend that finds no needle returns ``Keypoints.not_found`` with a
reason; one that cannot work at all raises ``BackendError``.

The registry maps a name to ``"module:Class"`` and imports the module only when that backend is
loaded, so heavy dependencies (torch) are paid for only by graphs that use them. Add a backend
with one line in ``BACKENDS`` (or ``register_backend`` at run time).
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Optional

import numpy as np

from common.errors import NeedletrackError
from common.detector.config import ClassicalConfig, DetectorConfig
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.oracle import Oracle
from common.runtime.messages import Calibration, GroundTruth, Keypoints
from common.runtime.params import ParamError, config_from, merge_schemas, parse_params


@dataclass
class _OracleCentreline:
    centreline: bool = True                       # the dense centreline too (with the true poses)


@dataclass
class _LearnedRun:
    weights: str | None = None                    # None: models/keypoint/model.pt
    device: str = "auto"                          # auto | cpu | cuda
    threads: int = 1                              # torch threads


OracleParams = merge_schemas("OracleParams", Oracle, _OracleCentreline)
"""Backend ``oracle``: keypoints from the ground truth, with simulated detector errors (px)."""
LearnedParams = merge_schemas("LearnedParams", DetectorConfig, _LearnedRun)
"""Backend ``learned``: the keypoint network (``common.detector.inference``)."""
ClassicalParams = ClassicalConfig
"""Backend ``classical``: the image-processing baseline (``common.detector.classical``)."""


@dataclass
class _NoParams:
    pass


BACKEND_PARAMS: dict[str, type] = {"oracle": OracleParams, "learned": LearnedParams, "classical": ClassicalParams}
"""Each backend's params, declared here so that a graph is checked without importing torch."""

BACKENDS: dict[str, str] = {
    "oracle": "common.detector.backends:OracleBackend",
    "learned": "common.detector.learned:LearnedBackend",
    "classical": "common.detector.classical:ClassicalBackend",
}


class BackendError(NeedletrackError, RuntimeError):
    """A backend that cannot be loaded or cannot run; the text says why."""


class KeypointBackend:
    """Base of the detector backends. ``params`` are the detector node's params (minus
    ``backend``). Subclasses implement ``detect``; ``detect_stereo`` may be overridden to
    process both images of a frame at once (e.g. one batched network call)."""

    name = "base"
    needs_image = True
    needs_truth = False

    def __init__(self, params: Optional[dict] = None):
        self.params = dict(params or {})
        try:
            self.p = parse_params(BACKEND_PARAMS.get(self.name, _NoParams), self.params)
        except ParamError as exc:
            raise BackendError(f"{self.name} backend: bad params: {exc}") from None

    def detect(self, image: Optional[np.ndarray], camera: str, truth: Optional[GroundTruth],
               calib: Calibration, *, seq: int = 0, stamp_ns: int = 0) -> Keypoints:
        raise NotImplementedError(f"{type(self).__name__}.detect")

    def reset(self) -> None:
        """A new source stream: forget any state carried from frame to frame (none here)."""

    def reject(self, camera: str, bbox=None) -> None:
        """Camera ``camera``'s last detections are a wrong lock (``LockRejected``: the other
        camera and the track disagree with them; ``bbox`` [x0, y0, x1, y1] px, the rejected
        box, or None): drop what is tracked of that camera and search it cold (nothing here: a
        backend that keeps no state from frame to frame)."""

    def last_notes(self) -> dict[str, str]:
        """What the last ``detect`` did that the node should count and say once: {counter name:
        the sentence to log the first time} (none here)."""
        return {}

    def detect_stereo(self, images: dict, truth: Optional[GroundTruth], calib: Calibration, *,
                      seq: int = 0, stamp_ns: int = 0) -> dict[str, Keypoints]:
        """``{camera: Keypoints}`` for the cameras in ``images`` (camera -> image or None)."""
        return {cam: self.detect(img, cam, truth, calib, seq=seq, stamp_ns=stamp_ns)
                for cam, img in images.items()}


def register_backend(name: str, target: str, params: type = _NoParams) -> None:
    """Add or replace a backend: ``target`` is ``"package.module:ClassName"``, ``params`` its
    params dataclass (default: none)."""
    if ":" not in target:
        raise ValueError(f"backend {name!r}: target must be 'module:Class', got {target!r}")
    BACKENDS[name] = target
    BACKEND_PARAMS[name] = params


def available_backends() -> list[str]:
    return sorted(BACKENDS)


def backend_class(name: str) -> type:
    """The backend class registered under ``name`` (imports its module)."""
    if name not in BACKENDS:
        raise BackendError(f"detector backend {name!r} is unknown; known: {', '.join(available_backends())}")
    module, _, cls_name = BACKENDS[name].partition(":")
    try:
        mod = importlib.import_module(module)
    except ImportError as exc:
        raise BackendError(f"detector backend {name!r}: cannot import {module} ({exc})") from exc
    cls = getattr(mod, cls_name, None)
    if not (isinstance(cls, type) and issubclass(cls, KeypointBackend)):
        raise BackendError(f"detector backend {name!r}: {module} has no KeypointBackend {cls_name}")
    return cls


def load_backend(name: str, params: Optional[dict] = None) -> KeypointBackend:
    """Instantiate the backend registered under ``name`` with ``params``."""
    return backend_class(name)(params)


class OracleBackend(KeypointBackend):
    """Keypoints from the frame's ground truth (``common.geometry.oracle``): params ``noise_px``,
    ``missing_prob``, ``outlier_prob``, ``outlier_px``, ``seed``. Uses the true poses when the
    ground truth has them (``T_world_ecm`` and ``T_world_needle``), else its ``keypoints``.
    With the poses it also gives the dense ``centreline`` (params ``centreline``, default true,
    and ``centreline_noise_px``, default noise_px / 2). It states the noise it adds
    (``keypoint_sigma_px``, ``centreline_sigma_px``)."""

    name = "oracle"
    needs_image = False
    needs_truth = True

    def __init__(self, params: Optional[dict] = None):
        super().__init__(params)
        try:
            self.oracle = config_from(Oracle, self.p)
        except (TypeError, ValueError) as exc:
            raise BackendError(f"oracle backend: bad params: {exc}") from exc

    def detect(self, image, camera, truth, calib, *, seq=0, stamp_ns=0) -> Keypoints:
        from common.geometry.oracle import arc_bbox, truth_T_ecm_needle
        if truth is None:
            return Keypoints.not_found(camera, seq, stamp_ns, self.name, "no ground truth for this frame")
        cam = StereoRig.from_dict(calib.cameras, calib.image_size)[camera]
        model = NeedleModel.from_dict(calib.needle)
        vis = None if truth.visible is None else truth.visible.get(camera)
        T = truth_T_ecm_needle(truth)
        bbox = None
        line = line_w = None
        if T is not None:
            uv, scores = self.oracle.keypoints(cam, T, model, seq, vis)
            bbox = arc_bbox(cam, T, model)
            if self.p.centreline:
                line, line_w = self.oracle.centreline(cam, T, model, seq)
        elif truth.keypoints is not None and truth.keypoints.get(camera) is not None:
            uv_true = np.asarray(truth.keypoints[camera], dtype=float).reshape(5, 2)
            v = np.all(np.isfinite(uv_true), axis=1)
            if vis is not None:
                v &= np.asarray(vis, dtype=bool).reshape(5)
            uv, scores = self.oracle.corrupt(np.nan_to_num(uv_true), v, seq, camera)
        else:
            return Keypoints.not_found(camera, seq, stamp_ns, self.name,
                                       "ground truth has neither poses nor keypoints")
        if truth.bbox is not None and truth.bbox.get(camera) is not None:
            bbox = np.asarray(truth.bbox[camera], dtype=float).reshape(4)
        if not np.any(scores > 0):
            return Keypoints.not_found(camera, seq, stamp_ns, self.name, "needle not visible")
        # the noise it adds is the noise it states (none stated without noise: the consumer's default)
        kp_sigma = self.oracle.noise_px or None
        cl_sigma = (self.oracle.noise_px / 2 if self.oracle.centreline_noise_px is None
                    else self.oracle.centreline_noise_px) or None
        return Keypoints(camera, seq, stamp_ns, True, uv, scores, float(scores.mean()), bbox, self.name,
                         centreline=line, centreline_w=line_w,
                         centreline_sigma_px=None if line is None else cl_sigma, keypoint_sigma_px=kp_sigma)
