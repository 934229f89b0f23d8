"""The evaluation of a run: the messages a graph published (``Collected``), scored against the
truth (``evaluate`` -> ``Evaluation``) and summed up per keypoint and per method (``keypoint_table``,
``pose_table``). The errors themselves: ``common.evaluation.metrics``."""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from common.evaluation.metrics import (
    NEES_99PCT,
    RIGHT_DEG,
    RIGHT_MM,
    SWAP_DEG,
    needle_visible,
    counted_seqs,
    keypoint_errors_2d,
    mean_std,
    pearson,
    point_errors_3d,
    pose_error_table,
    reliability_table,
    summary,
)
from common.data.truth import true_T_ecm_needle
from common.frames import CAMERAS
from common.geometry.ecm_kinematics import EcmArm
from common.geometry.end_identity import TIP_SURE
from common.geometry.needle import KEYPOINT_NAMES, NeedleModel
from common.methods import EXTRA_METHODS, MULTIVIEW_METHODS, REPORTED_METHODS
from common.runtime.messages import (
    Calibration,
    EndOfStream,
    GroundTruth,
    InHandPose,
    InstrumentState,
    Keypoints,
    NodeStats,
    Points3D,
    PoseEstimate,
)


# ---------------------------------------------------------------- collection

@dataclass
class Collected:
    """Everything the evaluator gathered from the graph, keyed by frame ``seq``.

    ``arrivals_ns[method][seq]``: wall-clock time (ns) the pose reached the evaluator;
    ``truth_arrivals_ns[seq]``: the frame's truth's (the source sends it with the images: when the
    frame was published, whatever its stamp says);
    ``node_ms[node]``: each node's median handler time (ms) from its stats (over every message
    it handled); ``node_cpu_ms[node]``: its CPU time per frame (ms) over the run.
    """

    truths: dict = field(default_factory=dict)
    keypoints: dict = field(default_factory=dict)        # (camera, seq) -> Keypoints
    points3d: dict = field(default_factory=dict)         # seq -> Points3D
    poses: dict = field(default_factory=dict)            # method -> seq -> PoseEstimate
    arrivals_ns: dict = field(default_factory=dict)      # method -> seq -> ns
    truth_arrivals_ns: dict = field(default_factory=dict)  # seq -> ns
    calib: Optional[Calibration] = None
    eos_frames: Optional[int] = None
    node_ms: dict = field(default_factory=dict)
    node_cpu_ms: dict = field(default_factory=dict)      # node -> CPU ms per frame over the run
    node_counters: dict = field(default_factory=dict)
    instruments: dict = field(default_factory=dict)      # seq -> {name: InstrumentState}
    arm_corrections: dict = field(default_factory=dict)  # seq -> {name: ArmCorrection} (the tracker's)
    in_hand: dict = field(default_factory=dict)          # seq -> InHandPose (the tracker's)
    first_arrival_ns: Optional[int] = None
    last_arrival_ns: Optional[int] = None

    # -- feeding (the evaluator node calls these from its handlers)
    def _touch(self, now_ns: int):
        if self.first_arrival_ns is None:
            self.first_arrival_ns = now_ns
        self.last_arrival_ns = now_ns

    def add_truth(self, msg: GroundTruth, now_ns: int):
        self.truths[msg.seq] = msg
        self.truth_arrivals_ns[msg.seq] = now_ns
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

    def add_instrument(self, msg: InstrumentState):
        self.instruments.setdefault(msg.seq, {})[msg.name] = msg

    def add_arm_correction(self, msg, now_ns: int):
        """The tracker's estimate of an arm's error (``ArmCorrection``) in a frame."""
        self.arm_corrections.setdefault(msg.seq, {})[msg.name] = msg
        self._touch(now_ns)

    def add_in_hand(self, msg: InHandPose, now_ns: int):
        self.in_hand[msg.seq] = msg
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
            self._counted = {m: counted_seqs(m, self.truths, posed) for m in (*REPORTED_METHODS, *EXTRA_METHODS)}
            self._counted_for = len(self.truths)
        for m in methods:
            got = self.poses.get(m, {})
            if any(s not in got for s in self._counted.get(m, ())):
                return False
        return True


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


def evaluate(col: Collected, methods=None) -> Evaluation:
    """Compute every per-frame error table. ``methods``: the pose methods to score (default:
    REPORTED_METHODS plus whichever EXTRA_METHODS were received)."""
    needle = NeedleModel.from_dict(col.calib.needle) if col.calib is not None else NeedleModel()
    arm = EcmArm.from_calibration(col.calib.ecm) if col.calib is not None else None
    if methods is None:
        methods = list(REPORTED_METHODS) + [m for m in EXTRA_METHODS if col.poses.get(m)]
    seqs = sorted(col.truths)
    T_true = {}
    for s in seqs:
        T = true_T_ecm_needle(col.truths[s], arm)
        if T is not None:
            T_true[s] = T
    posed = set(T_true)

    pose = {m: pose_error_table(col.poses.get(m, {}), T_true, counted_seqs(m, col.truths, posed), needle)
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
            if needle_visible(gt, cam) is False:
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
    and ``sure``: the same summaries over the poses not flagged ambiguous.

    The end identity's figures (docs/evaluation.md#end-identity-of-the-poses): ``confident_swaps``,
    poses turned end for end that state a sure tip or are not flagged; ``undecided``, the poses
    flagged with an unsure tip (below ``TIP_SURE``): their share and how many are turned;
    ``modulo_turn``, the errors with each undecided pose scored against the nearer of its two
    readings; ``reliability``, the stated turned share against the measured one per bin of the
    stated tip probability, each within the bound or not (``within_calibration_bound``);
    ``sure_and_right``, the share of all counted frames posed sure (not flagged) and within
    ``RIGHT_MM`` / ``RIGHT_DEG``."""
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
            confident = turned & (~flagged | tip_sure)
            out[m]["end_for_end"] = {"share": float(turned.sum() / n),
                                     "confident_share": float(confident.sum() / n)}
            out[m]["confident_swaps"] = int(confident.sum())
            undecided = stated & flagged & (np.nan_to_num(tip, nan=1.0) < TIP_SURE)
            out[m]["undecided"] = {"n": int(undecided.sum()), "share": float(undecided.sum() / n),
                                   "turned": int((undecided & turned).sum())}
            rot = t["orientation_rad"]
            rot_mod = np.where(undecided, np.fmin(rot, t.get("orientation_turned_rad", rot)), rot)
            out[m]["modulo_turn"] = {"position_mm": summary(t["position_m"] * 1e3),
                                     "orientation_deg": summary(np.degrees(rot_mod))}
            if stated.any():
                out[m]["reliability"] = reliability_table(tip[stated], turned[stated])
            sure_pose = ok & ~flagged
            right = (np.nan_to_num(t["position_m"], nan=np.inf) * 1e3 <= RIGHT_MM) & \
                    (np.degrees(np.nan_to_num(rot, nan=np.inf)) <= RIGHT_DEG)
            out[m]["sure_and_right"] = float((sure_pose & right).sum() / expected) if expected else None
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
