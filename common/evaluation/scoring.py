"""Evaluation against ground truth: pose, keypoint and 3D-point errors, and ``results.json``.

Pure functions and a message collector: no process, no network. Units: poses and points in
metres inside, reported in mm / deg / px as the result keys say. A pose's position error is the
distance between the estimated and true needle origins; its orientation error is the angle of
``R_est^T R_true`` (``common.geometry.transforms.pose_error``), both compared in the ECM frame of the
frame they were made for.

Which frames count: a single-frame method (``pnp_average``, ``pnp_joint``, ``triangulation``,
``refined``) counts every frame with a known true pose; a multi-view method (``multiview``,
``multiview_refined``) counts the last step of every sequence (frames without a ``sequence``
are each a sequence of their own). A counted frame without a pose is a failure.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from common.geometry.ecm_kinematics import EcmArm
from common.geometry.end_identity import TIP_SURE
from common.geometry.needle import KEYPOINT_NAMES, NeedleModel
from common.geometry.transforms import R_to_rotvec, inv_T, pose_error
from common.methods import EXTRA_METHODS, MULTIVIEW_METHODS, PAPER_POSE, REPORTED_METHODS, last_stage
from common.runtime.messages import (
    Calibration,
    EndOfStream,
    GroundTruth,
    Keypoints,
    NodeStats,
    Points3D,
    PoseEstimate,
)

CAMERAS = ("left", "right")
METHODS = REPORTED_METHODS
"""The methods every ``results.json`` reports (``common.methods``)."""
RESULT_KEYS = ("dataset", "frames", "detector", "detection_rate", "keypoints_2d_px",
               "keypoints_3d_mm", "pose", "timing")

PAPER = {
    "keypoints_2d_px": {"all": 5.58},
    "pose": PAPER_POSE,
    "rate_hz": 10.0,
}
"""The paper's figures: mean 2D keypoint error (px), Table III (mean mm, mean deg), speed."""


# ---------------------------------------------------------------- statistics

def summary(values) -> dict:
    """``{"mean", "median", "std", "max"}`` of the finite values (None for each when none)."""
    v = _finite(values)
    if v.size == 0:
        return {"mean": None, "median": None, "std": None, "max": None}
    return {"mean": float(v.mean()), "median": float(np.median(v)), "std": float(v.std()),
            "max": float(v.max())}


def mean_std(values) -> dict:
    """``{"mean", "std", "median", "n"}`` of the finite values (None when there are none)."""
    v = _finite(values)
    if v.size == 0:
        return {"mean": None, "std": None, "median": None, "n": 0}
    return {"mean": float(v.mean()), "std": float(v.std()), "median": float(np.median(v)),
            "n": int(v.size)}


def pearson(x, y) -> Optional[float]:
    """Pearson correlation of the pairs where both are finite (x, y in px or mm); None if
    undefined (fewer than 3 pairs or no spread)."""
    x, y = np.asarray(x, float).ravel(), np.asarray(y, float).ravel()
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < 3:
        return None
    # Spreads below 1e-9 (px, mm) are numerical noise: no correlation to speak of.
    if x.std() < 1e-9 or y.std() < 1e-9:
        return None
    dx, dy = x - x.mean(), y - y.mean()
    return float(dx @ dy / math.sqrt(float(dx @ dx) * float(dy @ dy)))


def percentile(values, q: float) -> Optional[float]:
    v = _finite(values)
    return float(np.percentile(v, q)) if v.size else None


def _finite(values) -> np.ndarray:
    v = np.asarray(values, dtype=float).ravel()
    return v[np.isfinite(v)]


# ---------------------------------------------------------------- ground truth

def true_T_ecm_needle(gt: GroundTruth, arm=None) -> Optional[np.ndarray]:
    """The true needle pose in the ECM frame of a frame, or None when the truth lacks it.

    ``T_world_ecm`` comes from the truth, else from ``arm`` (an ``EcmArm``) and the joints.
    """
    if gt.T_world_needle is None:
        return None
    T_world_ecm = gt.T_world_ecm
    if T_world_ecm is None and arm is not None and gt.ecm_joints is not None:
        T_world_ecm = arm.T_world_ecm(gt.ecm_joints)
    if T_world_ecm is None:
        return None
    return inv_T(np.asarray(T_world_ecm, float)) @ np.asarray(gt.T_world_needle, float)


def last_steps(truths: dict) -> list[int]:
    """Seqs of the last step of every sequence (largest ``step``, then largest seq).

    A frame without ``sequence`` is a sequence of its own.
    """
    best: dict = {}
    for seq, gt in truths.items():
        key = ("seq", seq) if gt.sequence is None else ("sequence", gt.sequence)
        rank = (gt.step if gt.step is not None else -1, seq)
        if key not in best or rank > best[key][0]:
            best[key] = (rank, seq)
    return sorted(s for _, s in best.values())


def counted_seqs(method: str, truths: dict, posed: set) -> list[int]:
    """Frames on which ``method`` is scored: see the module docstring. ``posed``: seqs with a
    known true pose."""
    seqs = last_steps(truths) if method in MULTIVIEW_METHODS else sorted(truths)
    return [s for s in seqs if s in posed]


# ---------------------------------------------------------------- collection

@dataclass
class Collected:
    """Everything the evaluator gathered from the graph, keyed by frame ``seq``.

    ``arrivals_ns[method][seq]``: wall-clock time (ns) the pose reached the evaluator;
    ``node_ms[node]``: each node's median handler time (ms) from its stats (over every message
    it handled); ``node_cpu_ms[node]``: its CPU time per frame (ms) over the run.
    """

    truths: dict = field(default_factory=dict)
    keypoints: dict = field(default_factory=dict)        # (camera, seq) -> Keypoints
    points3d: dict = field(default_factory=dict)         # seq -> Points3D
    poses: dict = field(default_factory=dict)            # method -> seq -> PoseEstimate
    arrivals_ns: dict = field(default_factory=dict)      # method -> seq -> ns
    calib: Optional[Calibration] = None
    eos_frames: Optional[int] = None
    node_ms: dict = field(default_factory=dict)
    node_cpu_ms: dict = field(default_factory=dict)      # node -> CPU ms per frame over the run
    node_counters: dict = field(default_factory=dict)
    first_arrival_ns: Optional[int] = None
    last_arrival_ns: Optional[int] = None

    # -- feeding (the evaluator node calls these from its handlers)
    def _touch(self, now_ns: int):
        if self.first_arrival_ns is None:
            self.first_arrival_ns = now_ns
        self.last_arrival_ns = now_ns

    def add_truth(self, msg: GroundTruth, now_ns: int):
        self.truths[msg.seq] = msg
        self._touch(now_ns)

    def add_keypoints(self, msg: Keypoints, now_ns: int):
        self.keypoints[(msg.camera, msg.seq)] = msg
        self._touch(now_ns)

    def add_points3d(self, msg: Points3D, now_ns: int):
        self.points3d[msg.seq] = msg
        self._touch(now_ns)

    def add_pose(self, method: str, msg: PoseEstimate, now_ns: int):
        """Store a pose under ``method`` (the input it came on; the message's own ``method``
        field may name a variant, e.g. the epnp node's ``joint``)."""
        self.poses.setdefault(method, {})[msg.seq] = msg
        self.arrivals_ns.setdefault(method, {})[msg.seq] = now_ns
        self._touch(now_ns)

    def add_calib(self, msg: Calibration):
        self.calib = msg

    def add_stats(self, msg: NodeStats):
        self.node_ms[msg.node] = float(msg.proc_ms_p50)
        self.node_counters[msg.node] = dict(msg.counters)

    def add_eos(self, msg: EndOfStream):
        self.eos_frames = int(msg.frames)

    # -- state
    @property
    def frames(self) -> int:
        """Stereo frames in the run: the source's count when it said, else the truths seen."""
        return self.eos_frames if self.eos_frames is not None else len(self.truths)

    def complete(self, methods) -> bool:
        """True when every frame has its truth and every wired method a pose for every counted
        frame (then the evaluator need not wait for its drain timeout)."""
        if self.eos_frames is None or len(self.truths) < self.eos_frames:
            return False
        if getattr(self, "_counted_for", None) != len(self.truths):   # computed once per truth set
            arm = EcmArm.from_calibration(self.calib.ecm) if self.calib is not None else None
            posed = {s for s, gt in self.truths.items() if true_T_ecm_needle(gt, arm) is not None}
            self._counted = {m: counted_seqs(m, self.truths, posed) for m in (*METHODS, *EXTRA_METHODS)}
            self._counted_for = len(self.truths)
        for m in methods:
            got = self.poses.get(m, {})
            if any(s not in got for s in self._counted.get(m, ())):
                return False
        return True


# ---------------------------------------------------------------- per-frame errors

@dataclass
class Evaluation:
    """Per-frame error tables computed from a ``Collected``.

    ``pose[method]``: dict with ``seqs`` (counted frames), ``position_m`` and ``orientation_rad``
    (NaN where the method failed), ``distance_m`` (true camera distance) and ``n_views``.
    ``err2d_px[seq]``: (2, 5) errors (left, right) x A..E, NaN where not detected or not visible.
    ``err3d_m[seq]``: (5,) triangulated-point errors, NaN where missing.
    """

    frames: int
    seqs: list
    T_true: dict                      # seq -> true T_ecm_needle
    pose: dict
    err2d_px: dict
    err3d_m: dict
    images: int
    detected: int
    false_detections: int
    empty_images: int


def needle_distance_m(T_ecm_needle: np.ndarray) -> float:
    """Camera distance of the needle: its origin's distance from the ECM origin (m)."""
    return float(np.linalg.norm(T_ecm_needle[:3, 3]))


def pose_error_table(poses: dict, T_true: dict, seqs) -> dict:
    """Errors of one method on the counted ``seqs``: NaN where no pose was given."""
    pos = np.full(len(seqs), np.nan)
    rot = np.full(len(seqs), np.nan)
    views = np.full(len(seqs), np.nan)
    nees = np.full(len(seqs), np.nan)
    amb = np.full(len(seqs), np.nan)
    tip = np.full(len(seqs), np.nan)
    for i, s in enumerate(seqs):
        p = poses.get(s)
        if p is None:
            continue
        T = np.asarray(p.T_ecm_needle if isinstance(p, PoseEstimate) else p, float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            continue
        pos[i], rot[i] = pose_error(T, T_true[s])
        views[i] = getattr(p, "n_views", 1)
        nees[i] = pose_nees(T, getattr(p, "covariance", None), T_true[s])
        if getattr(p, "ambiguous", None) is not None:
            amb[i] = float(p.ambiguous)
        if getattr(p, "end_identity", None) is not None:
            tip[i] = float(p.end_identity)
    dist = np.array([needle_distance_m(T_true[s]) for s in seqs])
    return {"seqs": list(seqs), "position_m": pos, "orientation_rad": rot, "distance_m": dist,
            "n_views": views, "nees": nees, "ambiguous": amb, "end_identity": tip}


NEES_99PCT = 16.81   # chi-square(6) exceeds this in 1% of the draws (its median: 5.35)
SWAP_DEG = 150.0
"""A pose this far off in orientation is the needle turned end for end (tip for tail)."""


def pose_nees(T_est: np.ndarray, covariance, T_true: np.ndarray) -> float:
    """Normalised estimation error squared of a pose with its covariance (6, 6) over [rotation
    vector (rad), translation (m)] in the ECM frame, the error being the truth as a left
    increment of the estimate: chi-square with 6 degrees of freedom (median 5.35) when the
    covariance is honest. NaN without a usable covariance."""
    if covariance is None:
        return float("nan")
    C = np.asarray(covariance, float)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)):
        return float("nan")
    d = np.concatenate([R_to_rotvec(T_true[:3, :3] @ T_est[:3, :3].T), T_true[:3, 3] - T_est[:3, 3]])
    try:
        return float(d @ np.linalg.solve(C, d))
    except np.linalg.LinAlgError:
        return float("nan")


def keypoint_errors_2d(kp: Optional[Keypoints], uv_true, visible=None) -> np.ndarray:
    """(5,) pixel errors of a detection against the true A..E; NaN where the detector gave no
    point (not found, or NaN) or the truth marks the point invisible."""
    err = np.full(5, np.nan)
    if kp is None or not kp.found or uv_true is None:
        return err
    uv_true = np.asarray(uv_true, float).reshape(5, 2)
    d = np.linalg.norm(np.asarray(kp.uv, float).reshape(5, 2) - uv_true, axis=1)
    ok = np.isfinite(d)
    if visible is not None:
        ok &= np.asarray(visible, bool).reshape(5)
    err[ok] = d[ok]
    return err


def point_errors_3d(p3: Optional[Points3D], T_true: np.ndarray, needle: NeedleModel) -> np.ndarray:
    """(5,) distances (m) of triangulated A..E from the true keypoints in the ECM frame."""
    err = np.full(5, np.nan)
    if p3 is None:
        return err
    true = needle.keypoints() @ T_true[:3, :3].T + T_true[:3, 3]
    d = np.linalg.norm(np.asarray(p3.points_ecm, float).reshape(5, 3) - true, axis=1)
    ok = np.isfinite(d) & np.asarray(p3.valid, bool).reshape(5)
    err[ok] = d[ok]
    return err


def _needle_visible(gt: GroundTruth, camera: str) -> Optional[bool]:
    """Whether the truth says the needle is seen in a camera (None when it does not say)."""
    if gt.visible is not None and gt.visible.get(camera) is not None:
        return bool(np.any(np.asarray(gt.visible[camera], bool)))
    if gt.bbox is not None and camera in gt.bbox:
        return gt.bbox[camera] is not None
    return None


def evaluate(col: Collected, methods=None) -> Evaluation:
    """Compute every per-frame error table. ``methods``: the pose methods to score (default:
    METHODS plus whichever EXTRA_METHODS were received)."""
    needle = NeedleModel.from_dict(col.calib.needle) if col.calib is not None else NeedleModel()
    arm = EcmArm.from_calibration(col.calib.ecm) if col.calib is not None else None
    if methods is None:
        methods = list(METHODS) + [m for m in EXTRA_METHODS if col.poses.get(m)]
    seqs = sorted(col.truths)
    T_true = {}
    for s in seqs:
        T = true_T_ecm_needle(col.truths[s], arm)
        if T is not None:
            T_true[s] = T
    posed = set(T_true)

    pose = {m: pose_error_table(col.poses.get(m, {}), T_true, counted_seqs(m, col.truths, posed))
            for m in methods}

    err2d, err3d = {}, {}
    images = detected = false_det = empty = 0
    for s in seqs:
        gt = col.truths[s]
        rows = []
        for cam in CAMERAS:
            kp = col.keypoints.get((cam, s))
            images += 1
            found = kp is not None and kp.found
            detected += found
            if _needle_visible(gt, cam) is False:
                empty += 1
                false_det += found
            uv = gt.keypoints.get(cam) if gt.keypoints else None
            vis = gt.visible.get(cam) if gt.visible else None
            rows.append(keypoint_errors_2d(kp, uv, vis))
        err2d[s] = np.stack(rows)
        if s in T_true:
            err3d[s] = point_errors_3d(col.points3d.get(s), T_true[s], needle)
    return Evaluation(frames=col.frames, seqs=seqs, T_true=T_true, pose=pose, err2d_px=err2d,
                      err3d_m=err3d, images=images, detected=detected, false_detections=false_det,
                      empty_images=empty)


# ---------------------------------------------------------------- tables

def keypoint_table(ev: Evaluation) -> dict:
    """Table II: per keypoint A..E and ``all``: 2D px and 3D mm mean/std (+median, n) and the
    2D-3D correlation over frames (2D error averaged over the two cameras)."""
    seqs = ev.seqs
    e2 = np.stack([ev.err2d_px[s] for s in seqs]) if seqs else np.full((0, 2, 5), np.nan)
    s3 = [s for s in seqs if s in ev.err3d_m]
    e3 = np.stack([ev.err3d_m[s] for s in s3]) * 1e3 if s3 else np.full((0, 5), np.nan)
    with warnings.catch_warnings():   # frames with no 2D error in either camera give NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        e2_frame = np.nanmean(e2, axis=1) if len(seqs) else np.full((0, 5), np.nan)  # (F, 5)
    e2_for3 = np.stack([e2_frame[seqs.index(s)] for s in s3]) if s3 else np.full((0, 5), np.nan)
    out2, out3, corr = {}, {}, {}
    for k, name in enumerate(KEYPOINT_NAMES):
        out2[name] = mean_std(e2[:, :, k])
        out3[name] = mean_std(e3[:, k])
        corr[name] = pearson(e2_for3[:, k], e3[:, k])
    out2["all"] = mean_std(e2)
    out3["all"] = mean_std(e3)
    corr["all"] = pearson(e2_for3, e3)
    return {"keypoints_2d_px": out2, "keypoints_3d_mm": out3, "correlation_2d_3d": corr}


def pose_table(ev: Evaluation) -> dict:
    """Table III: per method position (mm) and orientation (deg) summaries, n, failures; for
    methods that flag poses, the NEES, the ambiguous share, the poses turned end for end,
    (``confident_share``: of those not flagged ``ambiguous`` or stating a sure tip),
    ``end_identity`` (over the poses that state one: the share the poses' own probabilities say
    is turned, ``stated``, against the share that is, ``measured``; also over the flagged ones)
    and ``sure``: the same summaries over the poses not flagged ambiguous."""
    out = {}
    for m, t in ev.pose.items():
        expected = len(t["seqs"])
        ok = np.isfinite(t["position_m"])
        n = int(ok.sum())
        out[m] = {"position_mm": summary(t["position_m"] * 1e3),
                  "orientation_deg": summary(np.degrees(t["orientation_rad"])),
                  "n": n, "expected": expected, "failures": expected - n,
                  "failure_rate": (expected - n) / expected if expected else None,
                  "failed_seqs": [int(s) for s, good in zip(t["seqs"], ok) if not good]}
        if m in MULTIVIEW_METHODS:
            out[m]["mean_views"] = float(np.nanmean(t["n_views"])) if n else None
        nees = t["nees"][np.isfinite(t["nees"])]
        if len(nees):       # how honest the stated covariance is (chi-square(6): median 5.35)
            out[m]["nees"] = {"median": float(np.median(nees)), "over_99pct": float(np.mean(nees > NEES_99PCT)),
                              "n": int(len(nees))}
        amb = t["ambiguous"][np.isfinite(t["ambiguous"])]
        if len(amb):
            out[m]["ambiguous_share"] = float(amb.mean())
        if n:
            # turned end for end: about a half turn off; "confident" ones were not flagged
            # ambiguous, or stated their tip sure (flagged for another reason, a mirror image)
            turned = ok & (np.degrees(np.nan_to_num(t["orientation_rad"])) > SWAP_DEG)
            flagged = np.isfinite(t["ambiguous"]) & (np.nan_to_num(t["ambiguous"]) > 0)
            tip = t.get("end_identity", np.full(len(ok), np.nan))
            stated = ok & np.isfinite(tip)
            tip_sure = stated & (np.nan_to_num(tip) >= TIP_SURE)
            out[m]["end_for_end"] = {"share": float(turned.sum() / n),
                                     "confident_share": float((turned & (~flagged | tip_sure)).sum() / n)}
            if stated.any():
                wrong = 1.0 - tip
                out[m]["end_identity"] = {
                    part: {"n": int(sel.sum()), "stated": float(wrong[sel].mean()),
                           "measured": float(turned[sel].mean())}
                    for part, sel in (("all", stated), ("flagged", stated & flagged)) if sel.any()}
            if len(amb):   # what a robot that acts only on unflagged poses gets
                sure = ok & np.isfinite(t["ambiguous"]) & ~flagged
                out[m]["sure"] = {"n": int(sure.sum()),
                                  "position_mm": summary(t["position_m"][sure] * 1e3),
                                  "orientation_deg": summary(np.degrees(t["orientation_rad"][sure]))}
    return out


def process_cpu_seconds(pid: int) -> Optional[float]:
    """CPU time (user + system, s) process ``pid`` has used, from /proc; None if unknown."""
    import os
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def cpu_steal_seconds() -> Optional[float]:
    """CPU time (s, summed over CPUs) the hypervisor has given other guests so far (``steal`` in
    /proc/stat): on a shared virtual machine, what makes a slow minute; None if unknown."""
    import os
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def timing_summary(col: Collected, final_method: Optional[str] = None) -> dict:
    """``{"throughput_hz", "latency_ms": {"p50", "p99"}, "per_node_ms": {node: p50}}``.

    Latency: wall-clock arrival of the ``final_method`` pose at the evaluator minus the frame's
    ``stamp_ns`` (the time the source published the frame). Throughput: poses of the final
    method per second, from the first published frame to the last pose.
    """
    if final_method is None:
        final_method = last_stage(m for m in col.poses if col.poses.get(m))
    lat, thr = [], None
    if final_method is not None:
        poses, arr = col.poses[final_method], col.arrivals_ns[final_method]
        lat = [(arr[s] - p.stamp_ns) / 1e6 for s, p in poses.items()]
        first = min(p.stamp_ns for p in poses.values())
        span = (max(arr.values()) - first) / 1e9
        thr = len(poses) / span if span > 0 else None
    return {"throughput_hz": thr,
            "latency_ms": {"p50": percentile(lat, 50), "p99": percentile(lat, 99)},
            "per_node_ms": dict(sorted(col.node_ms.items())),
            "per_node_cpu_ms_per_frame": dict(sorted(col.node_cpu_ms.items())),
            "final_method": final_method}


def build_results(col: Collected, *, dataset: str, detector: str, ev: Optional[Evaluation] = None,
                  extra: Optional[dict] = None) -> dict:
    """The ``results.json`` document: exactly RESULT_KEYS, plus informative keys beside them."""
    ev = ev if ev is not None else evaluate(col)
    kt = keypoint_table(ev)
    pt = pose_table(ev)
    res = {
        "dataset": str(dataset),
        "frames": int(ev.frames),
        "detector": str(detector),
        "detection_rate": (ev.detected / ev.images) if ev.images else None,
        "keypoints_2d_px": kt["keypoints_2d_px"],
        "keypoints_3d_mm": kt["keypoints_3d_mm"],
        "pose": pt,
        "timing": timing_summary(col),
        "correlation_2d_3d": kt["correlation_2d_3d"],
        "failure_rate": {m: v["failure_rate"] for m, v in pt.items()},
        "images": ev.images,
        "false_detections": ev.false_detections,
        "images_without_needle": ev.empty_images,
        "frames_with_truth": len(ev.T_true),
        "node_counters": {n: {k: v for k, v in c.items()
                              if isinstance(v, int) and not isinstance(v, bool) and k != "restarts"}
                          for n, c in sorted(col.node_counters.items())},
        "paper": {"keypoints_2d_px": PAPER["keypoints_2d_px"],
                  "pose": {m: {"position_mm": p, "orientation_deg": o}
                           for m, (p, o) in PAPER["pose"].items()},
                  "rate_hz": PAPER["rate_hz"]},
    }
    if extra:
        res.update(extra)
    return res


def check_results(res: dict) -> list[str]:
    """Problems with a ``results.json`` document's required keys and types (empty when fine)."""
    bad = []

    def num(x, where, optional=True):
        if x is None and optional:
            return
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            bad.append(f"{where}: expected a number, got {type(x).__name__}")

    for k in RESULT_KEYS:
        if k not in res:
            bad.append(f"{k}: missing")
    if bad:
        return bad
    if not isinstance(res["dataset"], str):
        bad.append("dataset: expected a string")
    if isinstance(res["frames"], bool) or not isinstance(res["frames"], int):
        bad.append("frames: expected an int")
    if not isinstance(res["detector"], str):
        bad.append("detector: expected a string")
    num(res["detection_rate"], "detection_rate")
    for key in ("keypoints_2d_px", "keypoints_3d_mm"):
        for name in (*KEYPOINT_NAMES, "all"):
            d = res[key].get(name)
            if not isinstance(d, dict):
                bad.append(f"{key}.{name}: missing")
                continue
            for f in ("mean", "std"):
                if f not in d:
                    bad.append(f"{key}.{name}.{f}: missing")
                num(d.get(f), f"{key}.{name}.{f}")
    for m in METHODS:
        d = res["pose"].get(m)
        if not isinstance(d, dict):
            bad.append(f"pose.{m}: missing")
            continue
        for q in ("position_mm", "orientation_deg"):
            for f in ("mean", "median", "std", "max"):
                if not isinstance(d.get(q), dict) or f not in d[q]:
                    bad.append(f"pose.{m}.{q}.{f}: missing")
                else:
                    num(d[q][f], f"pose.{m}.{q}.{f}")
        if isinstance(d.get("n"), bool) or not isinstance(d.get("n"), int):
            bad.append(f"pose.{m}.n: expected an int")
    t = res["timing"]
    if not isinstance(t, dict):
        return bad + ["timing: expected a map"]
    num(t.get("throughput_hz"), "timing.throughput_hz")
    if not isinstance(t.get("latency_ms"), dict):
        bad.append("timing.latency_ms: missing")
    else:
        for f in ("p50", "p99"):
            if f not in t["latency_ms"]:
                bad.append(f"timing.latency_ms.{f}: missing")
            num(t["latency_ms"].get(f), f"timing.latency_ms.{f}")
    if not isinstance(t.get("per_node_ms"), dict):
        bad.append("timing.per_node_ms: expected a map")
    else:
        for node, v in t["per_node_ms"].items():
            num(v, f"timing.per_node_ms.{node}", optional=False)
    return bad


def to_jsonable(obj):
    """Replace NaN/inf by None and numpy scalars by Python numbers (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj
