"""``needletrack dataset from-bag BAG --preset ambf|dvrk [--topics MAP.yaml] --out DIR``: a bag
as a dataset folder (docs/dataset.md), so ``eval``, ``train`` and fine-tuning run on it.

The rig (K, dist, T_ecm_cam) must stay constant over the bag (the dataset's ``dataset.yaml``
holds one); ground truth (``T_world_needle``, with ``T_world_ecm``) gives the keypoints, their
visibility (in front of the camera and inside the image: a bag has no occlusion information) and
the arc's box, all through the distortion model when there is one. Consecutive frames whose
ground-truth needle pose stays put (within ``REST_TOL``: 1 um, 1 urad) form a ``sequence``
(the spec's multi-view group: the needle at rest while the endoscope moves), ``step`` counting
within it. The instruments the bag's topic map names (``common/ros/instruments.py``) go into each
frame's ``instruments`` (jaw frame in world, jaw angle; no ``holds_needle``: a bag does not say).
"""
from __future__ import annotations

import os
import time

import numpy as np

from common.data.dataset import DatasetMeta, Frame
from common.data.writer import DatasetWriter, staged_folder
from common.frames import CAMERAS
from common.geometry.camera import StereoRig
from common.geometry.transforms import inv_T
from common.ros.bag import BagError, BagStereo

REST_TOL = 1e-6          # m and rad: the needle has not moved between two frames


def _at_rest(a: np.ndarray, b: np.ndarray) -> bool:
    if np.linalg.norm(a[:3, 3] - b[:3, 3]) > REST_TOL:
        return False
    return float(np.abs(a[:3, :3] - b[:3, :3]).max()) <= REST_TOL


class RestGroups:
    """``(sequence, step)`` of successive ground-truth needle poses: a new sequence whenever
    the needle moved (more than ``REST_TOL``) since the last frame."""

    def __init__(self):
        self.sequence, self.step, self.last = -1, 0, None

    def __call__(self, T_world_needle: np.ndarray) -> tuple[int, int]:
        if self.last is not None and _at_rest(self.last, T_world_needle):
            self.step += 1
        else:
            self.sequence, self.step = self.sequence + 1, 0
        self.last = T_world_needle
        return self.sequence, self.step


def truth_projections(rig, needle, T_world_ecm, T_world_needle):
    """(keypoints, visible, bbox) per camera from the poses (through the distortion), or
    (None, None, None) when a keypoint is behind a camera."""
    from common.geometry.oracle import arc_bbox, true_keypoints
    T_en = inv_T(T_world_ecm) @ T_world_needle
    kp, vis, box = {}, {}, {}
    for c in CAMERAS:
        kp[c], vis[c] = true_keypoints(rig[c], T_en, needle)
        b = arc_bbox(rig[c], T_en, needle)
        box[c] = None if b is None else b.tolist()
    if not all(np.all(np.isfinite(kp[c])) for c in CAMERAS):
        return None, None, None
    return kp, vis, box


def _same_rig(a: dict, b: dict) -> str | None:
    for c in CAMERAS:
        for k in ("K", "dist", "T_ecm_cam"):
            x, y = np.asarray(a[c][k], float), np.asarray(b[c][k], float)
            if x.shape != y.shape or not np.allclose(x, y, atol=1e-6, rtol=1e-6):
                return f"{c}.{k}"
    return None


def sample_fault(s, topics: dict) -> str | None:
    """What is not finite in a StereoSample (intrinsics, camera poses, ECM joints and pose, the
    needle's pose), naming the topic it came from; None when all is."""
    def topic(*roles):
        return next((topics[r] for r in roles if r in topics), roles[0])
    for c in CAMERAS:
        for k in ("K", "dist"):
            if not np.all(np.isfinite(s.cameras[c][k])):
                return f"{topic('camera_info.' + c)}: the {c} camera's {k} is not finite"
        if not np.all(np.isfinite(s.cameras[c]["T_ecm_cam"])):
            return f"{topic('camera_state.' + c, 'registration')}: the {c} camera's pose is not finite"
    for what, value, roles in (("ECM joints", s.ecm_joints, ("ecm_joints",)),
                               ("T_world_ecm", s.T_world_ecm, ("camera_frame", "ecm_pose", "ecm_joints")),
                               ("T_world_needle", s.T_world_needle, ("needle_pose",))):
        if value is not None and not np.all(np.isfinite(value)):
            return f"{topic(*roles)}: {what} is not finite"
    return None


def from_bag(bag: str, out: str, preset: str | None = None, topics=None, image_format: str = "png",
             jpeg_quality: int = 95, max_frames: int = 0, stride: int = 1, progress: bool = False) -> dict:
    """Convert ``bag`` into the dataset folder ``out`` (written beside it under a temporary name,
    renamed at the end: a failed conversion leaves no folder); returns a summary dict (frames,
    with_truth, unit, topics, unpaired images, messages refused per topic, recovered, seconds).
    Raises BagError (bad bag/topics) or ValueError. A message that does not decode or cannot
    serve its role is skipped, counted in ``refused`` and logged once per topic."""
    if os.path.exists(os.path.join(out, "frames.jsonl")):
        raise ValueError(f"{out} already holds a dataset; use another --out")
    t0 = time.perf_counter()
    writer = None
    n = truth = 0
    groups = RestGroups()
    with BagStereo(bag, preset, topics) as src, staged_folder(out) as tmp:
        hint = src.frame_count_hint()
        bar = None
        if progress:
            from common.progress import progress_bar
            bar = progress_bar(total=hint, desc="from-bag", unit="frame")
        try:
            for s in src:
                if bar is not None:
                    bar.update(1)
                if s.index % stride:
                    continue
                fault = sample_fault(s, src.info["topics"])
                if fault:
                    raise BagError(f"{bag}: frame {s.index} (stamp {s.stamp_ns}): {fault}")
                if writer is None:
                    rig = StereoRig.from_dict(s.cameras, s.image_size)
                    first = s.cameras
                    needle = src.needle_model()
                    arm = None
                    if src.map.get("ecm"):
                        from common.geometry.ecm_kinematics import EcmArm
                        arm = EcmArm.from_dict(src.map["ecm"])
                    meta = DatasetMeta(s.image_size, rig, needle, arm,
                                       source=f"needletrack dataset from-bag {os.path.basename(bag)} "
                                              f"(preset {src.map.get('preset')}, unit {src.info.get('unit')})")
                    writer = DatasetWriter(tmp, meta, image_format=image_format, jpeg_quality=jpeg_quality)
                else:
                    bad = _same_rig(first, s.cameras)
                    if bad:
                        raise BagError(f"{bag}: frame {s.index} (stamp {s.stamp_ns}): {bad} changed during the bag; "
                                       f"a dataset folder holds one rig: convert the parts separately")
                paths = writer.write_images(n, s.images)
                fr = Frame(index=n, stamp_ns=s.stamp_ns, left=paths["left"], right=paths["right"],
                           ecm_joints=s.ecm_joints, T_world_ecm=s.T_world_ecm, instruments=s.instruments)
                if s.T_world_needle is not None and s.T_world_ecm is not None:
                    fr.sequence, fr.step = groups(s.T_world_needle)
                    fr.T_world_needle = s.T_world_needle
                    kp, vis, box = truth_projections(rig, needle, s.T_world_ecm, s.T_world_needle)
                    if kp is not None:
                        fr.keypoints, fr.visible, fr.bbox = kp, vis, box
                    truth += 1
                writer.append(fr)
                n += 1
                if max_frames and n >= max_frames:
                    break
        finally:
            if bar is not None:
                bar.close()
            if writer is not None:
                writer.close()
        if writer is None:
            raise BagError(f"{bag}: no stereo pair found on {src.info['topics'].get('image.left')} and "
                           f"{src.info['topics'].get('image.right')} (left/right header stamps within "
                           f"{src.map['stereo_tolerance_ms']} ms; images left out: {src.counts})")
        return {"frames": n, "with_truth": truth, "unit": src.info.get("unit"), "topics": src.info["topics"],
                "unpaired": dict(src.counts), "refused": dict(src.refused), "image_size": list(meta.image_size),
                "recovered": src.info.get("recovered"),
                "seconds": time.perf_counter() - t0}
