"""``needletrack dataset from-bag BAG --preset ambf|dvrk [--topics MAP.yaml] --out DIR``: a bag
as a dataset folder (docs/dataset.md), so ``eval``, ``train`` and fine-tuning run on it.

The rig (K, dist, T_ecm_cam) must stay constant over the bag (the dataset's ``dataset.yaml``
holds one); ground truth (``T_world_needle``, with ``T_world_ecm``) gives the keypoints, their
visibility (in front of the camera and inside the image: a bag has no occlusion information) and
the arc's box, all through the distortion model when there is one. Consecutive frames whose
ground-truth needle pose stays put (within ``REST_TOL``: 1 um, 1 urad) form a ``sequence``
(the spec's multi-view group: the needle at rest while the endoscope moves), ``step`` counting
within it.
"""
from __future__ import annotations

import os
import time

import numpy as np

from common.data.dataset import DatasetMeta, DatasetWriter, Frame
from common.geometry.camera import StereoRig
from common.geometry.transforms import inv_T
from common.ros.bag import BagError, BagStereo

CAMS = ("left", "right")
REST_TOL = 1e-6          # m and rad: the needle has not moved between two frames


def _at_rest(a: np.ndarray, b: np.ndarray) -> bool:
    if np.linalg.norm(a[:3, 3] - b[:3, 3]) > REST_TOL:
        return False
    c = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0))) <= REST_TOL * 10   # arccos near 1 is coarse


def _same_rig(a: dict, b: dict) -> str | None:
    for c in CAMS:
        for k in ("K", "dist", "T_ecm_cam"):
            x, y = np.asarray(a[c][k], float), np.asarray(b[c][k], float)
            if x.shape != y.shape or not np.allclose(x, y, atol=1e-6, rtol=1e-6):
                return f"{c}.{k}"
    return None


def from_bag(bag: str, out: str, preset: str | None = None, topics=None, image_format: str = "png",
             jpeg_quality: int = 95, max_frames: int = 0, stride: int = 1, progress: bool = False) -> dict:
    """Convert ``bag`` into the dataset folder ``out``; returns a summary dict (frames, with_truth,
    unit, topics, unpaired images, seconds). Raises BagError (bad bag/topics) or ValueError."""
    from common.geometry.oracle import arc_bbox, true_keypoints
    if os.path.exists(os.path.join(out, "frames.jsonl")):
        raise ValueError(f"{out} already holds a dataset; use another --out")
    t0 = time.perf_counter()
    writer = None
    n = truth = 0
    sequence, step, last_needle = -1, 0, None
    with BagStereo(bag, preset, topics) as src:
        hint = src.frame_count_hint()
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(total=hint, desc="from-bag", unit="frame")
        try:
            for s in src:
                if bar is not None:
                    bar.update(1)
                if s.index % stride:
                    continue
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
                    writer = DatasetWriter(out, meta, image_format=image_format, jpeg_quality=jpeg_quality)
                else:
                    bad = _same_rig(first, s.cameras)
                    if bad:
                        raise BagError(f"{bag}: frame {s.index} (stamp {s.stamp_ns}): {bad} changed during the bag; "
                                       f"a dataset folder holds one rig: convert the parts separately")
                paths = writer.write_images(n, s.images)
                fr = Frame(index=n, stamp_ns=s.stamp_ns, left=paths["left"], right=paths["right"],
                           ecm_joints=s.ecm_joints, T_world_ecm=s.T_world_ecm)
                if s.T_world_needle is not None and s.T_world_ecm is not None:
                    if last_needle is not None and _at_rest(last_needle, s.T_world_needle):
                        step += 1
                    else:
                        sequence, step = sequence + 1, 0
                    last_needle = s.T_world_needle
                    fr.sequence, fr.step = sequence, step
                    fr.T_world_needle = s.T_world_needle
                    T_en = inv_T(s.T_world_ecm) @ s.T_world_needle
                    kp, vis, box = {}, {}, {}
                    for c in CAMS:
                        uv, v = true_keypoints(rig[c], T_en, needle)
                        kp[c], vis[c] = uv, v
                        b = arc_bbox(rig[c], T_en, needle)
                        box[c] = None if b is None else b.tolist()
                    if all(np.all(np.isfinite(kp[c])) for c in CAMS):
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
                           f"{src.map['stereo_tolerance_ms']} ms; unpaired: {src.counts})")
        return {"frames": n, "with_truth": truth, "unit": src.info.get("unit"), "topics": src.info["topics"],
                "unpaired": dict(src.counts), "image_size": list(meta.image_size),
                "seconds": time.perf_counter() - t0}
