"""Pseudo-labels without ground truth: the world pose of a static needle that the pipeline's
views agree on, projected back into every image of the group as its training labels.

A group is the frames of one ``sequence`` (one needle at rest, the endoscope moving; frames
without a ``sequence`` are grouped by the fusion's own motion test: a new group where
``MultiViewFusion`` resets). Its refined poses (``adapt_run``) are fused over the endoscope's
poses (``MultiViewFusion``, every view of the group in its queue), and the group is kept only
when geometry confirms the fused pose (``LabelConfig``, checked in this order, the first that
fails names the drop reason):

- ``too_few_poses``: fewer than ``min_views`` frames were posed at all;
- ``views_disagree``: fewer than ``min_views`` views, or under ``min_inlier_share`` of the posed
  ones, are the fusion's inliers;
- ``spread``: the inliers' positions lie farther than ``max_spread_mm`` (RMS) from the fused one;
- ``tip_undecided``: the group's end identity (the mean of its views' log-odds about the fused
  pose, a turned view counting against it: ``common.geometry.fusion``) is below ``TIP_SURE``,
  not stated, or the fused pose is flagged ambiguous (a fused pose below ``TIP_SURE`` states a
  covariance spanning its turn, so this comes before ``uncertain``);
- ``uncertain``: the fused covariance, carried into the images, moves a keypoint of one of the
  group's views by more than ``max_sigma_px`` (1 sigma, the largest axis), or its largest
  orientation sigma exceeds ``max_sigma_deg``. Pixels, not millimetres, because a label is an
  image position: a far needle's depth is unsure by millimetres that move no keypoint;
- ``reprojection``: fewer than ``min_views`` views' detections (either way round) lie within
  ``max_view_px`` (median over the found keypoints) of the fused pose's projection.

Every frame of a kept group, posed or not, gets the fused pose: keypoints from
``common.data.check.project_keypoints`` (the spec's projection), ``visible`` where they lie in
front of the camera and inside the image (``common.geometry.oracle.true_keypoints``; an
occluder is not known), ``bbox`` the projected arc's (``oracle.arc_bbox``), and
``T_world_needle``/``T_world_ecm`` (the centreline target the trainer projects from them).
Every ``fit_every``-th kept group goes to a second folder that training never sees (the
calibration's, ``adapt_calibration``).
"""
from __future__ import annotations

import json
import os
import shutil
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from common.data.check import project_keypoints
from common.data.dataset import Dataset, Frame
from common.data.writer import DatasetWriter, link_or_copy, staged_folder
from common.frames import CAMERAS
from common.geometry.end_identity import TIP_SURE
from common.geometry.error_state import retract
from common.geometry.fusion import MultiViewFusion, covariance_to_frame
from common.geometry.oracle import arc_bbox, true_keypoints
from common.geometry.transforms import inv_T

REASONS = ("too_few_poses", "views_disagree", "spread", "tip_undecided", "uncertain", "reprojection")
LABELS_FILE = "labels.json"


@dataclass(frozen=True)
class LabelConfig:
    """What geometry must confirm for a group to be kept (the module docstring); mm, deg, px."""

    min_views: int = 3
    min_inlier_share: float = 0.6
    max_spread_mm: float = 1.5
    max_sigma_px: float = 1.5     # the detector's heatmap sigma (kp_sigma): label noise below it
    max_sigma_deg: float = 5.0
    min_tip: float = TIP_SURE
    max_view_px: float = 4.0
    fit_every: int = 6            # every n-th kept group is held out for the calibration (0: none)


@dataclass
class GroupVerdict:
    """One group: its frames (indices into the folder), whether it is kept, why not, the fused
    world pose and the figures checked."""

    key: str
    frames: list
    kept: bool = False
    reason: str | None = None
    T_world_needle: np.ndarray | None = None
    figures: dict = field(default_factory=dict)


def groups_of(ds: Dataset, outputs: dict) -> dict:
    """``{key: [frame index, ...]}``: frames of one ``sequence``, or, without one, runs of
    frames between the fusion's resets (the needle moved in the world)."""
    groups: dict = {}
    fusion, run = MultiViewFusion(k=1_000_000), 0
    for i, fr in enumerate(ds.frames):
        if fr.sequence is not None:
            groups.setdefault(f"seq{fr.sequence}", []).append(i)
            continue
        pose = outputs.get(fr.index).pose if fr.index in outputs else None
        if pose is not None and pose.get("T_world_ecm") is not None:
            if fusion.add(pose["T_ecm_needle"], pose["T_world_ecm"]).reset:
                run += 1
        groups.setdefault(f"run{run}", []).append(i)
    return groups


def _sigmas(cov: np.ndarray | None) -> tuple[float, float]:
    """(largest position sigma mm, largest orientation sigma deg) of a [w, v] covariance."""
    if cov is None:
        return float("inf"), float("inf")
    return (1e3 * float(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0))),
            float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0)))))


def keypoint_sigma_px(meta, T_world_ecms, T_world_needle: np.ndarray, cov_world: np.ndarray | None,
                      step: float = 1e-6) -> float:
    """The largest 1-sigma (px, the major axis) of any keypoint in any camera of the views at
    ``T_world_ecms`` when ``T_world_needle`` is unsure by ``cov_world`` ([w, v], world frame:
    ``common.geometry.error_state.retract``), linearised (central differences of
    ``project_keypoints``); inf without a covariance."""
    if cov_world is None:
        return float("inf")
    worst = 0.0
    for T_we in T_world_ecms:
        cols = []
        for k in range(6):
            d = np.zeros(6)
            d[k] = step
            plus = project_keypoints(meta, T_we, retract(T_world_needle, d))
            minus = project_keypoints(meta, T_we, retract(T_world_needle, -d))
            cols.append(np.concatenate([(plus[c] - minus[c]).ravel() for c in CAMERAS]) / (2 * step))
        J = np.stack(cols, axis=1)                          # (2 x 5 x cameras, 6)
        S = J @ cov_world @ J.T
        for i in range(0, len(S), 2):
            worst = max(worst, float(np.sqrt(max(np.linalg.eigvalsh(S[i:i + 2, i:i + 2]).max(), 0.0))))
    return worst


def view_error_px(meta, T_world_ecm, T_world_needle, detections: dict) -> float | None:
    """Median distance (px) of a frame's found keypoints, either way round (the better), to the
    projection of ``T_world_needle``; None when no camera found the needle."""
    proj = project_keypoints(meta, T_world_ecm, T_world_needle)
    errs = []
    for c in CAMERAS:
        kp = detections.get(c)
        if not kp or not kp.get("found") or kp.get("uv") is None:
            continue
        uv, ok = np.asarray(kp["uv"], float), np.asarray(kp["scores"], float) >= 0.5
        ok &= np.isfinite(uv).all(axis=1)
        if ok.sum() < 2:
            continue
        said = np.linalg.norm(uv[ok] - proj[c][ok], axis=1)
        turned = np.linalg.norm(uv[ok] - proj[c][::-1][ok], axis=1)
        errs.append(min(np.median(said), np.median(turned)))
    return float(np.median(errs)) if errs else None


def judge_group(key: str, frames: list, ds: Dataset, outputs: dict, cfg: LabelConfig) -> GroupVerdict:
    """Fuse a group's refined poses and check them (the module docstring)."""
    v = GroupVerdict(key, list(frames))
    posed = []
    for i in frames:
        fo = outputs.get(ds.frames[i].index)
        if fo is not None and fo.pose is not None and fo.pose.get("T_world_ecm") is not None:
            posed.append((i, fo))
    v.figures["posed"] = len(posed)
    if len(posed) < cfg.min_views:
        v.reason = "too_few_poses"
        return v
    fusion = MultiViewFusion(k=len(posed) + 1, reset_after=len(posed) + 1)
    for _, fo in posed:
        p = fo.pose
        fused = fusion.add(p["T_ecm_needle"], p["T_world_ecm"], p.get("covariance"),
                           common_sigma_m=p.get("model_sigma_m") or 0.0,
                           common_sigma_rad=p.get("model_sigma_rad") or 0.0,
                           ambiguous=bool(p.get("ambiguous")), end_identity=p.get("end_identity"),
                           identity_widened=p.get("identity_widened"))
    T_world = fused.T_world_needle
    v.T_world_needle = T_world
    sig_mm, sig_deg = _sigmas(fused.covariance)
    cov_world = None
    if fused.covariance is not None:
        R_world_ecm = T_world[:3, :3] @ fused.T_ecm_needle[:3, :3].T
        cov_world = covariance_to_frame(fused.covariance, R_world_ecm)
    T_world_ecms = [T for T in (frame_T_world_ecm(ds.frames[i], outputs, ds) for i in frames) if T is not None]
    sig_px = keypoint_sigma_px(ds.meta, T_world_ecms, T_world, cov_world)
    v.figures.update(inliers=fused.n_views, turned=fused.turned, spread_mm=1e3 * fused.rms_m,
                     sigma_mm=sig_mm, sigma_px=sig_px, sigma_deg=sig_deg, tip=fused.end_identity)
    errs = [view_error_px(ds.meta, fo.pose["T_world_ecm"], T_world, fo.keypoints) for _, fo in posed]
    agree = sum(1 for e in errs if e is not None and e <= cfg.max_view_px)
    v.figures["views_within_px"] = agree
    if fused.n_views < cfg.min_views or fused.n_views < cfg.min_inlier_share * len(posed):
        v.reason = "views_disagree"
    elif v.figures["spread_mm"] > cfg.max_spread_mm:
        v.reason = "spread"
    elif fused.end_identity is None or fused.end_identity < cfg.min_tip or fused.ambiguous:
        v.reason = "tip_undecided"          # (before "uncertain": its covariance spans the turn)
    elif not (sig_px <= cfg.max_sigma_px and sig_deg <= cfg.max_sigma_deg):
        v.reason = "uncertain"
    elif agree < cfg.min_views:
        v.reason = "reprojection"
    else:
        v.kept = True
    return v


def frame_T_world_ecm(fr: Frame, outputs: dict, ds: Dataset) -> np.ndarray | None:
    """The endoscope's world pose at a frame: the folder's, from its joints, or the pipeline's."""
    if fr.T_world_ecm is not None:
        return np.asarray(fr.T_world_ecm, float)
    if fr.ecm_joints is not None and ds.arm is not None:
        return ds.arm.T_world_ecm(fr.ecm_joints)
    fo = outputs.get(fr.index)
    if fo is not None and fo.pose is not None and fo.pose.get("T_world_ecm") is not None:
        return fo.pose["T_world_ecm"]
    return None


def labelled_frame(ds: Dataset, fr: Frame, T_world_ecm, T_world_needle, index: int, sequence: int,
                   paths: dict) -> Frame:
    """The frame with the labels the fused pose gives (the module docstring)."""
    kps = project_keypoints(ds.meta, T_world_ecm, T_world_needle)
    T_ecm_needle = inv_T(T_world_ecm) @ T_world_needle
    vis, box = {}, {}
    for c in CAMERAS:
        _, vis[c] = true_keypoints(ds.meta.rig[c], T_ecm_needle, ds.meta.needle)
        b = arc_bbox(ds.meta.rig[c], T_ecm_needle, ds.meta.needle)
        box[c] = None if b is None else b.tolist()
    return Frame(index=index, stamp_ns=fr.stamp_ns, left=paths["left"], right=paths["right"],
                 sequence=sequence, step=fr.step, ecm_joints=fr.ecm_joints, T_world_ecm=T_world_ecm,
                 T_world_needle=T_world_needle, keypoints=kps, visible=vis, bbox=box)


def write_labels(sources: list, out, cfg: LabelConfig = LabelConfig(), progress: bool = True) -> dict:
    """Judge every group of every ``(folder, outputs)`` in ``sources`` and write the kept ones'
    frames as two dataset folders, ``out/train`` and ``out/fit`` (every ``fit_every``-th kept
    group), and ``out/labels.json`` (the verdicts, the counts per reason); returns that report.
    A complete ``out`` (its labels.json) is kept as it is (resumable)."""
    from common.progress import progress_bar
    out = Path(out)
    if (out / LABELS_FILE).is_file():
        return json.loads((out / LABELS_FILE).read_text())
    verdicts, outputs_of = [], {}
    for folder, outputs in sources:
        outputs_of[str(folder)] = outputs
        ds = Dataset(str(folder))
        groups = groups_of(ds, outputs)
        for key, frames in progress_bar(groups.items(), desc=f"label {Path(folder).name}", unit="group",
                                show=progress, leave=False):
            verdicts.append((folder, ds, judge_group(key, frames, ds, outputs, cfg)))
    kept = [x for x in verdicts if x[2].kept]
    split = {id(v): ("fit" if cfg.fit_every and len(kept) > 1 and k % cfg.fit_every == cfg.fit_every - 1
                     else "train") for k, (_, _, v) in enumerate(kept)}
    out.mkdir(parents=True, exist_ok=True)
    for part in ("train", "fit", "teacher"):
        if (out / part).exists():
            shutil.rmtree(out / part)      # an unfinished earlier run's
    rows, meta0 = [], None
    for part in ("train", "fit"):
        mine = [(f, ds, v) for f, ds, v in kept if split[id(v)] == part]
        if not mine:
            continue
        meta0 = mine[0][1].meta
        with staged_folder(str(out / part)) as tmp:
            with DatasetWriter(tmp, meta0) as w:
                for g, (folder, ds, v) in enumerate(mine):
                    if ds.meta.to_dict() != meta0.to_dict():
                        raise ValueError(f"{folder}: another rig or needle than {mine[0][0]}; adapt "
                                         f"folders of one rig together")
                    for i in v.frames:
                        fr = ds.frames[i]
                        T_we = frame_T_world_ecm(fr, {}, ds)
                        if T_we is None:
                            continue
                        paths = _link_images(ds, fr, tmp, w.n_frames)
                        w.append(labelled_frame(ds, fr, T_we, v.T_world_needle, w.n_frames, g, paths))
                        rows.append({"part": part, "index": w.n_frames - 1, "folder": str(folder),
                                     "source_index": int(fr.index), "group": v.key})
    n_teacher = write_teacher_frames([x for x in verdicts if not x[2].kept], outputs_of, out / "teacher")
    counts = Counter(v.reason for _, _, v in verdicts if not v.kept)
    report = {"config": asdict(cfg),
              "groups": len(verdicts), "kept_groups": len(kept),
              "frames": sum(len(v.frames) for _, _, v in verdicts),
              "kept_frames": sum(len(v.frames) for _, _, v in kept),
              "train_frames": sum(1 for r in rows if r["part"] == "train"),
              "fit_frames": sum(1 for r in rows if r["part"] == "fit"),
              "teacher_images": n_teacher,
              "dropped_groups": {r: counts.get(r, 0) for r in REASONS},
              "dropped_frames": {r: sum(len(v.frames) for _, _, v in verdicts if v.reason == r) for r in REASONS},
              "verdicts": [{"folder": str(f), "group": v.key, "frames": len(v.frames), "kept": v.kept,
                            "reason": v.reason, **{k: _num(x) for k, x in v.figures.items()}}
                           for f, _, v in verdicts],
              "labels": rows}
    (out / (LABELS_FILE + ".tmp")).write_text(json.dumps(report, indent=1) + "\n")
    os.replace(out / (LABELS_FILE + ".tmp"), out / LABELS_FILE)
    return report


def write_teacher_frames(dropped: list, outputs_of: dict, out) -> int:
    """The dropped groups' frames as a folder of boxes only (``bbox`` where the shipped detector
    found the needle, no keypoints, no poses): no labels, the images on which fine-tuning keeps
    the shipped weights' outputs (``common.detector.train``: ``teacher_dirs``), so that what no
    confirmed label shows (a needle in the jaws, edge-on, far) is not forgotten. Returns the
    number of images with a box (none: no folder)."""
    rows = []
    for folder, ds, v in dropped:
        outputs = outputs_of[str(folder)]
        for i in v.frames:
            fr = ds.frames[i]
            fo = outputs.get(fr.index)
            box = {}
            for c in CAMERAS:
                kp = fo.keypoints.get(c) if fo is not None else None
                b = kp.get("bbox") if kp and kp.get("found") else None
                box[c] = [float(x) for x in b] if b is not None and np.isfinite(np.asarray(b, float)).all() else None
            if any(b is not None for b in box.values()):
                rows.append((ds, fr, box))
    if not rows:
        return 0
    meta0 = rows[0][0].meta
    with staged_folder(str(out)) as tmp:
        with DatasetWriter(tmp, meta0) as w:
            for ds, fr, box in rows:
                if ds.meta.to_dict() != meta0.to_dict():
                    raise ValueError(f"{ds.path}: another rig or needle than {rows[0][0].path}; adapt "
                                     f"folders of one rig together")
                paths = _link_images(ds, fr, tmp, w.n_frames)
                w.append(Frame(index=w.n_frames, stamp_ns=fr.stamp_ns, left=paths["left"], right=paths["right"],
                               bbox=box))
    return sum(1 for _, _, box in rows for b in box.values() if b is not None)


def _link_images(ds: Dataset, fr: Frame, folder, index: int) -> dict:
    """Link (or copy) a frame's images into ``folder`` as the ``index``-th frame's; returns their
    paths there, per camera."""
    paths = {}
    for c in CAMERAS:
        src = Path(ds.path) / fr.image(c)
        paths[c] = f"images/{c}/{index:06d}{src.suffix.lower()}"
        link_or_copy(str(src), str(Path(folder) / paths[c]))
    return paths


def _num(x):
    if x is None:
        return None
    x = float(x)
    return x if np.isfinite(x) else None


def summary_lines(report: dict) -> list:
    """The report as lines for a person: kept, and the drops per reason."""
    lines = [f"pseudo-labels: kept {report['kept_groups']} of {report['groups']} groups "
             f"({report['kept_frames']} of {report['frames']} frames; {report['train_frames']} to train on, "
             f"{report['fit_frames']} held out for the calibration)"]
    for r in REASONS:
        if report["dropped_groups"].get(r):
            lines.append(f"  dropped {report['dropped_groups'][r]:>4} groups ({report['dropped_frames'][r]} frames): {r}")
    return lines


def score_against_truth(out, truth: dict) -> dict:
    """How right the pseudo-labels in ``out`` are: ``truth`` maps each adapted folder to the same
    folder with its ground truth (read only here, to score). Returns the share of frames kept,
    the labels' keypoint error (px, over the truly visible keypoints), their pose error, and the
    share of kept groups whose tip is the true one (not turned end for end, ``SWAP_DEG``)."""
    from common.evaluation.metrics import SWAP_DEG
    from common.geometry.transforms import pose_error
    out = Path(out)
    rep = json.loads((out / LABELS_FILE).read_text())
    parts = {p: Dataset(str(out / p)) for p in ("train", "fit") if (out / p).is_dir()}
    truths = {str(k): Dataset(str(v)) for k, v in truth.items()}
    kp_err, pos_mm, rot_deg, tip_right = [], [], [], {}
    for row in rep["labels"]:
        t = truths.get(row["folder"])
        if t is None:
            continue
        lab = parts[row["part"]].frames[row["index"]]
        tf = next((f for f in t.frames if f.index == row["source_index"]), None)
        if tf is None or tf.T_world_needle is None or tf.keypoints is None:
            continue
        for c in CAMERAS:
            vis = np.asarray(tf.visible[c], bool) if tf.visible is not None else np.ones(5, bool)
            kp_err += list(np.linalg.norm(lab.keypoints[c][vis] - tf.keypoints[c][vis], axis=1))
        dt, dr = pose_error(lab.T_world_needle, tf.T_world_needle)
        pos_mm.append(1e3 * dt)
        rot_deg.append(np.degrees(dr))
        tip_right.setdefault((row["folder"], row["group"]), np.degrees(dr) < SWAP_DEG)
    f = lambda x, q: float(np.quantile(x, q)) if len(x) else None
    return {"frames": rep["frames"], "kept_frames": rep["kept_frames"],
            "share_kept": rep["kept_frames"] / rep["frames"] if rep["frames"] else None,
            "scored_frames": len(pos_mm),
            "keypoint_px": {"mean": float(np.mean(kp_err)) if kp_err else None, "median": f(kp_err, 0.5),
                            "p90": f(kp_err, 0.9)},
            "pose": {"position_mm_mean": float(np.mean(pos_mm)) if pos_mm else None,
                     "orientation_deg_median": f(rot_deg, 0.5)},
            "groups": len(tip_right), "tip_right": float(np.mean(list(tip_right.values()))) if tip_right else None}
