"""The detector's proposals for a folder's frames and the order in which they are labelled.

The detector runs through its backend's public API (``common.detector.backends.load_backend``,
``detect_stereo``), cold on each frame (``reset`` first), so any backend, today's network or the
next, proposes. A proposal is ``{camera: {"found", "uv" (5, 2) or None, "confidence",
"end_identity"}}``. Frames the detector is least sure of come first (``doubt``); proposals are
kept in the session file, keyed by the detector's name and params, so a reopened folder does
not run the detector again.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from common.frames import CAMERAS
from common.progress import progress_bar


def stereo_detections(ds, backend, frames=None, progress: bool = True, desc: str = "detecting"):
    """``(frame, {camera: Keypoints} or None)`` for each of ``frames`` (Frames of ``ds``, a
    ``Dataset``; default all) by ``backend`` (a ``KeypointBackend``), cold (``reset`` before each
    frame); None where the frame's images cannot be read. A progress bar over the frames."""
    from common.runtime.messages import Calibration
    meta = ds.meta
    calib = Calibration(stamp_ns=0, image_size=np.array(meta.image_size), cameras=meta.rig.to_dict(),
                        needle=meta.needle.to_dict(), ecm=None if meta.arm is None else meta.arm.to_dict(),
                        source=f"needletrack {ds.path}")
    for fr in progress_bar(ds.frames if frames is None else frames, desc=desc, unit="frame", show=progress):
        try:
            images = {c: ds.image(fr, c) for c in CAMERAS}
        except ValueError:
            yield fr, None
            continue
        backend.reset()
        yield fr, backend.detect_stereo(images, None, calib, seq=fr.index, stamp_ns=fr.stamp_ns)


def proposal_of(kps: dict) -> dict:
    """A proposal (the module docstring) from ``{camera: Keypoints}``."""
    return {c: {"found": bool(k.found),
                "uv": np.asarray(k.uv, float).round(3).tolist() if k.found else None,
                "confidence": round(float(k.confidence), 4),
                "end_identity": None if k.end_identity is None else round(float(k.end_identity), 4)}
            for c, k in kps.items()}


def detect_folder(ds, name: str, params: dict, progress: bool = True) -> list:
    """The proposal of every frame of ``ds`` (a ``Dataset``) by backend ``name`` with ``params``
    (None for a frame whose images cannot be read). Raises ``BackendError``."""
    from common.detector.backends import load_backend
    backend = load_backend(name, params)
    return [None if kps is None else proposal_of(kps)
            for _fr, kps in stereo_detections(ds, backend, progress=progress, desc=f"proposals ({name})")]


def doubt(proposal: Optional[dict]) -> float:
    """How unsure the detector is of a frame, in [0, 1]: 1 less the least sure camera's
    sureness, which is its confidence where it found the needle (times how sure it is of the tip,
    ``|2 p - 1|`` of its end identity ``p``, where it says), one less it where it found none.
    No proposal: 1."""
    if not proposal:
        return 1.0
    sure = []
    for c in CAMERAS:
        p = proposal.get(c)
        if p is None:
            sure.append(0.0)
            continue
        s = p["confidence"] if p["found"] else 1.0 - p["confidence"]
        if p["found"] and p.get("end_identity") is not None:
            s *= abs(2.0 * p["end_identity"] - 1.0)
        sure.append(min(max(s, 0.0), 1.0))
    return 1.0 - min(sure)


def label_order(proposals: Optional[list], n: int) -> list:
    """The frames' indices, the least sure first (``doubt``), ties in file order; without
    proposals, file order."""
    if not proposals:
        return list(range(n))
    return sorted(range(n), key=lambda i: (-round(doubt(proposals[i]), 6), i))
