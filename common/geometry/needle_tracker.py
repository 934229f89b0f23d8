"""The needle tracked over time: at rest, held in an instrument's jaws, or free and moving.

An error-state extended Kalman filter on SE(3). A pose's error is ``[w, v]`` (rad, m) with
``R = exp([w]x) R_hat`` and ``t = t_hat + v``, in the axes of the frame the pose is expressed in:
the order and convention of ``PoseEstimate.covariance``. The state, by mode:

- ``rest``: ``T_world_needle``, still but for a slow random walk (``rest_sigma_*``, per sqrt(s)):
  the case of the multi-view fusion;
- ``held``: ``T_jaw_needle`` of the holding instrument, its error in jaw axes, constant but for
  a slow slip (``slip_sigma_*``): the grasp-constrained state of Chiu, Richter and Yip (2022).
  The pose it gives is ``T_world_needle = T_world_jaw(t) @ T_jaw_needle``, the jaw frame as the
  instrument measures it; that measurement's own error (``jaw_sigma_*``, about the jaws' pivot)
  adds to what is stated in world;
- ``free``: ``T_world_needle`` and its velocity ``[omega, u]`` (rad/s, m/s, world axes; ``u``
  the origin's), constant but for white acceleration noise (``accel_*``): 12 error states.

A measurement is a ``T_world_needle`` with its 6x6 covariance (world axes). It is gated by its
Mahalanobis distance to the prediction (``gate_nis``, chi-square with 6 degrees of freedom);
``reset_after`` rejected in a row start the track again from the newest one; ``reset_after_held``
a settled track (at rest or held, that many frames old): a needle lying still or moving with
closed jaws does not jump, but a fit biased by jaws or tissue hiding part of the arc can be wrong
many frames in a row.

Grasp and release come from what the system measures, never from ground truth (``jaw_holds``,
``NeedleTracker._modes``): an instrument grasps the needle when its jaws are closed (``jaw_rad``
at most ``closed_rad``) with the tracked arc between them (within ``grasp_reach_m`` of the jaws'
axis, from the pivot to ``jaw_length_m`` along z). Every grasp is on trial: beside it the
alternative, the needle left where it was, is kept, and each frame's measurement adds to the
log likelihood ratio of the two (a sequential test; a frame counts only where the two predictions
lie at least 1 sigma apart: nothing while the jaws stand still). At ``-grasp_llr`` the needle
moves with the jaws and the grasp is sure; at ``+grasp_llr`` it stayed behind: the grasp is
undone, the needle at rest, and those jaws grasp nothing until they open. The holder lets go when
its jaws open (``jaw_rad`` at least ``open_rad``): to another instrument whose jaws hold it (a
handover), else the needle stays where the jaws let it go, at rest (in the tissue, on the pad).
A free needle is weighed the same way against the alternative that it stays where it was: at
``+grasp_llr`` it is at rest; at ``-grasp_llr`` it moves, and the alternative is armed again.

Which end is the tip belongs to the track: a measurement is read as it is or turned end for end
(``end_identity.end_for_end_delta``), whichever lies within the gate, and its stated end
identity is evidence for or against the track's (``end_identity.track_identity``), never a new
truth on its own.

One camera: a measurement fitted to one camera's view (``Measurement.one_camera``) updates a
track as any other but starts none unless ``start_one_camera`` (a monocular endoscope). One view
cannot tell a planar arc from its mirror image (``refine.mirror_pose``: the same image curve):
a track started from such a view has its mirror open (``Tracked.mirror_open``) until a stereo
measurement updates it; its poses are then stated with the mirror (the tracker step widens the
covariance to span it and flags them). A one-camera measurement weighs no grasp trial: the depth it
leaves open is where a needle carried and one left behind differ (on the arm set a window of one
camera's views undid a true grasp, and the needle left "at rest" was 21 mm off, sure of itself).

A track whose measurements are rejected ``reset_after`` times in a row is disputed
(``Tracked.disputed``) until one is taken again: its covariance grows by the newest rejected
measurement's offset (``C + d d^T``) and it is said flagged. A settled track restarts only after
``reset_after_held`` rejections and only from a measurement that may start one: meanwhile it must
not state itself sure (on the arm set a track left 21 mm off sat there, NEES in the thousands).

A track starts from a measurement fitted to ``start_arc_seen`` of the arc, or from a run of
``start_run`` partial views (each fitted to ``start_run_arc_seen``) that agree with each other:
a short part of the arc can fit a pose tens of degrees off, but rarely the same wrong pose many
frames in a row while the jaws move it (``NeedleTracker._from_partial``).
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from common.constraints import NonNegativeNumber, PositiveNumber, Probability, check_fields, number_at_least
from common.geometry.arm_correction import ArmCorrection, configuration_change, grasp_constraint, lever
from common.geometry.end_identity import end_for_end_delta, sigmoid, track_identity
from common.geometry.error_state import (  # noqa: F401  (retract: re-exported)
    block_rotation,
    constant_velocity,
    jaw_jacobian,
    nis,
    random_walk,
    retract,
)
from common.geometry.fusion import covariance_to_frame, without_common
from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T, pose_delta, symmetrise, transform_points

CHI2_6_999 = 22.46
"""Chi-square with 6 degrees of freedom exceeds this in 0.1% of the draws."""


@dataclass(frozen=True)
class TrackerConfig:
    """The tracker's models and rules (see the module docstring); lengths m, angles rad, time s."""
    gate_nis: float = CHI2_6_999            # a measurement farther than this (Mahalanobis^2) is rejected
    reset_after: int = 3                    # rejected measurements in a row that start a free track again
    reset_after_held: int = 30              # ... a settled one (1 s at 30 Hz: see the docstring)
    start_arc_seen: Probability = 0.6       # a track starts from a pose fitted to this much of its arc
    start_run: int = 10                     # ... or from this many partial views in a row that agree
    start_run_arc_seen: Probability = 0.45  # ... each fitted to at least this much (start_run 0: never)
    corr_frames: number_at_least(1.0) = 5.0  # consecutive frames whose fits' errors move together
    rest_sigma_m: NonNegativeNumber = 0.05e-3           # random walk of a needle at rest, per sqrt(s)
    rest_sigma_rad: NonNegativeNumber = math.radians(0.2)
    slip_sigma_m: NonNegativeNumber = 0.1e-3            # slip in the jaws, per sqrt(s)
    slip_sigma_rad: NonNegativeNumber = math.radians(0.5)
    accel_m_s2: NonNegativeNumber = 0.1                 # white acceleration of a free needle
    accel_rad_s2: NonNegativeNumber = 3.0
    free_speed_m_s: NonNegativeNumber = 0.02            # 1 sigma of a just-freed needle's velocity
    free_turn_rad_s: NonNegativeNumber = math.radians(90.0)
    jaw_sigma_m: NonNegativeNumber = 0.05e-3            # the jaws' measured pose: its error, about the pivot
    jaw_sigma_rad: NonNegativeNumber = math.radians(0.1)
    closed_rad: float = 0.3                 # jaws at or below this are closed
    open_rad: float = 0.45                  # a holder's jaws at or above this let go
    grasp_reach_m: float = 0.002            # the arc this near the jaws' axis lies between them
    jaw_length_m: float = 0.009             # the jaws' axis: from the pivot this far along z
    grasp_llr: float = 4.6                  # log likelihood ratio that settles a trial (100:1): grasp, rest
    trial_frame_llr: PositiveNumber = 1.5   # one frame's evidence in a trial at most this: no one view settles it
    regrasp_travel_m: PositiveNumber = 0.002   # refused jaws try again once they moved this far (pivot or tip)
    max_coast_s: float = 0.5                # a free needle unseen this long is lost
    start_one_camera: bool = False          # a pose fitted to one camera's view may start a track (monocular)
    # each arm's kinematic error, estimated online (common.geometry.arm_correction; off: the reports as exact)
    arm_correction: bool = False            # estimate each arm's error (docs/tracking.md); off: the reports as exact
    arm_prior_m: NonNegativeNumber = 3.0e-3             # a correction's shift before any news: 1 sigma per axis
    arm_prior_rad: NonNegativeNumber = math.radians(2.5)   # ... its turn
    arm_walk_m: NonNegativeNumber = 0.05e-3             # a correction's random walk in time, per sqrt(s): shift
    arm_walk_rad: NonNegativeNumber = math.radians(0.05)   # ... turn
    arm_drift_m: NonNegativeNumber = 1.0e-3             # ... and per sqrt of the arm's configuration change: shift
    arm_drift_rad: NonNegativeNumber = math.radians(1.0)   # ... turn
    arm_drift_length_m: number_at_least(1e-6) = 0.015   # a configuration change of 1: this much travel of the jaws
    arm_drift_turn_rad: number_at_least(1e-6) = math.radians(45.0)   # ... or this much turn
    grasp_sigma_m: number_at_least(1e-6) = 0.3e-3       # a sure grasp's geometry: the wire off the jaw faces' middle
    grasp_sigma_rad: number_at_least(1e-6) = math.radians(5.0)   # ... its tangent off the jaw faces

    def __post_init__(self):
        if not (self.gate_nis > 0 and min(self.reset_after, self.reset_after_held) >= 1 and self.grasp_llr > 0
                and 0 <= self.closed_rad < self.open_rad and self.max_coast_s > 0
                and min(self.grasp_reach_m, self.jaw_length_m) > 0 and self.start_run >= 0):
            raise ValueError("tracker: needs gate_nis, grasp_llr > 0, reset_after and reset_after_held >= 1, "
                             "0 <= closed_rad < open_rad, max_coast_s > 0 and positive grasp lengths")
        check_fields(self, "tracker: {name} {why}")


@dataclass(frozen=True)
class Jaw:
    """An instrument's measured state: ``T_world_jaw`` (4x4, m; docs/dataset.md) and opening (rad)."""
    T_world_jaw: np.ndarray
    jaw_rad: float


@dataclass(frozen=True)
class Measurement:
    """A measured ``T_world_needle`` with its covariance (6x6, [w, v], world axes) and the
    probability that its tip is where it says (None: not stated). ``alternatives``: other poses
    (world) the images fit nearly as well (an ambiguous fit's mirror image, whose spread the
    covariance already spans): the track takes the reading it explains best. ``common_sigma_m``,
    ``common_sigma_rad``: the part of its error, 1 sigma per axis, that every measurement of
    this needle shares (``PoseEstimate.model_sigma_*``, inside ``covariance``): the filter takes
    it out before weighing and states it again with the track, as a fusion of views does
    (``common.geometry.fusion.without_common``), since averaging frames cannot shrink it."""
    T_world_needle: np.ndarray
    covariance: np.ndarray
    end_identity: Optional[float] = None
    common_sigma_m: float = 0.0
    common_sigma_rad: float = 0.0
    alternatives: tuple = ()
    arc_seen: Optional[float] = None        # the share of the arc it was fitted to (None: not said)
    one_camera: bool = False                # fitted to one camera's view (its depth as wide as that leaves it)

    def own(self, corr_frames: float = 1.0) -> "Measurement":
        """The measurement with its covariance less the shared part, times ``corr_frames``."""
        C = without_common(self.covariance, self.common_sigma_m, self.common_sigma_rad) * corr_frames
        return Measurement(self.T_world_needle, C, self.end_identity, alternatives=self.alternatives,
                           arc_seen=self.arc_seen, one_camera=self.one_camera)

    def starts(self, cfg: "TrackerConfig") -> bool:
        """Whether a track may start (or restart) from it: fitted to ``start_arc_seen`` of its arc,
        and to both cameras' views unless ``start_one_camera``."""
        if self.one_camera and not cfg.start_one_camera:
            return False
        return self.arc_seen is None or self.arc_seen >= cfg.start_arc_seen

    def may_run(self, cfg: "TrackerConfig") -> bool:
        """Whether it may join a run of partial views that starts a track (``_from_partial``)."""
        if self.one_camera and not cfg.start_one_camera:
            return False
        return self.arc_seen is not None and self.arc_seen >= cfg.start_run_arc_seen


@dataclass(frozen=True)
class Tracked:
    """The track after a frame: ``T_world_needle`` and its covariance (6x6, world axes); the
    ``mode``, the ``holder`` and, while held, ``T_jaw_needle`` with its covariance (jaw axes);
    ``end_identity`` the track's probability that its tip is right (None: never stated);
    ``used``: the frame's measurement updated the track (None: there was none), ``turned``: it
    was read end for end, ``nis`` its Mahalanobis^2; ``event``: what changed (``start``,
    ``grasp:NAME``, ``handover:NAME``, ``release``, ``ungrasp``, ``rest``, ``restart``,
    ``flip``), or None."""
    T_world_needle: np.ndarray
    covariance: np.ndarray
    mode: str
    holder: Optional[str] = None
    T_jaw_needle: Optional[np.ndarray] = None
    jaw_covariance: Optional[np.ndarray] = None
    end_identity: Optional[float] = None
    used: Optional[bool] = None
    turned: bool = False
    nis: float = float("nan")
    event: Optional[str] = None
    corrections: Optional[dict] = None      # arm_correction: {name: (K 4x4, 6x6)} (NeedleTracker.corrections)
    mirror_open: bool = False               # started from one camera's view, no stereo view since (module docstring)
    disputed: bool = False                  # reset_after measurements in a row rejected: covariance spans the newest


# ---------------------------------------------------------------- small pieces

def turned_end_for_end(T: np.ndarray, needle: NeedleModel) -> np.ndarray:
    """The pose read end for end: the half turn of ``end_identity.end_for_end_delta``."""
    return retract(T, end_for_end_delta(T, needle))


def jaw_holds(jaw: Jaw, T_world_needle: np.ndarray, needle: NeedleModel, cfg: TrackerConfig,
              n_arc: int = 33, reach_m: Optional[float] = None) -> bool:
    """Whether ``jaw``'s jaws are closed on the arc at ``T_world_needle``: closed, and some point
    of the arc within ``reach_m`` (default ``grasp_reach_m``) of the jaws' axis (pivot to
    ``jaw_length_m`` along z)."""
    if not jaw.jaw_rad <= cfg.closed_rad:
        return False
    p = transform_points(inv_T(jaw.T_world_jaw) @ T_world_needle, needle.sample_arc(n_arc))
    z = np.clip(p[:, 2], 0.0, cfg.jaw_length_m)
    d = np.sqrt(p[:, 0] ** 2 + p[:, 1] ** 2 + (p[:, 2] - z) ** 2)
    return bool(d.min() <= (cfg.grasp_reach_m if reach_m is None else reach_m))


def jaw_travel(T_from: np.ndarray, T_to: np.ndarray, jaw_length_m: float) -> float:
    """How far jaws moved between two poses: the larger travel of their pivot and their tip
    (``jaw_length_m`` along z), m."""
    tip = np.array([0.0, 0.0, jaw_length_m, 1.0])
    return float(max(np.linalg.norm(T_to[:3, 3] - T_from[:3, 3]), np.linalg.norm((T_to @ tip - T_from @ tip)[:3])))


# ---------------------------------------------------------------- the filter

class NeedleTracker:
    """The filter (see the module docstring). ``step`` once per frame, in time order."""

    def __init__(self, needle: NeedleModel, config: TrackerConfig = TrackerConfig()):
        self.needle, self.cfg = needle, config
        self.reset()

    def reset(self, keep_arms: bool = False) -> None:
        """Forget the track (``keep_arms``: but not the arms' corrections, which are the arms')."""
        arms = (self.arms, self.P[self.n:, self.n:]) if keep_arms and getattr(self, "arms", None) else None
        self.mode: Optional[str] = None
        self.holder: Optional[str] = None
        self.T = None                  # T_world_needle (rest, free) or T_jaw_needle (held)
        self.P = None                  # 6x6 (rest, held) or 12x12 (free), then 6 per arm (arm_correction)
        self.n = 0                     # the needle's states in P (0: no track)
        self.arms: dict = {}           # name -> ArmCorrection, in P's order after the needle's states
        self.arms_stamp_ns: Optional[int] = None
        if arms is not None:
            self.arms, self.P = arms
        self.vel = np.zeros(6)         # free: [omega, u]
        self.stamp_ns: Optional[int] = None
        self.last_seen_ns: Optional[int] = None
        self.identity: Optional[tuple] = None      # end_identity.track_identity's state
        self.rejected, self.age = 0, 0             # rejected in a row; frames since the track started
        self.trial: Optional[dict] = None          # the alternative: the needle stayed (_arm_trial)
        self.refused: dict = {}                    # jaws whose grasp was undone: their reported pose then
        self._last_jaws: dict = {}
        self.common = np.zeros(6)                  # the shared error's variances, the newest measurement's
        self.mirror_open = False                   # the track rests on one camera's views alone
        self.disputed: Optional[np.ndarray] = None  # the newest rejected measurement's offset (world [w, v])
        self.candidate: Optional["NeedleTracker"] = None   # a track of partial views only (_from_partial)
        self.run = 0                               # the partial views in a row it took

    @property
    def active(self) -> bool:
        return self.mode is not None

    def snapshot(self) -> dict:
        """The whole filter state (a copy): ``restore`` it to step again from there, e.g. with a
        measurement that came after its frame was stepped."""
        return copy.deepcopy({k: v for k, v in vars(self).items() if k not in ("needle", "cfg")})

    def restore(self, snapshot: dict) -> None:
        """Back to the state ``snapshot`` took (the snapshot stays usable)."""
        vars(self).update(copy.deepcopy(snapshot))

    # -- the state seen in world
    def world(self, jaws: dict) -> tuple[np.ndarray, np.ndarray]:
        """(T_world_needle, 6x6 covariance in world axes) of the current state."""
        if self.mode != "held":
            return self.T, self.P[:6, :6]
        Tj = self.jaw_pose(jaws, self.holder)
        Tw = Tj @ self.T
        if self.arms:
            W = self._world_jacobian(jaws)
            return Tw, symmetrise(W @ self.P @ W.T + self._jaw_noise(Tj, Tw))
        return Tw, symmetrise(covariance_to_frame(self.P, Tj[:3, :3]) + self._jaw_noise(Tj, Tw))

    # -- the arms' corrections (arm_correction; common.geometry.arm_correction)
    def jaw_pose(self, jaws: dict, name: str) -> np.ndarray:
        """Instrument ``name``'s jaw pose: as reported, corrected where its arm's error is estimated."""
        arm = self.arms.get(name)
        T = jaws[name].T_world_jaw
        return T if arm is None else arm.corrected(T)

    def corrected_jaws(self, jaws: dict) -> dict:
        """``jaws`` with each pose corrected (the same dict when no arm's error is estimated)."""
        if not self.arms:
            return jaws
        return {n: Jaw(self.jaw_pose(jaws, n), j.jaw_rad) for n, j in jaws.items()}

    def _arm_cols(self, name: str) -> slice:
        i = self.n + 6 * list(self.arms).index(name)
        return slice(i, i + 6)

    def _world_jacobian(self, jaws: dict) -> np.ndarray:
        """W (6 x all states): the world pose's error of the needle as the state's error maps to it."""
        W = np.zeros((6, len(self.P)))
        if self.mode != "held":
            W[:, :6] = np.eye(6)
            return W
        Tj = self.jaw_pose(jaws, self.holder)
        W[:, :6] = block_rotation(Tj[:3, :3])
        arm = self.arms.get(self.holder)
        if arm is not None:
            W[:, self._arm_cols(self.holder)] = lever((Tj @ self.T)[:3, 3], arm.centre)
        return W

    def _world_cross(self, jaws: dict) -> Optional[np.ndarray]:
        """The world pose's error's covariance with the arms' (6 x 6 per arm); None without arms."""
        if not self.arms:
            return None
        return self._world_jacobian(jaws) @ self.P[:, self.n:]

    def _arms_step(self, stamp_ns: int, jaws: dict) -> None:
        """Each arm heard from gets a correction (none yet, its prior's covariance); each drifts:
        a random walk in time and in the arm's configuration change since the last frame."""
        c = self.cfg
        for name in sorted(jaws):
            if name not in self.arms:
                self.arms[name] = ArmCorrection.at(jaws[name].T_world_jaw)
                prior = np.diag([c.arm_prior_rad ** 2] * 3 + [c.arm_prior_m ** 2] * 3)
                N = 0 if self.P is None else len(self.P)
                P = np.zeros((N + 6, N + 6))
                if N:
                    P[:N, :N] = self.P
                P[N:, N:] = prior
                self.P = P
        dt = 0.0 if self.arms_stamp_ns is None else max(0.0, (stamp_ns - self.arms_stamp_ns) * 1e-9)
        self.arms_stamp_ns = stamp_ns
        for name, arm in self.arms.items():
            s = 0.0
            if name in jaws:
                s = configuration_change(arm.last, jaws[name].T_world_jaw, c.arm_drift_length_m, c.arm_drift_turn_rad)
                arm.last = np.asarray(jaws[name].T_world_jaw, float).copy()
            cols = self._arm_cols(name)
            self.P[cols, cols] += random_walk(c.arm_walk_rad, c.arm_walk_m, dt) \
                + random_walk(c.arm_drift_rad, c.arm_drift_m, s)

    def corrections(self, jaws: dict) -> dict:
        """``{name: (K, covariance)}`` per arm: the correction (4x4, world: ``K @ T_world_jaw``
        corrects the report) and the covariance of the corrected jaw pose (6x6, [w, v], world
        axes, about the jaws' pivot where the arm reports them now, else where it last did)."""
        out = {}
        for name, arm in self.arms.items():
            T = arm.corrected(jaws[name].T_world_jaw if name in jaws else arm.last)
            J = lever(T[:3, 3], arm.centre)
            cols = self._arm_cols(name)
            out[name] = (arm.K, symmetrise(J @ self.P[cols, cols] @ J.T))
        return out

    def holds(self, jaws: dict, name: str, T_world_needle: np.ndarray) -> bool:
        """``jaw_holds`` with ``name``'s jaws as corrected, the reach widened by 2 sigma of where
        the correction puts their pivot (an arm not yet corrected is millimetres off)."""
        arm = self.arms.get(name)
        if arm is None:
            return jaw_holds(jaws[name], T_world_needle, self.needle, self.cfg)
        T = arm.corrected(jaws[name].T_world_jaw)
        J = lever(T[:3, 3], arm.centre)[3:]
        cols = self._arm_cols(name)
        sigma = math.sqrt(max(np.linalg.eigvalsh(J @ self.P[cols, cols] @ J.T).max(), 0.0))
        return jaw_holds(Jaw(T, jaws[name].jaw_rad), T_world_needle, self.needle, self.cfg,
                         reach_m=self.cfg.grasp_reach_m + 2.0 * sigma)

    def _grasp_geometry(self, jaws: dict) -> None:
        """A grasp found sure: the needle's pose in the (corrected) jaws weighed once against the
        grasp's geometry (``arm_correction.grasp_constraint``): what tells the holder's correction
        from the grasp where the product of the two is all the images see."""
        c = self.cfg
        r, Hg = grasp_constraint(self.T, self.needle, c.jaw_length_m)
        H = np.zeros((2, len(self.P)))
        H[:, :6] = Hg
        R = np.diag([c.grasp_sigma_m ** 2, c.grasp_sigma_rad ** 2])
        self._correct(r, symmetrise(H @ self.P @ H.T + R), H)

    def _jaw_noise(self, T_world_jaw: np.ndarray, T_world_needle: np.ndarray) -> np.ndarray:
        """The jaws' measured pose's error as it moves a held needle (6x6, world axes)."""
        J = jaw_jacobian(T_world_jaw, T_world_needle)
        return J @ np.diag([self.cfg.jaw_sigma_rad ** 2] * 3 + [self.cfg.jaw_sigma_m ** 2] * 3) @ J.T

    def _set_world(self, mode: str, T_world: np.ndarray, P_world: np.ndarray, jaws: dict,
                   holder: Optional[str] = None, cross: Optional[np.ndarray] = None) -> None:
        """Put the state in ``mode`` from a world pose and its covariance (a free needle starts
        with no known velocity: 0, 1 sigma ``free_speed_m_s``, ``free_turn_rad_s``); ``cross``:
        the world pose's error's covariance with the arms' corrections (None: independent)."""
        if self.arms:
            return self._set_world_with_arms(mode, T_world, P_world, jaws, holder, cross)
        self.n = 12 if mode == "free" else 6
        self.mode, self.holder = mode, holder
        if mode == "held":
            Tj = jaws[holder].T_world_jaw
            self.T, self.P = inv_T(Tj) @ T_world, symmetrise(covariance_to_frame(P_world, Tj[:3, :3].T))
        elif mode == "free":
            c = self.cfg
            self.T, self.vel = T_world, np.zeros(6)
            self.P = np.zeros((12, 12))
            self.P[:6, :6] = P_world
            self.P[6:, 6:] = np.diag([c.free_turn_rad_s ** 2] * 3 + [c.free_speed_m_s ** 2] * 3)
        else:
            self.T, self.P = T_world, P_world

    def _set_world_with_arms(self, mode, T_world, P_world, jaws, holder, cross) -> None:
        """``_set_world`` beside the arms' corrections: the needle's new states and their
        covariance with the corrections, the corrections' own kept."""
        c = self.cfg
        A = self.P[self.n:, self.n:]
        X = np.zeros((6, len(A))) if cross is None else cross
        P_world = np.asarray(P_world, float)
        self.mode, self.holder = mode, holder
        if mode == "held":
            Tj = self.jaw_pose(jaws, holder)
            self.T = inv_T(Tj) @ T_world
            B = block_rotation(Tj[:3, :3].T)          # the world error into jaw axes, less the correction's part
            cols = slice(6 * list(self.arms).index(holder), 6 * list(self.arms).index(holder) + 6)
            Hc = lever(T_world[:3, 3], self.arms[holder].centre)
            Xb = X[:, cols]
            Pn = B @ (P_world - Xb @ Hc.T - Hc @ Xb.T + Hc @ A[cols, cols] @ Hc.T) @ B.T
            Xn = B @ (X - Hc @ A[cols, :])
        elif mode == "free":
            self.T, self.vel = T_world, np.zeros(6)
            Pn = np.zeros((12, 12))
            Pn[:6, :6] = P_world
            Pn[6:, 6:] = np.diag([c.free_turn_rad_s ** 2] * 3 + [c.free_speed_m_s ** 2] * 3)
            Xn = np.vstack([X, np.zeros((6, len(A)))])
        else:
            self.T, Pn, Xn = T_world, P_world, X
        self.n = len(Pn)
        self.P = symmetrise(np.block([[Pn, Xn], [Xn.T, A]]))

    # -- predict
    def predict(self, stamp_ns: int) -> None:
        """The state carried to ``stamp_ns`` by its mode's motion model."""
        dt = max(0.0, (stamp_ns - self.stamp_ns) * 1e-9)
        self.stamp_ns = stamp_ns
        c = self.cfg
        if self.arms:
            return self._predict_with_arms(dt)
        if self.mode == "free":
            F, Q = constant_velocity(dt, c.accel_rad_s2, c.accel_m_s2)
            self.T = retract(self.T, dt * self.vel)
            self.P = symmetrise(F @ self.P @ F.T + Q)
        elif self.mode == "held":
            self.P = self.P + random_walk(c.slip_sigma_rad, c.slip_sigma_m, dt)
        else:
            self.P = self.P + random_walk(c.rest_sigma_rad, c.rest_sigma_m, dt)

    def _predict_with_arms(self, dt: float) -> None:
        c, n = self.cfg, self.n
        if self.mode == "free":
            F, Q = constant_velocity(dt, c.accel_rad_s2, c.accel_m_s2)
            self.T = retract(self.T, dt * self.vel)
            Fa = np.eye(len(self.P))
            Fa[:n, :n] = F
            self.P = Fa @ self.P @ Fa.T
            self.P[:n, :n] += Q
            self.P = symmetrise(self.P)
        elif self.mode == "held":
            self.P[:n, :n] += random_walk(c.slip_sigma_rad, c.slip_sigma_m, dt)
        else:
            self.P[:n, :n] += random_walk(c.rest_sigma_rad, c.rest_sigma_m, dt)

    # -- update
    def _innovation(self, T_meas: np.ndarray, R_meas: np.ndarray, jaws: dict):
        """(residual, S, H) of a measured world pose against the state."""
        Tw, _ = self.world(jaws)
        r = pose_delta(T_meas, Tw)
        if self.arms:
            if self.mode == "held":
                R_meas = R_meas + self._jaw_noise(self.jaw_pose(jaws, self.holder), Tw)
            H = self._world_jacobian(jaws)
            return r, symmetrise(H @ self.P @ H.T + R_meas), H
        n = len(self.P)
        H = np.zeros((6, n))
        if self.mode == "held":
            Tj = jaws[self.holder].T_world_jaw
            H[:, :6] = block_rotation(Tj[:3, :3])
            R_meas = R_meas + self._jaw_noise(Tj, Tw)
        else:
            H[:, :6] = np.eye(6)
        return r, symmetrise(H @ self.P @ H.T + R_meas), H

    def _correct(self, r: np.ndarray, S: np.ndarray, H: np.ndarray) -> None:
        K = np.linalg.solve(S, H @ self.P).T
        dx = K @ r
        self.T = retract(self.T, dx[:6])
        if self.mode == "free":
            self.vel = self.vel + dx[6:self.n]
        for i, arm in enumerate(self.arms.values()):
            arm.inner = retract(arm.inner, dx[self.n + 6 * i:self.n + 6 * i + 6])
        IKH = np.eye(len(self.P)) - K @ H
        S_r = S - H @ self.P @ H.T                 # the measurement's noise (Joseph form)
        self.P = symmetrise(IKH @ self.P @ IKH.T + K @ S_r @ K.T)

    def _read(self, m: Measurement, jaws: dict):
        """How to read ``m`` against the track: (turn it, the track turned, nis, residual, S,
        H), or None when no reading lies within the gate. The readings: the pose and its
        ``alternatives``, each as it is and turned end for end."""
        readings = [(T, turned) for P in (m.T_world_needle, *m.alternatives)
                    for T, turned in ((P, False), (turned_end_for_end(P, self.needle), True))]

        def best(of_turned=None):
            cand = [(self._innovation(T, m.covariance, jaws), turned) for T, turned in readings
                    if of_turned is None or turned == of_turned]
            (r, S, H), turned = min(cand, key=lambda c: nis(c[0][0], c[0][1]))
            return nis(r, S), r, S, H, turned
        d, r, S, H, turned = best()
        if d > self.cfg.gate_nis:
            return None
        same = not turned                          # the track explains the reading as read
        if m.end_identity is None:                 # no evidence: the reading the track explains
            return turned, False, d, r, S, H
        turn, self.identity = track_identity(m.end_identity, self.identity, same)
        if same != turn:                           # the evidence agrees with the track
            return turned, False, d, r, S, H
        # the evidence outweighs the track's: the track turns, the reading stands
        self.T = turned_end_for_end(self.T, self.needle)      # T @ half turn, in any frame
        d, r, S, H, turned = best(of_turned=turn)
        return turned, True, d, r, S, H

    # -- modes
    def _start(self, m: Measurement, jaws: dict) -> None:
        """A new track from ``m``: held when some jaws hold it, else at rest."""
        T, P = m.T_world_needle, np.asarray(m.covariance, float)
        self.identity, self.trial = None, None
        self.mirror_open = bool(m.one_camera)
        if m.end_identity is not None:
            turn, self.identity = track_identity(m.end_identity, None, None)
            if turn:
                T = turned_end_for_end(T, self.needle)
        holder = next((n for n in sorted(jaws) if n not in self.refused and self.holds(jaws, n, T)), None)
        self._set_world("held" if holder else "rest", T, P, jaws, holder)
        if holder is not None:          # on trial, as every grasp
            self._arm_trial(T, P)

    def _modes(self, jaws: dict) -> Optional[str]:
        """Grasp, handover, release and rest decided from the jaws and the track; the event."""
        c = self.cfg
        Tw, Pw = self.world(jaws)
        X = self._world_cross(jaws)
        if self.mode == "held":
            if jaws[self.holder].jaw_rad < c.open_rad:
                return None
            other = next((n for n in sorted(jaws) if n != self.holder and self.holds(jaws, n, Tw)), None)
            if other is not None:
                self._set_world("held", Tw, Pw, jaws, other, X)
                self._arm_trial(Tw, Pw)          # the new grasp is on trial too
                return f"handover:{other}"
            self.trial = None              # let go where something holds it: tissue, the pad
            self._set_world("rest", Tw, Pw, jaws, cross=X)
            return "release"
        holder = next((n for n in sorted(jaws) if n not in self.refused and self.holds(jaws, n, Tw)), None)
        if holder is not None:
            self._arm_trial(Tw, Pw)
            self._set_world("held", Tw, Pw, jaws, holder, X)
            return f"grasp:{holder}"
        if self.mode == "free" and self.trial is None:
            self._arm_trial(self.T, self.P[:6, :6])
        return None

    def _arm_trial(self, T_world: np.ndarray, P_world: np.ndarray) -> None:
        """Keep beside the state the alternative that the needle stays at ``T_world``: a filter
        of a needle at rest from there, and the evidence against it (log likelihood ratio)."""
        self.trial = {"T": T_world.copy(), "P": np.array(P_world, float), "stamp": self.stamp_ns, "llr": 0.0}

    def _weigh_trial(self, m: Measurement, jaws: dict, stamp_ns: int) -> None:
        """The frame's evidence that the needle stayed (the alternative) rather than moved as the
        state says: half the difference of the two predictions' Mahalanobis^2 under the state's
        predicted covariance (the same for both: what differs is where they put the needle),
        each bounded by the gate, counted only when the predictions lie at least 1 sigma apart
        (jaws that stand still tell nothing). Then the alternative takes the measurement, as a
        needle at rest."""
        t, c = self.trial, self.cfg
        dt = max(0.0, (stamp_ns - t["stamp"]) * 1e-9) if t["stamp"] is not None else 0.0
        t["P"] = t["P"] + random_walk(c.rest_sigma_rad, c.rest_sigma_m, dt)
        t["stamp"] = stamp_ns
        readings = (m.T_world_needle, turned_end_for_end(m.T_world_needle, self.needle))
        Tw, Pw = self.world(jaws)
        S = Pw + m.covariance

        def dist(T_pred):
            return min(min(nis(pose_delta(T, T_pred), S) for T in readings), c.gate_nis)
        if nis(pose_delta(Tw, t["T"]), S) >= 1.0:      # only where the two tell different stories
            cap = c.trial_frame_llr
            t["llr"] += float(np.clip(0.5 * (dist(Tw) - dist(t["T"])), -cap, cap))
        S_alt = t["P"] + m.covariance
        r = min((pose_delta(T, t["T"]) for T in readings), key=lambda r: nis(r, S_alt))
        if nis(r, S_alt) <= c.gate_nis:
            K = np.linalg.solve(S_alt, t["P"]).T
            t["T"] = retract(t["T"], K @ r)
            t["P"] = symmetrise((np.eye(6) - K) @ t["P"])

    def _settle_trial(self, jaws: dict) -> Optional[str]:
        """A grasp: sure once the evidence says the needle moves with the jaws; undone (the
        needle left where it was, at rest) once it says it stayed behind. A free needle: at rest
        once the evidence says it stays where the alternative was armed; armed again where it
        is once the evidence says it moves."""
        t, c = self.trial, self.cfg
        if self.mode == "free":
            if t["llr"] >= c.grasp_llr:
                self.trial = None
                self._set_world("rest", self.T, self.P[:6, :6], jaws, cross=self._world_cross(jaws))
                return "rest"
            if t["llr"] <= -c.grasp_llr:
                self.trial = None
            return None
        if t["llr"] <= -c.grasp_llr:
            self.trial = None
            if self.holder in self.arms:         # the grasp is sure: its geometry tells the arm's error
                self._grasp_geometry(jaws)
        elif t["llr"] >= c.grasp_llr:
            self.trial = None
            self.refused[self.holder] = jaws[self.holder].T_world_jaw.copy()
            self._set_world("rest", t["T"], t["P"], jaws)
            return "ungrasp"
        return None

    # -- one frame
    def step(self, stamp_ns: int, jaws: dict, measurement: Optional[Measurement]) -> Optional[Tracked]:
        """The track at ``stamp_ns`` given the instruments' states (``{name: Jaw}``) and the
        frame's measurement (None: no pose this frame). None while there is no track."""
        event = None
        if self.cfg.arm_correction:
            self._arms_step(stamp_ns, jaws)
        self.refused = {n: T for n, T in self.refused.items() if n in jaws and jaws[n].jaw_rad < self.cfg.open_rad
                        and jaw_travel(T, jaws[n].T_world_jaw, self.cfg.jaw_length_m) < self.cfg.regrasp_travel_m}
        if self.active and self.mode == "held" and self.holder not in jaws:
            Tw, Pw = self.world(self._last_jaws)      # the holder's state did not come: let it go
            self._set_world("free", Tw, Pw, jaws, cross=self._world_cross(self._last_jaws))
            event = "release"
        if self.active:
            self.predict(stamp_ns)
            self.age += 1
            if self.mode == "free" and measurement is None and \
                    (stamp_ns - self.last_seen_ns) * 1e-9 > self.cfg.max_coast_s:
                self.reset(keep_arms=True)
                return None
        if not self.active and (measurement is None or not measurement.starts(self.cfg)):
            return self._from_partial(stamp_ns, jaws, measurement)
        self.candidate, self.run = None, 0
        if measurement is not None:
            self.common = np.array([measurement.common_sigma_rad ** 2] * 3 + [measurement.common_sigma_m ** 2] * 3)
            measurement = measurement.own(self.cfg.corr_frames)
        used, turned, d = None, False, float("nan")
        if not self.active:
            self._start(measurement, jaws)
            self.stamp_ns = self.last_seen_ns = stamp_ns
            used, event = True, "start"
        elif measurement is not None:
            if self.trial is not None and not measurement.one_camera:
                self._weigh_trial(measurement, jaws, stamp_ns)   # one view cannot tell near from far
            read = self._read(measurement, jaws)
            used = read is not None
            if used:
                turned, flipped, d, r, S, H = read
                self._correct(r, S, H)
                self.rejected, self.last_seen_ns, self.disputed = 0, stamp_ns, None
                if not measurement.one_camera:
                    self.mirror_open = False         # a stereo view tells the arc from its mirror image
                event = "flip" if flipped else event
            else:
                self.rejected += 1
                self.disputed = self._offset(measurement, jaws)
                settled = self.mode != "free" and self.age >= self.cfg.reset_after_held
                if self.rejected >= (self.cfg.reset_after_held if settled else self.cfg.reset_after) \
                        and measurement.starts(self.cfg):
                    refused = self.refused
                    self.reset(keep_arms=True)
                    self.refused = refused
                    self._start(measurement, jaws)
                    self.stamp_ns = self.last_seen_ns = stamp_ns
                    if self.mode == "rest":       # it moved: free until it settles
                        self._set_world("free", self.T, self.P[:6, :6], jaws, cross=self._world_cross(jaws))
                    used, event = True, "restart"
            if self.trial is not None and event != "restart":
                event = self._settle_trial(jaws) or event
        event = self._modes(jaws) or event
        self._last_jaws = dict(jaws)
        return self._output(jaws, used, turned, d, event)

    def _from_partial(self, stamp_ns: int, jaws: dict, m: Optional[Measurement]) -> Optional[Tracked]:
        """No track, and no measurement that may start one alone: partial views (fitted to at
        least ``start_run_arc_seen`` of the arc) are tracked apart, unpublished, and become the
        track once ``start_run`` of them in a row agree (each within the gate of that track's
        prediction; one that is not starts the run again from it). Frames without a pose are
        predicted and do not break the run. None until then."""
        if m is None:
            if self.candidate is not None and self.candidate.step(stamp_ns, jaws, None) is None:
                self.candidate, self.run = None, 0
            return None
        if self.cfg.start_run <= 0 or not m.may_run(self.cfg):
            return None
        if self.candidate is None:
            self.candidate = NeedleTracker(self.needle, replace(self.cfg, start_arc_seen=0.0, start_run=0))
            if self.arms:                           # it starts from the arms' corrections as they are
                self.candidate.arms, self.candidate.P = copy.deepcopy(self.arms), self.P[self.n:, self.n:].copy()
                self.candidate.arms_stamp_ns = self.arms_stamp_ns
        out = self.candidate.step(stamp_ns, jaws, m)
        if out is None or not out.used or out.event == "restart":
            self.candidate.reset(keep_arms=True)
            out = self.candidate.step(stamp_ns, jaws, m)
            self.run = 1
        else:
            self.run += 1
        if self.run < self.cfg.start_run:
            return None
        self.restore(self.candidate.snapshot())     # its own candidate and run are none
        return replace(out, event="start")

    def _offset(self, m: Measurement, jaws: dict) -> np.ndarray:
        """The measurement's offset from the track (world [w, v]), read as it is or turned end for
        end, whichever turns less."""
        Tw, _ = self.world(jaws)
        return min((pose_delta(T, Tw) for T in (m.T_world_needle, turned_end_for_end(m.T_world_needle, self.needle))),
                   key=lambda r: float(np.linalg.norm(r[:3])))

    def _output(self, jaws, used, turned, d, event) -> Tracked:
        Tw, Pw = self.world(jaws)
        Pw = Pw + np.diag(self.common)              # isotropic: the same in every frame's axes
        disputed = self.disputed is not None and self.rejected >= self.cfg.reset_after
        if disputed:                                # the images disagree with the track: say how far
            Pw = Pw + np.outer(self.disputed, self.disputed)
        held = self.mode == "held"
        p = None if self.identity is None else sigmoid(self.identity[0])
        corrections = self.corrections(jaws) if self.cfg.arm_correction else None
        P_jaw = (self.P[:6, :6] if self.arms else self.P) + np.diag(self.common) if held else None
        return Tracked(Tw.copy(), Pw, self.mode, self.holder, self.T.copy() if held else None, P_jaw,
                       p, used, turned, d, event, corrections, self.mirror_open, disputed)
