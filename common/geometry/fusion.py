"""Multi-view fusion: the needle pose from the last k estimates made while the endoscope moves.

Each estimate ``T_ecm_needle_i`` is kept with the endoscope pose ``T_world_ecm_i`` at which it
was made. At every new estimate all queued ones are mapped into the current ECM frame,
``inv(T_world_ecm_now) @ T_world_ecm_i @ T_ecm_needle_i``, outliers are removed (farther than
``max_dist_m`` or ``max_angle_rad`` from a robust centre, the medoid), and the inliers are
averaged: chordal rotation mean and mean translation, or, when every inlier carries a 6x6
covariance, their information-weighted mean (Gauss-Newton on the Mahalanobis distances), whose
stated covariance allows for the views' errors being alike (``fuse_poses``). A position and
orientation error every view shares (``common_sigma_m``, ``common_sigma_rad``: the needle
model's own, declared inside each covariance) is taken out before the views are weighed and
added back once to the fused covariance: averaging views does not shrink it, and it must not
hide what each view's images pin down.

Covariances follow ``common.geometry.pnp``: over ``[w, v]`` with ``R = exp([w]x) R0``, ``t = t0 + v``
(rotation in ECM axes about the needle origin, translation of the origin, rad and m). Moving
one to another ECM frame rotates both blocks: ``Sigma' = blkdiag(R, R) Sigma blkdiag(R, R)^T``.

Which end is the tip is decided by evidence, not by a count: views turned end for end from the
fused pose (the same origin within ``max_dist_m``, more than ``TURNED_RAD`` off) are never
averaged with it, but when their stated end identities (log-odds summed) outweigh the inliers'
the fusion is made of them instead. A view unsure of its tip carries a covariance widened over
its turn (``common.geometry.end_identity.state``, which the view says: ``identity_widened``);
that widening is taken out (``end_identity.reading_covariance``) before the views
are weighed (it says "or the other end", not "anywhere between": weighed with it, a view's
loose turn direction, coupled to its position, pulled a fused pose 11 deg off views 1.5 and
4.7 deg off). The fused pose states the mean of every view's log-odds about it (a turned view's
counting against it) and, below ``TIP_SURE``, is flagged ``ambiguous`` with its covariance
widened over the turn again, by that probability, as the pose nodes do for one frame
(``FusedPose.identity_widened``).

A planar arc seen nearly edge-on has a mirror image that fits one view almost as well
(``common.geometry.refine.mirror_pose``); a pose node flags such a view ``ambiguous``. The
mirror image moves with the viewpoint and the needle does not, so the group decides: a flagged
view is read as its mirror image where that is what the others agree on
(``mirror_consensus``), with its covariance carried along (``refine.mirror_covariance``).

The queue resets when the needle has moved in the world: when the last ``reset_after``
estimates agree with one another but are all farther than ``reset_dist_m`` or
``reset_angle_rad`` from the fused pose of the older ones (a single wild estimate is only an
outlier), or when the estimate's ``sequence`` label changes.
"""
from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass

import numpy as np

from common.constraints import PositiveNumber, at_least, check_fields
from common.geometry.end_identity import TIP_SURE, identity_covariance, logit, reading_covariance, sigmoid, was_widened
from common.geometry.needle import NeedleModel
from common.geometry.refine import mirror_covariance, mirror_pose
from common.geometry.transforms import inv_T, make_T, pose_mean, rotvec_to_R, symmetrise

TURNED_RAD = np.deg2rad(150.0)
"""A view this far off in orientation, at the fused pose's origin, is the needle turned end for end."""


@dataclass
class QueuedEstimate:
    """One estimate in the queue; ``covariance`` is in its own ECM frame (or None)."""

    T_ecm_needle: np.ndarray
    T_world_ecm: np.ndarray
    covariance: np.ndarray | None = None
    seq: int | None = None
    common_sigma_m: float = 0.0      # inside covariance, shared by every view (module docstring)
    common_sigma_rad: float = 0.0
    ambiguous: bool = False          # the view's images could not decide (e.g. which end is the tip)
    end_identity: float | None = None  # probability that the tip is where the pose puts it
    identity_widened: bool | None = None   # its covariance spans its turn (None: not stated)

    @property
    def T_world_needle(self) -> np.ndarray:
        return self.T_world_ecm @ self.T_ecm_needle


@dataclass
class FusedPose:
    """The fused pose in the current ECM frame and in the world.

    ``n_views``: estimates averaged (the inliers); ``n_queued``: estimates in the queue;
    ``inliers``: mask over the queue, oldest first; ``covariance`` (6, 6) in the current ECM
    frame when the inputs carried covariances; ``reset``: this estimate started a new queue;
    ``rms_m``: RMS distance of the inliers' positions to the fused one; ``common_sigma_m``,
    ``common_sigma_rad`` the inliers' shared position and orientation error, inside
    ``covariance``; ``ambiguous`` when every inlier was (averaging views that each could not
    decide does not decide: the covariance is then the inliers' mean one, which spans what each
    left open); ``end_identity`` the probability that the tip is where the pose puts it: the
    mean log-odds of the inliers' and of the views turned end for end from it, which count
    against it (None when none stated one); ``turned``: how many views were turned end for end;
    ``identity_widened``: whether ``covariance`` spans the turn end for end (widened here below
    ``TIP_SURE``, or the mean of inliers' covariances that each did).
    """

    T_ecm_needle: np.ndarray
    T_world_needle: np.ndarray
    n_views: int
    n_queued: int
    inliers: np.ndarray
    covariance: np.ndarray | None = None
    reset: bool = False
    rms_m: float = 0.0
    common_sigma_m: float = 0.0
    ambiguous: bool = False
    common_sigma_rad: float = 0.0
    end_identity: float | None = None
    turned: int = 0
    identity_widened: bool = False



def without_common(cov: np.ndarray, sigma_m: float, sigma_rad: float = 0.0) -> np.ndarray:
    """``cov`` less a shared isotropic position variance ``sigma_m**2`` and orientation variance
    ``sigma_rad**2`` (the views' own part); ``cov`` unchanged when that would not leave it
    positive definite (a producer that did not add it)."""
    if not (sigma_m > 0 or sigma_rad > 0):
        return cov
    out = np.array(cov, dtype=float)
    out[:3, :3] -= max(sigma_rad, 0.0) ** 2 * np.eye(3)
    out[3:, 3:] -= max(sigma_m, 0.0) ** 2 * np.eye(3)
    return out if np.linalg.eigvalsh(symmetrise(out)).min() > 0 else cov


def covariance_to_frame(cov: np.ndarray, R_a_b: np.ndarray) -> np.ndarray:
    """A [w, v] pose covariance expressed in frame b -> the same in frame a."""
    A = np.zeros((6, 6))
    A[:3, :3] = A[3:, 3:] = R_a_b
    return A @ cov @ A.T


def pairwise_errors(Ts, Us=None):
    """(position m, angle rad) matrices between poses ``Ts`` (n) and ``Us`` (m, default Ts)."""
    Ts = np.asarray(Ts, dtype=float).reshape(-1, 4, 4)
    Us = Ts if Us is None else np.asarray(Us, dtype=float).reshape(-1, 4, 4)
    dt = np.linalg.norm(Ts[:, None, :3, 3] - Us[None, :, :3, 3], axis=2)
    tr = np.einsum("aij,bij->ab", Ts[:, :3, :3], Us[:, :3, :3])      # trace(R_a^T R_b)
    return dt, np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def gate_distances(Ts, max_dist_m: float, max_angle_rad: float):
    """Pairwise distances between poses in units of the inlier gate, truncated at 2:
    ``min(2, max(dt / max_dist_m, dr / max_angle_rad))`` (<= 1: within the gate)."""
    dt, dr = pairwise_errors(Ts)
    return np.minimum(2.0, np.maximum(dt / max_dist_m, dr / max_angle_rad))


def robust_centre(Ts, max_dist_m: float, max_angle_rad: float) -> int:
    """Index of the medoid: the pose with the smallest sum of ``gate_distances`` to all the others."""
    return int(np.argmin(gate_distances(Ts, max_dist_m, max_angle_rad).sum(axis=1)))


def _log_so3_many(R: np.ndarray) -> np.ndarray:
    """(m, 3, 3) rotations -> (m, 3) rotation vectors; for angles well below pi (inliers)."""
    c = np.clip((np.einsum("mii->m", R) - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(c)
    v = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1) / 2.0
    s = np.sin(th)
    scale = np.where(s > 1e-12, th / np.where(s > 1e-12, s, 1.0), 1.0)
    return v * scale[:, None]


def information_mean(Ts, covariances, T0=None, iterations: int = 10):
    """Information-weighted mean of poses with [w, v] covariances (all in one frame).

    Minimises sum_i r_i^T inv(Sigma_i) r_i, r_i = [log(R_i R^T), t_i - t], by Gauss-Newton from
    ``T0`` (default the chordal mean). Returns (T, covariance of the mean) or None when a
    covariance is singular. The poses must lie well within a half turn of one another.
    """
    Ts = np.asarray(Ts, dtype=float).reshape(-1, 4, 4)
    C = np.asarray(covariances, dtype=float).reshape(-1, 6, 6)
    try:
        infos = np.linalg.inv(0.5 * (C + C.transpose(0, 2, 1)))
        H_inv = np.linalg.inv(infos.sum(axis=0))
    except np.linalg.LinAlgError:
        return None
    if not (np.all(np.isfinite(infos)) and np.all(np.isfinite(H_inv))):
        return None
    T = pose_mean(Ts) if T0 is None else np.array(T0, dtype=float)
    for _ in range(iterations):
        r = np.concatenate([_log_so3_many(Ts[:, :3, :3] @ T[:3, :3].T), Ts[:, :3, 3] - T[:3, 3]], axis=1)
        delta = H_inv @ np.einsum("mij,mj->i", infos, r)
        T = make_T(rotvec_to_R(delta[:3]) @ T[:3, :3], T[:3, 3] + delta[3:])
        if np.linalg.norm(delta[:3]) < 1e-10 and np.linalg.norm(delta[3:]) < 1e-11:   # 1e-10 rad, 0.01 nm
            break
    return T, symmetrise(H_inv)


def fuse_poses(Ts, covariances=None, max_dist_m: float = 0.005,
               max_angle_rad: float = np.deg2rad(15.0)):
    """Robust mean of poses given in one frame -> (T, inlier mask, covariance or None).

    Inliers lie within ``max_dist_m`` and ``max_angle_rad`` of the medoid; they are averaged by
    ``information_mean`` when every inlier has a covariance, else chordal/arithmetic mean. The
    covariance is the covariance intersection of the inliers with equal weights: n times the
    information mean's, which would hold only for independent views. These are not: the same
    needle through the same detector from nearly the same place, their errors move together
    (the fused refined poses' NEES median, in ``needletrack eval``'s results, is near
    chi-square(6)'s 5.35 so, several times that taken as independent).
    """
    Ts = [np.asarray(T, dtype=float) for T in Ts]
    if not Ts:
        raise ValueError("fuse_poses: no poses")
    c = robust_centre(Ts, max_dist_m, max_angle_rad)
    dt, dr = pairwise_errors(Ts, [Ts[c]])
    inl = (dt[:, 0] <= max_dist_m) & (dr[:, 0] <= max_angle_rad)
    sel = [T for T, ok in zip(Ts, inl) if ok]
    T = pose_mean(sel)
    cov = None
    if covariances is not None:
        covs = [C for C, ok in zip(covariances, inl) if ok]
        if all(C is not None for C in covs):
            # Weighed by covariances no wider than the inlier gate: every inlier lies within it,
            # so a wider spread (a view unsure which end is the tip) says "no weight", and is
            # not left to decide a direction every view leaves open. The stated covariance
            # keeps each view's own.
            gate = np.array([max_angle_rad] * 3 + [max_dist_m] * 3)
            res = information_mean(sel, [_clip_to_gate(C, gate) for C in covs], T)
            stated = information_mean(sel, covs, T, iterations=0)
            if res is not None and stated is not None:
                T, cov = within_views(res[0], sel, T), len(sel) * stated[1]
    return T, inl, cov


def within_views(T_weighted: np.ndarray, Ts, T_mean: np.ndarray) -> np.ndarray:
    """``T_weighted``, a matrix-weighted mean of the poses ``Ts``, with its rotation held among
    theirs: the plain mean's (``T_mean``) where it lies farther from that than every view does.
    Views whose covariances are long and coupled (rotation about an arc seen edge-on against
    depth) differ a little in how they couple, and their weighted rotation then runs out along
    the long direction, past every view (the standard set's group 22: 5.5 deg off from five
    views 1.2-2.8 deg off). The position keeps its weighting: there the coupling is what
    corrects the views' depth."""
    _, dr = pairwise_errors(Ts, [T_mean])
    _, er = pairwise_errors([T_weighted], [T_mean])
    return T_weighted if er[0, 0] <= dr.max() else make_T(T_mean[:3, :3], T_weighted[:3, 3])


def mirror_consensus(Ts, mirrors, max_dist_m: float, max_angle_rad: float) -> np.ndarray:
    """Which views to read as their mirror image (bool mask): ``mirrors[i]`` is view i's mirror
    reading (``refine.mirror_pose``, in the same frame as ``Ts``) or None for a view that is sure
    of its own. The needle is one pose in the world, and a mirror image moves with the viewpoint:
    of all readings, the group's is the one that the most views have a reading within the gate
    of (``max_dist_m``, ``max_angle_rad``); among equals, the one that the most views' own
    readings agree with, then the nearest (``gate_distances``). A view
    takes its mirror where that is nearer the group's reading than its own."""
    alt = [i for i, M in enumerate(mirrors) if M is not None]
    take = np.zeros(len(Ts), bool)
    if not alt:
        return take
    n = len(Ts)
    D = gate_distances(list(Ts) + [mirrors[i] for i in alt], max_dist_m, max_angle_rad)
    near = D[:, :n].copy()
    for k, i in enumerate(alt):
        near[:, i] = np.minimum(near[:, i], D[:, n + k])
    views, own, spread = (near <= 1.0).sum(axis=1), (D[:, :n] <= 1.0).sum(axis=1), near.sum(axis=1)
    c = min(range(len(D)), key=lambda a: (-views[a], -own[a], spread[a]))
    for k, i in enumerate(alt):
        take[i] = D[c, n + k] < D[c, i]
    return take


def _clip_to_gate(C: np.ndarray, gate: np.ndarray) -> np.ndarray:
    """``C`` with its spread in units of ``gate`` (6,) limited to 1 sigma."""
    S = np.diag(1.0 / gate)
    w, V = np.linalg.eigh(S @ symmetrise(C) @ S)
    Si = np.diag(gate)
    return Si @ (V * np.minimum(w, 1.0)) @ V.T @ Si


@dataclass(frozen=True)
class FusionConfig:
    """The fusion queue's settings (the fusion node's params of the same names); distances in mm,
    angles in degrees, as a graph states them."""
    k: at_least(1) = 5                          # estimates fused: the newest k
    max_dist_mm: PositiveNumber = 5.0           # an estimate farther than this from the fused pose is an outlier ...
    max_angle_deg: PositiveNumber = 15.0        # ... or turned more than this
    reset_dist_mm: PositiveNumber = 10.0        # reset_after estimates in a row this far from the fused pose ...
    reset_angle_deg: PositiveNumber = 45.0      # ... or turned this much mean the needle moved: the queue starts again
    reset_after: at_least(1) = 3
    use_covariance: bool = True                 # weigh the estimates by their covariances (else equally)

    def __post_init__(self):
        check_fields(self, "fusion: {name} {why}")


class MultiViewFusion:
    """The fusion queue (see the module docstring). ``config``: its settings, ``settings`` any of
    its fields set anew (``MultiViewFusion(k=3)``); kept as metres and radians (``max_dist_m``,
    ``max_angle_rad``, ``reset_dist_m``, ``reset_angle_rad``)."""

    def __init__(self, config: FusionConfig | None = None, *, needle: NeedleModel | None = None, **settings):
        self.config = c = dataclasses.replace(config or FusionConfig(), **settings)
        self.k = c.k
        self.max_dist_m, self.max_angle_rad = c.max_dist_mm * 1e-3, float(np.deg2rad(c.max_angle_deg))
        self.reset_dist_m, self.reset_angle_rad = c.reset_dist_mm * 1e-3, float(np.deg2rad(c.reset_angle_deg))
        self.reset_after = c.reset_after
        self.use_covariance = c.use_covariance
        self.needle = NeedleModel() if needle is None else needle   # its arc's turn and mirror image
        self._centroid = self.needle.sample_arc(64).mean(0)
        self.queue: deque[QueuedEstimate] = deque()
        self.sequence: int | None = None
        self.resets = 0

    def __len__(self) -> int:
        return len(self.queue)

    def reset(self) -> None:
        self.queue.clear()
        self.sequence = None

    def add(self, T_ecm_needle, T_world_ecm=None, covariance=None, seq: int | None = None,
            sequence: int | None = None, common_sigma_m: float = 0.0,
            ambiguous: bool = False, common_sigma_rad: float = 0.0,
            end_identity: float | None = None, identity_widened: bool | None = None) -> FusedPose:
        """Queue an estimate made at ``T_world_ecm`` (identity when unknown: a still endoscope)
        and return the fused pose in the current ECM frame. ``common_sigma_m``,
        ``common_sigma_rad``: the position and orientation error (m, rad, per axis) inside
        ``covariance`` that every view shares; ``ambiguous``: the estimate was flagged so;
        ``end_identity``: its probability that the tip is where it puts it; ``identity_widened``:
        whether its covariance spans its turn (``PoseEstimate.identity_widened``; None: not
        stated, ``end_identity.was_widened``)."""
        T_world_ecm = np.eye(4) if T_world_ecm is None else np.asarray(T_world_ecm, dtype=float)
        est = QueuedEstimate(np.asarray(T_ecm_needle, dtype=float), T_world_ecm,
                             None if covariance is None else np.asarray(covariance, dtype=float), seq,
                             float(common_sigma_m or 0.0), float(common_sigma_rad or 0.0), bool(ambiguous),
                             None if end_identity is None else float(end_identity), identity_widened)
        reset = False
        if sequence is not None and self.sequence is not None and sequence != self.sequence:
            self.queue.clear()
            reset = True
        if sequence is not None:
            self.sequence = sequence
        self.queue.append(est)
        if not reset and self._moved():
            for _ in range(len(self.queue) - self.reset_after):
                self.queue.popleft()
            reset = True
        while len(self.queue) > self.k:
            self.queue.popleft()
        if reset:
            self.resets += 1
        return self._fuse(T_world_ecm, reset)

    def _moved(self) -> bool:
        n = self.reset_after
        if len(self.queue) <= n:
            return False
        items = list(self.queue)
        recent, older = items[-n:], items[:-n]
        centre, _, _ = fuse_poses([e.T_world_needle for e in older], None,
                                  self.max_dist_m, self.max_angle_rad)
        Tr = [e.T_world_needle for e in recent]
        dt, dr = pairwise_errors(Tr, [centre])
        far = bool(np.all((dt > self.reset_dist_m) | (dr > self.reset_angle_rad)))
        dt, dr = pairwise_errors(Tr)
        agree = bool(np.all((dt <= self.max_dist_m) & (dr <= self.max_angle_rad)))
        return far and agree

    def _reading(self, e: QueuedEstimate, T_now_i: np.ndarray, mirror: np.ndarray | None = None):
        """View ``e``'s reading in the current ECM frame (``T_now_i``: its ECM frame there), or,
        given ``mirror`` (its mirror image in its own ECM frame), that: (pose, covariance to
        weigh it by, covariance as stated)."""
        T, given = e.T_ecm_needle, e.covariance
        weigh = None if given is None else without_common(self._as_read(e), e.common_sigma_m, e.common_sigma_rad)
        if mirror is not None:
            def mirrored(C):
                return None if C is None else mirror_covariance(e.T_ecm_needle, C, self.needle, _centroid=self._centroid)
            T, given, weigh = mirror, mirrored(given), mirrored(weigh)
        R = T_now_i[:3, :3]
        return (T_now_i @ T, None if weigh is None else covariance_to_frame(weigh, R),
                None if given is None else covariance_to_frame(given, R))

    def _fuse(self, T_world_ecm_now, reset: bool) -> FusedPose:
        T_now_world = inv_T(T_world_ecm_now)
        frames = [T_now_world @ e.T_world_ecm for e in self.queue]
        # an ambiguous view's mirror image (refine.mirror_pose), in its own ECM frame
        own = [mirror_pose(e.T_ecm_needle, self.needle, _centroid=self._centroid) if e.ambiguous else None
               for e in self.queue]
        take = mirror_consensus([F @ e.T_ecm_needle for e, F in zip(self.queue, frames)],
                                [None if M is None else F @ M for M, F in zip(own, frames)],
                                self.max_dist_m, self.max_angle_rad)
        Ts, covs, given = (list(x) for x in zip(*(self._reading(e, F, M if t else None)
                                                  for e, F, M, t in zip(self.queue, frames, own, take))))
        T, inl, cov = fuse_poses(Ts, covs if self.use_covariance else None,
                                 self.max_dist_m, self.max_angle_rad)
        z = np.array([0.0 if e.end_identity is None else logit(e.end_identity) for e in self.queue])
        T, inl, cov, turned = self._vote(Ts, covs, z, T, inl, cov)
        common = max((e.common_sigma_m for e, ok in zip(self.queue, inl) if ok), default=0.0)
        common_rad = max((e.common_sigma_rad for e, ok in zip(self.queue, inl) if ok), default=0.0)
        if cov is not None and (common > 0 or common_rad > 0):
            cov = cov.copy()
            cov[:3, :3] += common_rad ** 2 * np.eye(3)
            cov[3:, 3:] += common ** 2 * np.eye(3)
        ambiguous = all(e.ambiguous for e, ok in zip(self.queue, inl) if ok)
        widened = False
        if ambiguous and cov is not None:
            cov = np.mean([C for C, ok in zip(given, inl) if ok], axis=0)
            widened = all(was_widened(e.end_identity, e.identity_widened) for e, ok in zip(self.queue, inl) if ok)
        said = np.array([e.end_identity is not None for e in self.queue]) & (inl | turned)
        p = None
        if said.any():
            p = sigmoid(np.mean(np.where(inl, z, -z)[said]))
            if p < TIP_SURE:                                  # the views leave the tip open
                if cov is not None and not ambiguous:         # (else their own covariances span it)
                    cov = identity_covariance(T, cov, self.needle, p)
                    widened = True
                ambiguous = True
        d = np.array([Ti[:3, 3] - T[:3, 3] for Ti, ok in zip(Ts, inl) if ok])
        rms = float(np.sqrt(np.mean(np.sum(d * d, axis=1))))
        return FusedPose(T, T_world_ecm_now @ T, int(inl.sum()), len(Ts), inl, cov, reset, rms, common,
                         ambiguous, common_rad, p, int(turned.sum()), widened)

    def _as_read(self, e: QueuedEstimate) -> np.ndarray:
        """``e``'s covariance without the widening over its turn that a view unsure of its tip
        states (``end_identity.state``): what its images pin down about its reading."""
        return reading_covariance(e.T_ecm_needle, e.covariance, self.needle, e.end_identity, e.identity_widened)

    def _vote(self, Ts, covs, z, T, inl, cov):
        """Which end is the tip, by evidence: the fusion of the views turned end for end from ``T``
        when their summed log-odds ``z`` outweigh the inliers'. Returns (T, inliers, covariance,
        the views turned from T)."""
        turned = self._turned(Ts, T, inl)
        if turned.any() and z[turned].sum() > z[inl].sum():
            sel = np.flatnonzero(turned)
            T, sub_inl, cov = fuse_poses([Ts[i] for i in sel], [covs[i] for i in sel] if self.use_covariance
                                         else None, self.max_dist_m, self.max_angle_rad)
            inl = np.zeros(len(Ts), bool)
            inl[sel[sub_inl]] = True
            turned = self._turned(Ts, T, inl)
        return T, inl, cov, turned

    def _turned(self, Ts, T, inl) -> np.ndarray:
        """Views turned end for end from ``T``: at its origin, more than ``TURNED_RAD`` off."""
        dt, dr = pairwise_errors(Ts, [T])
        return ~inl & (dt[:, 0] <= self.max_dist_m) & (dr[:, 0] > TURNED_RAD)
