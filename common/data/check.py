"""The dataset format's consistency checks (``docs/dataset.md``): the ground truth's projection,
the joints' forward kinematics, the takes of a moving needle, the image files (``check_dataset``)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from common.frames import CAMERAS
from common.geometry.transforms import inv_T, pose_error, transform_points
from common.data.instruments import T_jaw_needle
from common.data.dataset import (
    Dataset,
    DatasetError,
    DatasetMeta,
    FRAMES_FILE,
    Frame,
)

GRASP_TOL_M, GRASP_TOL_RAD = 1e-6, 1e-5
"""How far a held needle may move in the jaws between two frames (JSON keeps full precision)."""


@dataclass
class CheckReport:
    frames: int = 0
    with_truth: int = 0
    max_reproj_px: float = 0.0
    mean_reproj_px: float = 0.0
    max_fk_m: float = 0.0
    images_checked: int = 0
    errors: list = field(default_factory=list)
    warnings: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.errors


def project_keypoints(meta: DatasetMeta, T_world_ecm: np.ndarray, T_world_needle: np.ndarray) -> dict:
    """Ground-truth keypoints {camera: (5, 2) px} from the poses, as the spec defines them."""
    p_ecm = transform_points(inv_T(T_world_ecm) @ T_world_needle, meta.needle.keypoints())
    return {c: meta.rig[c].project_from_ecm(p_ecm) for c in CAMERAS}


def check_frame(meta: DatasetMeta, fr: Frame, tol_px: float = 0.1, tol_fk_m: float = 1e-5) -> tuple[list, float, float]:
    """Spec consistency of one frame: (errors, max reprojection px, FK position error m)."""
    errs, reproj, fk = [], float("nan"), float("nan")
    where = f"{FRAMES_FILE}:{fr.line}"
    w, h = meta.image_size
    if fr.keypoints is not None and fr.T_world_ecm is not None and fr.T_world_needle is not None:
        proj = project_keypoints(meta, fr.T_world_ecm, fr.T_world_needle)
        reproj = max(float(np.max(np.linalg.norm(proj[c] - fr.keypoints[c], axis=1))) for c in CAMERAS)
        if not reproj <= tol_px:
            errs.append(f"{where}: keypoints: differ from the projection of T_world_needle through "
                        f"T_world_ecm, T_ecm_cam and K by {reproj:.3f} px (tolerance {tol_px} px)")
    if fr.ecm_joints is not None and fr.T_world_ecm is not None and meta.arm is not None:
        T = meta.arm.T_world_ecm(fr.ecm_joints)
        fk = float(np.linalg.norm(T[:3, 3] - fr.T_world_ecm[:3, 3]))
        rot = float(np.linalg.norm(T[:3, :3] - fr.T_world_ecm[:3, :3]))
        if fk > tol_fk_m or rot > 1e-4:
            errs.append(f"{where}: T_world_ecm: differs from the ECM forward kinematics of ecm_joints "
                        f"by {fk * 1000:.3f} mm / {rot:.2e} (rotation)")
    if fr.visible is not None and fr.keypoints is not None:
        for c in CAMERAS:
            uv = fr.keypoints[c]
            inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= h - 0.5)
            bad = np.flatnonzero(fr.visible[c] & ~inside)
            if len(bad):
                errs.append(f"{where}: visible.{c}: keypoint {'ABCDE'[bad[0]]} is marked visible "
                            f"but lies outside the image at {uv[bad[0]].round(1).tolist()}")
    if fr.bbox is not None:
        for c in CAMERAS:
            b = fr.bbox[c]
            if b is not None and (b[0] < -0.5 - 1e-6 or b[1] < -0.5 - 1e-6 or b[2] > w - 0.5 + 1e-6 or b[3] > h - 0.5 + 1e-6):
                errs.append(f"{where}: bbox.{c}: {b} lies outside the {w}x{h} image")
    return errs, reproj, fk


def check_take(first: Frame, prev: Optional[Frame], fr: Frame) -> list:
    """A frame against its sequence: all of it at rest or all of it moving; at rest, the
    first frame's ``T_world_needle``; moving, the needle rigid in the true jaws of an instrument
    that holds it in this frame and the one before (``holds_needle``; ``T_world_jaw_truth`` where
    given: a reported jaw pose carries the arm's error, and a real recording's moves)."""
    where = f"{FRAMES_FILE}:{fr.line}"
    if fr.at_rest != first.at_rest:
        return [f"{where}: needle_at_rest: {fr.needle_at_rest} in sequence {fr.sequence}, whose first frame "
                f"(line {first.line}) says {first.needle_at_rest}; a sequence rests or moves as a whole"]
    if fr.at_rest:
        if (fr.T_world_needle is not None and first.T_world_needle is not None
                and not np.allclose(fr.T_world_needle, first.T_world_needle, atol=1e-9)):
            return [f"{where}: T_world_needle: differs from the first frame of sequence {fr.sequence} "
                    f"(line {first.line}); the needle must be at rest (or the frames say needle_at_rest: false)"]
        return []
    errs = []
    if prev is None or fr.T_world_needle is None or prev.T_world_needle is None:
        return errs
    for name, inst in (fr.instruments or {}).items():
        before = (prev.instruments or {}).get(name)
        if not (inst.holds_needle and before is not None and before.holds_needle):
            continue
        dt, da = pose_error(T_jaw_needle(before, prev.T_world_needle, truth=True),
                            T_jaw_needle(inst, fr.T_world_needle, truth=True))
        if dt > GRASP_TOL_M or da > GRASP_TOL_RAD:
            errs.append(f"{where}: instruments.{name}: holds_needle in this frame and the one before (line "
                        f"{prev.line}), but the needle moved {dt * 1000:.4f} mm / {np.rad2deg(da):.4f} deg in its jaws")
    return errs


def check_dataset(ds: Dataset, tol_px: float = 0.1, images: bool = True, progress: bool = False,
                  max_errors: int = 50) -> CheckReport:
    """The spec's consistency checks over a loaded folder (see ``check_frame``), plus: every
    image decodes at ``image_size``; frames of one ``sequence`` share one ``T_world_needle``
    (the needle at rest) or, in a moving take, keep the needle rigid in the jaws that hold it
    (``check_take``), and have increasing ``step``."""
    rep = CheckReport(frames=len(ds))
    errs = []
    reprojs = []
    it = ds.frames
    if progress:
        from common.progress import progress_bar
        it = progress_bar(it, desc="check", unit="frame")
    seq_first: dict = {}
    prev: dict = {}
    for fr in it:
        e, rp, fk = check_frame(ds.meta, fr, tol_px)
        errs += e
        if not math.isnan(rp):
            reprojs.append(rp)
        if not math.isnan(fk):
            rep.max_fk_m = max(rep.max_fk_m, fk)
        if fr.sequence is not None:
            first = seq_first.get(fr.sequence)
            if first is None:
                seq_first[fr.sequence] = fr
            else:
                errs += check_take(first, prev.get(fr.sequence), fr)
            prev[fr.sequence] = fr
        if images:
            for c in CAMERAS:
                try:
                    ds.image(fr, c)
                    rep.images_checked += 1
                except DatasetError as exc:
                    errs.append(str(exc))
        if len(errs) >= max_errors:
            errs.append(f"... stopped after {max_errors} errors")
            break
    for s, frs in ds.sequences().items():
        steps = [f.step for f in frs if f.step is not None]
        if steps and steps != sorted(set(steps)):
            rep.warnings.append(f"sequence {s}: steps {steps[:10]} are not strictly increasing")
    if not len(ds):
        errs.append(f"{FRAMES_FILE}: no frames (a dataset needs at least one)")
    rep.errors = errs
    rep.with_truth = len(reprojs)
    if reprojs:
        rep.max_reproj_px = float(np.max(reprojs))
        rep.mean_reproj_px = float(np.mean(reprojs))
    return rep
