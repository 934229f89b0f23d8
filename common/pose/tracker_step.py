"""The frame step of the tracker (the ``tracker`` node): refined poses and the instruments'
states to the tracked pose and the needle in the jaws (``common.geometry.needle_tracker``,
docs/tracking.md).

Frames (``common.runtime.pairing.FrameJoin``): each frame is stepped once, in ``seq`` order, when
its ECM pose (what holds a frame), its truth (with ``truth_wired``: the ``sequence`` label; a new
take starts a new track, ``resets.sequence``) and the states of the instruments heard from in the
last ``max_wait`` frames are in, and either its pose is in, its notice that it has none came
(``NoPoseNotice``), or a later frame's pose or notice came (the refine node, which handles
frames in order, is past it): a frame without a pose is predicted by the motion model (counted
``coasted``). A frame waits at most ``max_wait`` frames for its pose. One that comes later,
within ``replay`` frames, is filtered in all the same: the filter goes back to that frame's
state and steps again to the newest (``replayed``); what was published meanwhile stays, the
next frames carry it. Older ones are dropped (``late_pose``). After ``on_eos`` (a finite
source ended) no frame waits any more.

Instruments (``InstrumentTable``): an instrument's state is the newest at or before the frame,
at most ``instrument_max_age`` frames old; at most ``MAX_INSTRUMENTS`` names are followed, one
quiet that long making room (more are counted ``instruments.too_many``).

A pose is a measurement (``measurement``) in world axes: its covariance as its reading
(``end_identity.reading_covariance``: the widening over the turn it says it has taken out, the
track weighs both ends itself); an ``ambiguous`` pose is read with its mirror image
(``refine.mirror_pose``) as the alternative the track may explain better; a pose without a
covariance is no measurement (``no_covariance``). A track whose mirror is open
(``Tracked.mirror_open``: started from one camera's view, no stereo view since) is said flagged
``ambiguous``, its covariance widened to span the mirror image (``MIRROR_SHARE``; counted
``mirror_open``); a disputed track (``Tracked.disputed``: its measurements rejected ``reset_after``
times in a row, the covariance widened to the newest) is said flagged too (counted ``disputed``).
A pose fitted to one camera's view
(``on_pose(..., one_camera=True)``, the refine node's ``one_camera``) is a measurement that starts
no track unless ``TrackerConfig.start_one_camera`` (``Measurement.one_camera``); with
``one_camera_wired``, a frame said to have no pose for that reason (``NoPoseNotice`` reason
``one_camera``) waits for its one-camera pose instead of being stepped without one.

Each public method returns the ``(output, message)`` pairs to publish: ``pose`` (``method``:
``T_ecm_needle`` with the world pose, the covariance in ECM axes, ``residual`` the measurement's
Mahalanobis^2, unit ``chi2``; the track's ``end_identity`` and ``mode``, below ``TIP_SURE``
flagged ``ambiguous`` with the covariance spanning the turn), ``in_hand`` (``InHandPose`` while
an instrument holds the needle), ``no_pose`` (a frame stepped without a track, reason
``no_track``) and, with ``arm_correction``, ``arm_correction`` (``ArmCorrection``: each arm's
estimated error, per frame the arm reports its jaws in, with or without a track; the needle in the
jaws is then in the corrected jaw frame). Counters go to ``count(name, n)``: ``rejected``, ``turned``, ``events.<event>``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import numpy as np

from common.data.instruments import MAX_INSTRUMENTS
from common.geometry.end_identity import reading_covariance, state
from common.geometry.fusion import covariance_to_frame
from common.geometry.needle import NeedleModel
from common.geometry.needle_tracker import Jaw, Measurement, NeedleTracker, TrackerConfig
from common.geometry.refine import mirror_pose
from common.geometry.transforms import inv_T, pose_delta, symmetrise
from common.runtime.messages import (
    ArmCorrection,
    Calibration,
    EcmPose,
    EndOfStream,
    GroundTruth,
    InHandPose,
    InstrumentState,
    NoPoseNotice,
    PoseEstimate,
)
from common.runtime.pairing import FrameJoin, SeqCache, Wait


MIRROR_SHARE = 0.5
"""A track whose mirror is open states its covariance widened by this share of the mirror's offset
(``C + 0.5 d d^T``: the two readings equally likely, as ``end_identity`` widens an unsure tip)."""


@dataclass(frozen=True)
class FrameInputs:
    """What one frame's step takes: kept to step it again when its pose comes late."""
    stamp_ns: int
    T_world_ecm: np.ndarray
    jaws: dict
    measurement: Measurement | None
    sequence: object


def jaw_frame_id(name: str) -> str:
    """The frame id of instrument ``name``'s jaw frame: ``psm1`` -> ``psm1_jaw``."""
    return f"{name}_jaw"


class InstrumentTable:
    """The instruments' states by name and frame (module docstring): at most ``MAX_INSTRUMENTS``
    names, each state standing for later frames ``max_age`` frames; ``keep`` frames of each."""

    def __init__(self, max_age: int, keep: int):
        self.max_age, self.keep = max_age, keep
        self.states: dict = {}              # name -> SeqCache(seq -> Jaw)

    def put(self, msg: InstrumentState) -> bool:
        """Take an instrument's state; False when the table is full of live names."""
        if msg.name not in self.states and len(self.states) >= MAX_INSTRUMENTS:
            stalest = min(self.states, key=lambda n: max(self.states[n], default=-1))
            if max(self.states[stalest], default=-1) >= msg.seq - self.max_age:
                return False                             # a bounded table of live names
            del self.states[stalest]                     # an instrument gone quiet makes room
        self.states.setdefault(msg.name, SeqCache(self.keep)).put(
            msg.seq, Jaw(np.asarray(msg.T_world_jaw, float), float(msg.jaw_rad)))
        return True

    def heard(self) -> list[int]:
        """Each instrument's newest seq (their states come in order)."""
        return [next(reversed(states)) for states in self.states.values() if states]   # newest put last

    def at(self, seq: int) -> dict:
        """Each instrument's newest state at or before ``seq``, at most ``max_age`` frames old."""
        out = {}
        for name, states in self.states.items():
            at = max((s for s in states if s <= seq), default=None)
            if at is not None and seq - at <= self.max_age:
                out[name] = states[at]
        return out


class TrackerStep:
    """The tracker's frames (module docstring). ``max_wait``, ``replay``, ``instrument_max_age``
    in frames; ``method``: the tracked poses' method; ``reset_on_sequence``: a new truth sequence
    label starts a new track; ``truth_wired``: whether frames wait for their truth."""

    def __init__(self, config: TrackerConfig = TrackerConfig(), *, max_wait: int = 1, replay: int = 15,
                 instrument_max_age: int = 5, method: str = "tracked", reset_on_sequence: bool = True,
                 truth_wired: bool = True, one_camera_wired: bool = False,
                 count: Callable[..., None] | None = None):
        self.config, self.max_wait, self.replay = config, max_wait, replay
        self.one_camera_wired = one_camera_wired
        self.instrument_max_age, self.method = instrument_max_age, method
        self.reset_on_sequence, self.truth_wired = reset_on_sequence, truth_wired
        self.count = count or (lambda name, n=1: None)    # a counter sink: the node's count
        self.needle = NeedleModel()
        self.tracker = NeedleTracker(self.needle, config)
        self._clear()
        self._out: list = []

    def _clear(self):
        size = 2 * self.max_wait + 64
        self.poses = SeqCache(size)
        self.one_camera = SeqCache(size)   # seqs whose pose was fitted to one camera's view
        self.posed_none = SeqCache(size)   # seqs the refine node said it gives no pose
        self.ecm = SeqCache(size)          # seq -> EcmPose
        self.sequences = SeqCache(size)
        self.history = SeqCache(self.replay + 1)   # seq -> [the state before its step, FrameInputs, counted]
        # the states of every frame that may still wait for its pose
        self.jaws = InstrumentTable(self.instrument_max_age, 2 * max(self.max_wait, self.instrument_max_age) + 64)
        waits = [Wait("pose", lambda s, _: self.ended or s in self.poses or s in self.posed_none
                      or self.newest_said > s)]
        if self.truth_wired:
            waits.append(Wait("truth", lambda s, _: self.ended or s in self.sequences))
        waits.append(Wait("instruments", lambda s, _: self.ended or all(
            n >= s for n in self.jaws.heard() if n >= s - self.max_wait)))
        self.frames = FrameJoin(waits, self.max_wait, in_order=True)
        self.newest_said = -1               # the newest frame the refine node posed or said it has no pose
        self.stepped = -1                   # the last frame stepped
        self.sequence = None
        self.ended = False                  # the source said EndOfStream: no frame waits any more

    def reset(self) -> list:
        """A new source stream: every frame, and the track, start again."""
        self._clear()
        self.tracker.reset()
        return self._take()

    # ---------------------------------------------------------------- inputs
    def on_calib(self, msg: Calibration) -> list:
        needle = NeedleModel.from_dict(msg.needle)
        if needle != self.needle:
            self.needle = needle
            self.tracker = NeedleTracker(needle, self.config)
        return self._take()

    def on_truth(self, msg: GroundTruth) -> list:
        self.sequences.put(msg.seq, msg.sequence)
        self._drain()
        return self._take()

    def on_instruments(self, msg: InstrumentState) -> list:
        if not self.jaws.put(msg):
            self.count("instruments.too_many")
            return self._take()
        self._drain()
        return self._take()

    def on_ecm(self, msg: EcmPose) -> list:
        self.ecm.put(msg.seq, msg)
        if msg.seq > self.stepped:
            self.frames.hold(msg.seq, msg.seq)
        self._drain()
        return self._take()

    def on_eos(self, msg: EndOfStream) -> list:
        """A finite source ended: every frame still waiting is stepped now (a pose still in
        flight for one of them comes late)."""
        self.ended = True
        for seq in sorted(self.frames.drop()):
            if seq > self.stepped and seq in self.ecm:
                self._step(seq)
        return self._take()

    def on_pose(self, msg: PoseEstimate, one_camera: bool = False) -> list:
        """A frame's pose; ``one_camera``: fitted to one camera's view (module docstring)."""
        if msg.seq <= self.stepped:
            self._late(msg, one_camera)
            return self._take()
        if one_camera:
            self.one_camera.put(msg.seq, True)
        self.poses.put(msg.seq, msg)
        self.newest_said = max(self.newest_said, msg.seq)
        self.frames.see(msg.seq)
        self._drain()
        return self._take()

    def on_no_pose(self, msg: NoPoseNotice) -> list:
        """The refine node gives frame ``msg.seq`` no pose: it waits for nothing more of it."""
        if msg.seq <= self.stepped:
            return self._take()
        if self.one_camera_wired and msg.reason == "one_camera":
            return self._take()           # its pose comes on one_camera
        self.posed_none.put(msg.seq, msg.reason)
        self.newest_said = max(self.newest_said, msg.seq)
        self.frames.see(msg.seq)
        self._drain()
        return self._take()

    # ---------------------------------------------------------------- frames
    def _drain(self):
        for r in self.frames.due():
            if r.item > self.stepped:
                self._step(r.item)

    def measurement(self, pose: PoseEstimate | None, T_world_ecm: np.ndarray,
                    one_camera: bool = False) -> Measurement | None:
        """The measurement a pose gives (module docstring); None: coasted, or no covariance."""
        if pose is None:
            self.count("coasted")
            return None
        if pose.covariance is None:
            self.count("no_covariance")
            return None
        T_ecm_needle = np.asarray(pose.T_ecm_needle, float)
        # the pose's covariance may span its turn end for end; the track reads both ends itself
        covariance = reading_covariance(T_ecm_needle, np.asarray(pose.covariance, float), self.needle,
                                        pose.end_identity, pose.identity_widened)
        # an ambiguous fit: its mirror image fits the images nearly as well (the covariance spans it)
        mirror = (T_world_ecm @ mirror_pose(T_ecm_needle, self.needle),) if pose.ambiguous else ()
        return Measurement(T_world_ecm @ T_ecm_needle,
                           covariance_to_frame(covariance, T_world_ecm[:3, :3]),
                           pose.end_identity, pose.model_sigma_m or 0.0, pose.model_sigma_rad or 0.0, mirror,
                           pose.arc_seen, one_camera)

    def _step(self, seq: int):
        self.stepped = seq
        ecm = self.ecm.get(seq)
        pose = self.poses.pop(seq, None)
        one_camera = bool(self.one_camera.pop(seq, False))
        if one_camera and pose is not None:
            self.count("one_camera")
        self.posed_none.pop(seq, None)
        T_world_ecm = np.asarray(ecm.T_world_ecm, float)
        inputs = FrameInputs(int(ecm.stamp_ns), T_world_ecm, self.jaws.at(seq),
                             self.measurement(pose, T_world_ecm, one_camera), self.sequences.get(seq))
        state_before = self._state() if self.replay else None
        out = self._advance(inputs, count=True)
        counted = self._count_outcome(out, ())
        if self.replay:
            self.history.put(seq, [state_before, inputs, counted])
        self._publish_corrections(seq, inputs)
        if out is None:
            self.count("no_pose.no_track")
            self._out.append(("no_pose", NoPoseNotice(seq, inputs.stamp_ns, self.method, "no_track")))
            return
        self._publish(seq, inputs.stamp_ns, T_world_ecm, out, inputs.sequence)

    def _publish_corrections(self, seq: int, inputs: FrameInputs):
        """Each arm's estimated error, for the arms that report their jaws in this frame."""
        if not self.config.arm_correction:
            return
        for name, (K, cov) in self.tracker.corrections(inputs.jaws).items():
            if name in inputs.jaws:
                self._out.append(("arm_correction", ArmCorrection(
                    name, seq, inputs.stamp_ns, K, K @ inputs.jaws[name].T_world_jaw, cov)))

    def _advance(self, inputs: FrameInputs, count: bool):
        """The filter stepped over one frame (a new take first starts a new track)."""
        if self.reset_on_sequence and inputs.sequence is not None and inputs.sequence != self.sequence:
            if count and self.sequence is not None and self.tracker.active:
                self.count("resets.sequence")
            self.tracker.reset()
            self.sequence = inputs.sequence
        return self.tracker.step(inputs.stamp_ns, inputs.jaws, inputs.measurement)

    def _count_outcome(self, out, counted) -> tuple:
        """Count what the step found (``rejected``, ``turned``, ``events.<event>``) that is not
        in ``counted`` already (a frame stepped again counts only what is new); returns it."""
        found = () if out is None else tuple(
            k for k, yes in (("rejected", out.used is False), ("turned", out.turned),
                             (f"events.{(out.event or '').split(':')[0]}", bool(out.event))) if yes)
        for k in found:
            if k not in counted:
                self.count(k)
        return found

    def _state(self):
        return self.tracker.snapshot(), self.sequence

    def _late(self, msg: PoseEstimate, one_camera: bool = False):
        """A pose for a frame already stepped without it (predicted): within ``replay`` frames,
        the filter goes back to that frame and steps again to the newest with it (``replayed``);
        the frames published meanwhile stay as they were, the next ones carry it. Older, or for a
        frame stepped with a pose: dropped (``late_pose``)."""
        entry = self.history.get(msg.seq)
        if entry is None or entry[1].measurement is not None:
            self.count("late_pose")
            return
        measurement = self.measurement(msg, entry[1].T_world_ecm, one_camera)
        if measurement is None:
            return
        (snapshot, self.sequence) = entry[0]
        self.tracker.restore(snapshot)
        for seq in [s for s in self.history if s >= msg.seq]:
            entry = self.history[seq]
            if seq == msg.seq:
                entry[1] = dataclasses.replace(entry[1], measurement=measurement)
            entry[0] = self._state()
            entry[2] = self._count_outcome(self._advance(entry[1], count=False), entry[2])
        self.count("replayed")

    def _publish(self, seq, stamp_ns, T_world_ecm, out, sequence):
        T_ecm_needle = inv_T(T_world_ecm) @ out.T_world_needle
        cov = covariance_to_frame(out.covariance, T_world_ecm[:3, :3].T)
        if out.disputed:
            self.count("disputed")
        if out.mirror_open:       # one view: the arc's mirror image fits as well (needle_tracker docstring)
            d = pose_delta(mirror_pose(T_ecm_needle, self.needle), T_ecm_needle)
            cov = cov + MIRROR_SHARE * np.outer(d, d)
            self.count("mirror_open")
        stated = state(T_ecm_needle, cov, self.needle, out.end_identity)
        cov = stated.covariance
        self._out.append(("pose", PoseEstimate(
            seq, stamp_ns, self.method, T_ecm_needle, out.T_world_needle, T_world_ecm,
            0.0 if out.nis != out.nis else float(out.nis), "chi2", 1, symmetrise(cov),
            ambiguous=bool(stated.unsure or out.mirror_open or out.disputed), sequence=sequence,
            end_identity=out.end_identity,
            mode=out.mode,
            identity_widened=stated.widened)))
        if out.mode == "held":
            self._out.append(("in_hand", InHandPose(
                out.holder, seq, stamp_ns, jaw_frame_id(out.holder), out.T_jaw_needle,
                symmetrise(out.jaw_covariance), out.end_identity)))

    def _take(self) -> list:
        out, self._out = self._out, []
        return out
