"""Which end of the needle is the tip: combining the cameras' evidence, turning observations end
for end, and a covariance that spans both answers when the images cannot decide.

A detector states per image ``p``, the probability that its keypoint A is the tip (A..E as
said) rather than the tail (then its A..E are E..A). Keypoints A..E are equally spaced on the arc,
so turning an observation end for end reverses them (and the centreline); the pose that fits the
turned observation is ``refine.tip_for_tail`` of the other: a half turn about the arc's axis of
symmetry, the same origin. Probabilities are in [0, 1]; covariances are 6x6 over
[rotation vector (rad), translation (m)] in the ECM frame, as the pose solvers give them.

This module is the end-identity policy's one home: its constants (``TIP_SURE``, the track's
decay and cap, the caps a fitted pose's tip takes), the widening of an unsure pose's covariance
over the turn (``state``) and its undoing for a consumer that weighs both readings itself
(``reading_covariance``, from what the pose says it did: ``PoseEstimate.identity_widened``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, Mapping, NamedTuple

import numpy as np

from common.frames import CAMERAS
from common.geometry.needle import NeedleModel
from common.geometry.transforms import symmetrise, transform_points

CAMERA_CORRELATION = 0.5
"""How much of a second camera's evidence is new: the two views see the same needle, so their
errors share a cause (the same thread hidden, the same light); their log-odds are averaged and
scaled up by 1 + this, not summed."""


TIP_SURE = 0.95
"""A pose whose tip is at least this probable is posed as is and is sure of it; below it, it is
flagged ``ambiguous`` with a covariance spanning the turn (``state``): the pose nodes', the
tracker's and the fusion's threshold, and what the evaluation counts as a sure tip."""


def logit(p: float) -> float:
    """Log-odds of a probability, clipped to [1e-9, 1 - 1e-9] first."""
    p = min(max(float(p), 1e-9), 1.0 - 1e-9)
    return math.log(p / (1.0 - p))


def sigmoid(z: float) -> float:
    """The probability of log-odds ``z`` (the inverse of ``logit``), overflow-safe."""
    return 1.0 / (1.0 + math.exp(-max(min(float(z), 40.0), -40.0)))


TRACK_DECAY = 0.8
"""A frame's end-identity evidence weighs this much less each frame after (``track_identity``)."""
TRACK_CAP = math.log(0.999 / 0.001)
"""The tracked needle's log-odds are capped here: a track is never surer than 0.999."""


def track_identity(p_frame: float, track: tuple[float, float] | None, same_as_track: bool | None
                   ) -> tuple[bool, tuple[float, float]]:
    """Identity is the needle's, not a frame's: a frame's probability ``p_frame`` that its A is
    the tip, combined with the tracked needle's ``track`` = (log-odds >= 0 that its reading is
    right, weight; None: no track). ``same_as_track``: whether the frame reads the needle the way
    the track does (its keypoints reproject the tracked pose as read, not turned); None when that
    cannot be told, and then the frame stands alone.

    The track's log-odds are the mean of its frames', each weighted ``TRACK_DECAY`` less per frame
    of age, not their sum: the frames of one needle share the causes of their errors (its look,
    a hidden thread, the light), so agreeing frames keep the track steady (one frame's weak
    contrary evidence does not turn it, strong evidence does) but do not make it surer than a
    typical frame. Returns (turn: read the frame end for end, the new track)."""
    z = logit(p_frame)                       # evidence that the frame's A is the tip
    same, w = True, 1.0
    if track is not None and same_as_track is not None:
        same = same_as_track
        m, w0 = track
        w = TRACK_DECAY * w0 + 1.0
        z = (TRACK_DECAY * w0 * m + (z if same else -z)) / w      # about the track's reading
    z = min(max(z, -TRACK_CAP), TRACK_CAP)
    # z > 0: the reading (the frame's if same, else the track's) is right
    return (z < 0) == same, (abs(z), w)


def unfamiliar_octaves(unfamiliarity: float | None) -> float:
    """How unlike the detector's training looks an image is, in octaves of its unfamiliarity
    (``Keypoints.unfamiliarity``, about 1 on those looks): log2 of it, clipped to [0, 3]; 0 when
    not stated. The end-identity fit's ``far`` feature (``common.detector.end_identity``)."""
    u = unfamiliarity
    return float(min(max(math.log2(u), 0.0), 3.0)) if u is not None and math.isfinite(u) and u > 0 else 0.0


def second_view_news(unfamiliarity: Iterable[float | None]) -> float:
    """How much of a second camera's evidence is new: ``CAMERA_CORRELATION`` where both images
    are like the training looks, none where one is at least twice as unlike them (an octave),
    linear in between. On a look the network never saw its errors come from the look, which
    both views share: two cameras that agree there are no surer than one."""
    far = max((unfamiliar_octaves(u) for u in unfamiliarity), default=0.0)
    return CAMERA_CORRELATION * max(0.0, 1.0 - far)


def stereo_end_identity(p_left: float | None, p_right: float | None,
                        news: float = CAMERA_CORRELATION) -> float | None:
    """The stereo frame's probability that A is the tip, from each camera's (None: not stated):
    their log-odds averaged and scaled by 1 + ``news`` (``second_view_news``) per camera beyond
    the first."""
    ps = [p for p in (p_left, p_right) if p is not None and math.isfinite(p)]
    if not ps:
        return None
    scale = 1.0 + news * (len(ps) - 1)
    return sigmoid(scale * sum(logit(p) for p in ps) / len(ps))


@dataclass(frozen=True)
class Settled:
    """How to read a stereo frame: ``turn`` it end for end (its E..A as A..E) before solving;
    ``p``, the probability that the reading's A is the tip (>= 0.5; None: nobody stated it, A is
    taken as said); ``track``, the tracked needle's new state for ``track_identity`` (None: no
    track kept)."""
    turn: bool
    p: float | None
    track: tuple[float, float] | None = None


def settle(p_left: float | None, p_right: float | None, *, tracking: bool = False,
           track: tuple[float, float] | None = None, same_as_track: bool | None = None,
           news: float = CAMERA_CORRELATION) -> Settled:
    """The end-identity policy of a stereo frame, from each camera's statement (None: not stated).

    Alone (``tracking`` false) the frame is turned when its stereo probability is below 0.5, so
    the pose is always the likelier answer. With ``tracking`` the frame is read against the
    tracked needle (``track_identity``): ``same_as_track`` says whether the frame reads the
    needle the way the track does (None: cannot be told); a frame that states nothing ends the
    track. ``news``: how much of the second camera's evidence is new (``second_view_news``).
    The returned ``p`` is what the pose states (``state``)."""
    p = stereo_end_identity(p_left, p_right, news)
    if p is None:
        return Settled(False, None, None)
    if not tracking:
        return Settled(p < 0.5, max(p, 1.0 - p), None)
    turn, new_track = track_identity(p, track, same_as_track)
    return Settled(turn, sigmoid(new_track[0]), new_track)


class Stated(NamedTuple):
    """What a pose states about its tip (``state``): ``unsure`` (to be flagged ``ambiguous``) and
    its ``covariance`` (widened over the turn when unsure; None stays None)."""
    unsure: bool
    covariance: np.ndarray | None

    @property
    def widened(self) -> bool:
        """Whether the covariance was widened over the turn (``PoseEstimate.identity_widened``)."""
        return self.unsure and self.covariance is not None


def state(T_ecm_needle: np.ndarray, covariance: np.ndarray | None, needle: NeedleModel,
          p: float | None, min_p: float = TIP_SURE) -> Stated:
    """What a pose whose tip has probability ``p`` states: (unsure, covariance). Below ``min_p``
    the tip is unsure: the pose is to be flagged ``ambiguous`` and its covariance (6x6, [w, v],
    ECM frame; None stays None) spans the end-for-end turn (``identity_covariance``)."""
    if p is None or p >= min_p:
        return Stated(False, covariance)
    if covariance is not None:
        covariance = identity_covariance(T_ecm_needle, covariance, needle, p)
    return Stated(True, covariance)


def was_widened(p: float | None, widened: bool | None) -> bool:
    """Whether a pose's covariance spans its turn end for end: what it says it did (``widened``,
    ``PoseEstimate.identity_widened``); a pose that does not say (a foreign or older source) is
    taken as this policy would have stated it, widened below ``TIP_SURE``."""
    if widened is not None:
        return bool(widened)
    return p is not None and p < TIP_SURE


def reading_covariance(T_ecm_needle: np.ndarray, covariance: np.ndarray, needle: NeedleModel,
                       p: float | None, widened: bool | None) -> np.ndarray:
    """A pose's covariance as its reading (``without_identity_covariance`` where it was widened
    over the turn, ``was_widened``): for a consumer that weighs both readings itself (the
    tracker, the fusion)."""
    if p is None or not was_widened(p, widened):
        return covariance
    return without_identity_covariance(T_ecm_needle, covariance, needle, p)


def turn_observation(uv: np.ndarray, scores: np.ndarray, centreline: np.ndarray | None = None,
                     centreline_w: np.ndarray | None = None):
    """The observation read end for end: keypoints E..A as A..E, the centreline reversed."""
    return (np.asarray(uv)[::-1].copy(), np.asarray(scores)[::-1].copy(),
            None if centreline is None else np.asarray(centreline)[::-1].copy(),
            None if centreline_w is None else np.asarray(centreline_w)[::-1].copy())


def end_for_end_delta(T_ecm_needle: np.ndarray, needle: NeedleModel) -> np.ndarray:
    """[rotation vector, translation] (6,) from a pose to its end-for-end turn (ECM frame): a
    half turn about the arc's axis of symmetry, which passes through the origin."""
    m = 0.5 * sum(needle.arc_span_rad)
    u = T_ecm_needle[:3, :3] @ np.array([math.cos(m), math.sin(m), 0.0])
    return np.concatenate([math.pi * u, np.zeros(3)])


def with_ends_seen(p: float | None, ends: tuple[bool, bool], p_max: float) -> float | None:
    """The tip probability a pose states when its fitted arc showed ``ends`` (A's end seen, E's
    end seen; ``arc_support.ends_seen``): at most ``p_max`` with an end unseen, its tip read from
    one end and a cut (the jaws, the tissue). None stays None."""
    return p if p is None or all(ends) else min(p, p_max)


READING_MARGIN = 2.0
"""A camera's keypoints read a pose end for end when its turn reprojects them this many times
closer (score-weighted mean distance) than the pose does (``reads_as_keypoints``)."""
READING_MIN_PX = 5.0
"""... and the pose is off them by more than this (px): nearer, a pose and its turn both fit (a
far or edge-on needle) and the keypoints tell nothing."""


def camera_readings(rig, needle: NeedleModel, T_ecm_needle: np.ndarray, uv: Mapping, scores: Mapping,
                    margin: float = READING_MARGIN, min_px: float = READING_MIN_PX) -> dict[str, bool]:
    """Per camera with keypoints (``uv`` {camera: (5, 2) px}, every finite one weighted by its
    ``scores``, the low-scored too): whether they read the pose as fitted (True) or turned end
    for end (False). Turned when the pose turned reprojects them ``margin`` times closer
    (score-weighted mean distance) than the pose does, the pose more than ``min_px`` off them;
    or when the camera's A alone does so: a camera's stated probability is about the end at its
    A, and its E may have fallen onto the same end, its B..D off the wire, so that the mean over
    all five tells nothing. Nearer than ``min_px`` a pose and its turn both fit (a far or
    edge-on needle) and the keypoints say nothing against the pose."""
    model = needle.keypoints()
    out = {}
    for name, pts in uv.items():
        pts = None if pts is None else np.asarray(pts, float).reshape(-1, 2)
        if pts is None or len(pts) != len(model):
            continue
        w = np.asarray(scores.get(name, np.ones(len(pts))), float).reshape(-1)
        ok = np.isfinite(pts).all(axis=1) & (w > 0)
        if not ok.any():
            continue
        cam = rig[name]
        proj = cam.project(transform_points(cam.T_cam_ecm @ T_ecm_needle, model))
        d_read = np.linalg.norm(pts - proj, axis=1)
        d_turn = np.linalg.norm(pts - proj[::-1], axis=1)
        wr = w[ok] / w[ok].sum()
        turned = float(wr @ d_read[ok]) > max(margin * float(wr @ d_turn[ok]), min_px)
        turned |= bool(ok[0]) and d_read[0] > max(margin * d_turn[0], min_px)
        out[name] = not turned
    return out


def reads_as_keypoints(rig, needle: NeedleModel, T_ecm_needle: np.ndarray, uv: Mapping,
                       scores: Mapping, margin: float = READING_MARGIN,
                       min_px: float = READING_MIN_PX) -> bool | None:
    """Whether the pose puts its tip where every camera's keypoints put A (``camera_readings``):
    False when some camera reads it turned, None when no camera has keypoints. The fit may rest
    on a few keypoints scored above its gate while the others, and the tip probability stated
    for them, read the needle the other way (one stray E on the tip): the probability is then
    not the pose's."""
    return read_as_fitted(camera_readings(rig, needle, T_ecm_needle, uv, scores, margin, min_px))


def read_as_fitted(readings: Mapping[str, bool]) -> bool | None:
    """Whether every camera reads the pose as fitted (``camera_readings``); None: no camera has
    keypoints."""
    return all(readings.values()) if readings else None


def read_tip_probability(p_by_camera: Mapping[str, float | None], readings: Mapping[str, bool],
                         news: float = CAMERA_CORRELATION) -> float | None:
    """The probability of the pose's tip that the cameras' own statements give (``p_by_camera``,
    each the probability that its A is the tip), each taken about the end of the pose at its A
    (``readings``, ``camera_readings``: a camera reading the pose turned speaks of its tail);
    combined as ``stereo_end_identity`` (one camera alone: its own statement). None when no
    camera with a reading states one."""
    unknown = sorted(set(p_by_camera) - set(CAMERAS))
    if unknown:
        raise ValueError(f"read_tip_probability: cameras must be among {CAMERAS}, got {unknown}")
    read = {c: (p if readings[c] else 1.0 - p) for c, p in p_by_camera.items() if p is not None and c in readings}
    if not read:
        return None
    return stereo_end_identity(read.get("left"), read.get("right"), news=news)


def with_reading(p: float | None, reads: bool | None, p_max: float = 0.5,
                 p_read: float | None = None) -> float | None:
    """The tip probability a pose states when its keypoints ``reads`` it as fitted
    (``reads_as_keypoints``): when some camera's read it end for end, its evidence split, at most
    the larger of ``p_max`` and ``p_read``, what the cameras' statements give the pose's tip
    taken each about the end at its A (``read_tip_probability``; None: ``p_max``): a camera
    that read the pose turned but was itself unsure takes little away. None stays None."""
    if p is None or reads is not False:
        return p
    return min(p, p_max if p_read is None else max(p_max, p_read))


def fitted_tip_probability(p: float | None, ends: tuple[bool, bool] | None, reads: bool | None, *,
                           end_unseen_p_max: float, reading_p_max: float = 0.5,
                           p_read: float | None = None, partial: bool = False) -> tuple[float | None, tuple[str, ...]]:
    """The tip probability a fitted pose states, from its frame's ``p`` (``settle``): capped at
    ``end_unseen_p_max`` when its arc showed an end no camera saw (``ends``, ``with_ends_seen``;
    None: not measured) or when it is a ``partial`` view (fitted to too little of its arc,
    ``arc_support.partial_view``: such a pose can be tens of degrees off, and a tip read right
    in the images is then no sure tip of the pose), then, when some camera's keypoints read the
    pose end for end (``reads``), at the larger of ``reading_p_max`` and ``p_read``
    (``with_reading``). Returns (p, the caps that lowered it, by name: ``end_unseen``,
    ``partial_view``, ``reading_turned``, in that order). None stays None."""
    caps = []
    stated = p if ends is None else with_ends_seen(p, ends, end_unseen_p_max)
    if stated != p:
        caps.append("end_unseen")
    if partial and stated is not None and stated > end_unseen_p_max:
        stated = end_unseen_p_max
        caps.append("partial_view")
    read = with_reading(stated, reads, reading_p_max, p_read)
    if read != stated:
        caps.append("reading_turned")
    return read, tuple(caps)


def pose_tip_probability(p: float | None, ends: tuple[bool, bool] | None, readings: Mapping[str, bool],
                         p_by_camera: Mapping[str, float | None], *, end_unseen_p_max: float,
                         reading_p_max: float = 0.5, partial: bool = False,
                         news: float = CAMERA_CORRELATION) -> tuple[float | None, tuple[str, ...]]:
    """``fitted_tip_probability`` from each camera's reading of the pose (``camera_readings``)
    and its own statement (``p_by_camera``): turned when some camera reads the pose turned, at
    most what ``read_tip_probability`` gives then (with ``news``, ``second_view_news``)."""
    return fitted_tip_probability(p, ends, read_as_fitted(readings), end_unseen_p_max=end_unseen_p_max,
                                  reading_p_max=reading_p_max, partial=partial,
                                  p_read=read_tip_probability(p_by_camera, readings, news))


def without_identity_covariance(T_ecm_needle: np.ndarray, covariance: np.ndarray, needle: NeedleModel,
                                p: float) -> np.ndarray:
    """``identity_covariance`` undone: the covariance of the pose's reading as read, for a
    consumer that weighs both readings itself (the tracker). Left as it is where taking the turn
    out would not leave it positive definite (it was not added)."""
    d = end_for_end_delta(T_ecm_needle, needle)
    C = np.asarray(covariance, float) - (1.0 - p) * np.outer(d, d)
    C = symmetrise(C)
    return C if np.linalg.eigvalsh(C)[0] > 0 else np.asarray(covariance, float)


def identity_covariance(T_ecm_needle: np.ndarray, covariance: np.ndarray, needle: NeedleModel,
                        p: float) -> np.ndarray:
    """The error's second moment about this pose when it is right with probability ``p`` and
    turned end for end otherwise: ``C + (1 - p) d d^T`` with ``d`` the turn (so a consumer's
    NEES stays honest whichever answer is true)."""
    d = end_for_end_delta(T_ecm_needle, needle)
    return np.asarray(covariance, float) + (1.0 - p) * np.outer(d, d)
