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
from typing import Optional

import numpy as np

from common.messages import Calibration, GroundTruth, Keypoints

BACKENDS: dict[str, str] = {
    "oracle": "common.keypoint_backends:OracleBackend",
    "learned": "common.keypoint_detector:LearnedBackend",
    "classical": "common.classical_detector:ClassicalBackend",
}


class BackendError(RuntimeError):
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

    def detect(self, image: Optional[np.ndarray], camera: str, truth: Optional[GroundTruth],
               calib: Calibration, *, seq: int = 0, stamp_ns: int = 0) -> Keypoints:
        raise NotImplementedError(f"{type(self).__name__}.detect")

    def detect_stereo(self, images: dict, truth: Optional[GroundTruth], calib: Calibration, *,
                      seq: int = 0, stamp_ns: int = 0) -> dict[str, Keypoints]:
        """``{camera: Keypoints}`` for the cameras in ``images`` (camera -> image or None)."""
        return {cam: self.detect(img, cam, truth, calib, seq=seq, stamp_ns=stamp_ns)
                for cam, img in images.items()}


def register_backend(name: str, target: str) -> None:
    """Add or replace a backend: ``target`` is ``"package.module:ClassName"``."""
    if ":" not in target:
        raise ValueError(f"backend {name!r}: target must be 'module:Class', got {target!r}")
    BACKENDS[name] = target


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
    """Keypoints from the frame's ground truth (``common.oracle``): params ``noise_px``,
    ``missing_prob``, ``outlier_prob``, ``outlier_px``, ``seed``. Uses the true poses when the
    ground truth has them (``T_world_ecm`` and ``T_world_needle``), else its ``keypoints``.
    With the poses it also gives the dense ``centreline`` (params ``centreline``, default true,
    and ``centreline_noise_px``, default noise_px / 2)."""

    name = "oracle"
    needs_image = False
    needs_truth = True

    def __init__(self, params: Optional[dict] = None):
        super().__init__(params)
        from common.oracle import Oracle
        try:
            self.oracle = Oracle.from_params(self.params)
        except (TypeError, ValueError) as exc:
            raise BackendError(f"oracle backend: bad params: {exc}") from exc

    def detect(self, image, camera, truth, calib, *, seq=0, stamp_ns=0) -> Keypoints:
        from common.oracle import arc_bbox, truth_T_ecm_needle
        if truth is None:
            return Keypoints.not_found(camera, seq, stamp_ns, self.name, "no ground truth for this frame")
        cam = calib.rig()[camera]
        model = calib.needle_model()
        vis = None if truth.visible is None else truth.visible.get(camera)
        T = truth_T_ecm_needle(truth)
        bbox = None
        line = line_w = None
        if T is not None:
            uv, scores = self.oracle.keypoints(cam, T, model, seq, vis)
            bbox = arc_bbox(cam, T, model)
            if self.params.get("centreline", True):
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
        return Keypoints(camera, seq, stamp_ns, True, uv, scores, float(scores.mean()), bbox, self.name,
                         centreline=line, centreline_w=line_w)
