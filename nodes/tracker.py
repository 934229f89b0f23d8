"""Tracker node: the needle followed through grasp, handover and tissue
(``common.geometry.needle_tracker``, docs/tracking.md).

Inputs: ``pose`` (the refine node's ``PoseEstimate``s, with covariance: the measurements),
``ecm`` (``EcmPose``: the frame clock and each frame's endoscope pose), ``instruments``
(``InstrumentState`` per instrument and frame: the jaws' pose and opening; ``holds_needle`` is
never read), ``calib`` (the needle model), optionally ``no_pose`` (the refine node's
``NoPoseNotice``s: the frames it gives no pose) and ``truth``, read only for its
``sequence`` label (a new take starts a new track, ``resets.sequence``), and ``eos`` (a finite
source's ``EndOfStream``: the frames still waiting are stepped at once, and later ones as soon
as their ECM pose is in).

Each frame is stepped once, in ``seq`` order, when its ECM pose, its truth (when wired) and the
states of the instruments heard from in the last ``max_wait`` frames are in, and either its pose is in, its
notice that it has none came (``no_pose``: stepped at once), or a later frame's pose or notice
came (the refine node, which handles frames in order, is past it: a frame the detectors or the
pairing dropped): a frame without a pose is predicted by the motion model (counted
``coasted``). A frame waits at most ``max_wait`` frames (1: until the next frame) for its pose.
One that comes later, within ``replay`` frames, is filtered in all the same: the filter goes
back to that frame's state and steps again to the newest (``replayed``); what was published
meanwhile stays, the next frames carry it. Older ones are dropped (``late_pose``). An
instrument's state is the newest at or before the frame, at most ``instrument_max_age`` frames
old (at most ``MAX_INSTRUMENTS`` names are followed, one quiet that long making room; more are
counted ``instruments.too_many``).

An ``ambiguous`` pose is read with its mirror image (``refine.mirror_pose``) as the alternative
the track may explain better.

Outputs: ``pose``, method ``params.method`` (``tracked``): ``T_ecm_needle`` with
``T_world_needle``, ``T_world_ecm`` and the covariance (ECM axes); ``residual`` the
measurement's Mahalanobis^2 against the prediction (unit ``chi2``; 0 when coasted);
``end_identity`` the track's, below 0.95 flagged ``ambiguous`` with the covariance spanning the
turn; ``mode`` the track's (``rest``, ``held``, ``free``): what the fusion node reads to fuse
only views of a needle at rest. ``in_hand``: while an instrument holds the needle,
``InHandPose`` (``T_jaw_needle`` and its covariance in the jaw frame ``<name>_jaw``). ``no_pose``:
a frame stepped without a track (none yet, or lost), ``NoPoseNotice`` (method ``params.method``,
reason ``no_track``, counted ``no_pose.no_track``): the fusion's ``untracked`` input, so that it
does not wait for that frame's mode. Counters: ``rejected`` (gated out), ``turned``
(read end for end), ``events.<event>`` (``grasp``, ``handover``, ``release``, ``ungrasp``,
``rest``, ``restart``, ``flip``), ``no_covariance`` (a pose without one is no measurement).
Params: every ``TrackerConfig`` field, ``max_wait``, ``replay``, ``instrument_max_age``, ``method``:
``needletrack describe tracker``.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from common.constraints import at_least
from common.data.instruments import MAX_INSTRUMENTS
from common.geometry.end_identity import TIP_SURE, state, without_identity_covariance
from common.geometry.fusion import covariance_to_frame
from common.geometry.needle import NeedleModel
from common.geometry.needle_tracker import Jaw, Measurement, NeedleTracker, TrackerConfig
from common.geometry.refine import mirror_pose
from common.geometry.transforms import inv_T
from common.runtime.messages import (
    Calibration,
    EcmPose,
    EndOfStream,
    GroundTruth,
    InHandPose,
    InstrumentState,
    NoPoseNotice,
    PoseEstimate,
)
from common.runtime.node import Node, NodeError, run
from common.runtime.pairing import SeqCache, SeqJoin
from common.runtime.params import config_from, merge_schemas


@dataclass
class _NodeParams:
    max_wait: at_least(1) = 1         # frames a frame waits for its pose (then it is predicted)
    replay: at_least(0) = 15          # frames back a late pose is still filtered in (stepping again)
    instrument_max_age: at_least(1) = 5   # frames an instrument's newest state stands for a later frame
    method: str = "tracked"           # the method name of the tracked poses
    reset_on_sequence: bool = True    # a new truth sequence label (a new take) starts a new track


@dataclass(frozen=True)
class _Inputs:
    """What one frame's step takes: kept to step it again when its pose comes late."""
    stamp_ns: int
    T_world_ecm: np.ndarray
    jaws: dict
    measurement: Measurement | None
    sequence: object


def jaw_frame_id(name: str) -> str:
    """The frame id of instrument ``name``'s jaw frame: ``psm1`` -> ``psm1_jaw``."""
    return f"{name}_jaw"


class TrackerNode(Node):
    """Refined poses + instruments' states -> the tracked pose, and the needle in the jaws."""

    INPUTS = {"pose": PoseEstimate, "ecm": EcmPose, "instruments": InstrumentState,
              "calib": Calibration, "truth": GroundTruth, "eos": EndOfStream, "no_pose": NoPoseNotice}
    OUTPUTS = ("pose", "in_hand", "no_pose")
    KEEP_ALL = ("pose", "ecm", "instruments", "calib", "truth", "eos", "no_pose")

    Params = merge_schemas("TrackerParams", TrackerConfig, _NodeParams)

    def setup(self):
        try:
            self.config = config_from(TrackerConfig, self.p)
        except ValueError as exc:
            raise NodeError(str(exc)) from None
        if not self.wired("ecm"):
            raise NodeError("tracker: the ecm input is needed (each frame's endoscope pose, and the frame clock)")
        self.needle = NeedleModel()
        self.tracker = NeedleTracker(self.needle, self.config)
        self._clear()

    def _clear(self):
        self.poses = SeqCache(2 * self.p.max_wait + 64)
        self.posed_none = SeqCache(2 * self.p.max_wait + 64)   # seqs the refine node said it gives no pose
        self.ecm = SeqCache(2 * self.p.max_wait + 64)   # seq -> EcmPose
        self.sequences = SeqCache(2 * self.p.max_wait + 64)
        self.history = SeqCache(self.p.replay + 1)   # seq -> [the state before its step, _Inputs, counted]
        self.jaws: dict = {}                # name -> SeqCache(seq -> Jaw)
        self.frames = SeqJoin(self.p.max_wait, in_order=True)
        self.newest_said = -1               # the newest frame the refine node posed or said it has no pose
        self.stepped = -1                   # the last frame stepped
        self.sequence = None
        self.ended = False                  # the source said EndOfStream: no frame waits any more

    def on_stream_reset(self):
        self._clear()
        self.tracker.reset()

    # ---------------------------------------------------------------- inputs
    def on_calib(self, msg: Calibration):
        needle = NeedleModel.from_dict(msg.needle)
        if needle != self.needle:
            self.needle = needle
            self.tracker = NeedleTracker(needle, self.config)

    def on_truth(self, msg: GroundTruth):
        self.sequences.put(msg.seq, msg.sequence)
        self._drain()

    def on_instruments(self, msg: InstrumentState):
        if msg.name not in self.jaws and len(self.jaws) >= MAX_INSTRUMENTS:
            stalest = min(self.jaws, key=lambda n: max(self.jaws[n], default=-1))
            if max(self.jaws[stalest], default=-1) >= msg.seq - self.p.instrument_max_age:
                self.count("instruments.too_many")      # a bounded table of live names
                return
            del self.jaws[stalest]                      # an instrument gone quiet makes room
        # the states of every frame that may still wait for its pose
        self.jaws.setdefault(msg.name, SeqCache(2 * max(self.p.max_wait, self.p.instrument_max_age) + 64)).put(
            msg.seq, Jaw(np.asarray(msg.T_world_jaw, float), float(msg.jaw_rad)))
        self._drain()

    def on_ecm(self, msg: EcmPose):
        self.ecm.put(msg.seq, msg)
        if msg.seq > self.stepped:
            self.frames.hold(msg.seq, msg.seq)
        self._drain()

    def on_eos(self, msg: EndOfStream):
        """A finite source ended: every frame still waiting is stepped now (a pose still in
        flight for one of them comes late)."""
        self.ended = True
        for seq in sorted(self.frames.drop()):
            if seq > self.stepped and seq in self.ecm:
                self._step(seq)

    def on_pose(self, msg: PoseEstimate):
        if msg.seq <= self.stepped:
            self._late(msg)
            return
        self.poses.put(msg.seq, msg)
        self.newest_said = max(self.newest_said, msg.seq)
        self.frames.see(msg.seq)
        self._drain()

    def on_no_pose(self, msg: NoPoseNotice):
        """The refine node gives frame ``msg.seq`` no pose: it waits for nothing more of it."""
        if msg.seq <= self.stepped:
            return
        self.posed_none.put(msg.seq, msg.reason)
        self.newest_said = max(self.newest_said, msg.seq)
        self.frames.see(msg.seq)
        self._drain()

    # ---------------------------------------------------------------- frames
    def _ready(self, seq: int, heard: list) -> bool:
        """The frame's pose is in, or will not come; and its truth and the state of every
        instrument heard from in the last ``max_wait`` frames are in (``heard``: each one's newest
        seq; their states come in order: a later one means this one came)."""
        if self.ended:
            return True
        pose = seq in self.poses or seq in self.posed_none or self.newest_said > seq
        truth = not self.wired("truth") or seq in self.sequences
        return pose and truth and all(n >= seq for n in heard if n >= seq - self.p.max_wait)

    def _drain(self):
        heard = [next(reversed(states)) for states in self.jaws.values() if states]   # newest put last
        for seq, _complete in self.frames.due(lambda s, _item: self._ready(s, heard)):
            if seq > self.stepped:
                self._step(seq)

    def _jaws_at(self, seq: int) -> dict:
        """Each instrument's newest state at or before ``seq``, at most ``instrument_max_age``
        frames old."""
        out = {}
        for name, states in self.jaws.items():
            at = max((s for s in states if s <= seq), default=None)
            if at is not None and seq - at <= self.p.instrument_max_age:
                out[name] = states[at]
        return out

    def _measurement(self, pose: PoseEstimate | None, T_world_ecm: np.ndarray) -> Measurement | None:
        if pose is None:
            self.count("coasted")
            return None
        if pose.covariance is None:
            self.count("no_covariance")
            return None
        T_ecm_needle = np.asarray(pose.T_ecm_needle, float)
        covariance = np.asarray(pose.covariance, float)
        if pose.end_identity is not None and pose.end_identity < TIP_SURE:
            # the pose's covariance spans its turn end for end; the track reads both ends itself
            covariance = without_identity_covariance(T_ecm_needle, covariance, self.needle, pose.end_identity)
        # an ambiguous fit: its mirror image fits the images nearly as well (the covariance spans it)
        mirror = (T_world_ecm @ mirror_pose(T_ecm_needle, self.needle),) if pose.ambiguous else ()
        return Measurement(T_world_ecm @ T_ecm_needle,
                           covariance_to_frame(covariance, T_world_ecm[:3, :3]),
                           pose.end_identity, pose.model_sigma_m or 0.0, pose.model_sigma_rad or 0.0, mirror,
                           pose.arc_seen)

    def _step(self, seq: int):
        self.stepped = seq
        ecm = self.ecm.get(seq)
        pose = self.poses.pop(seq, None)
        self.posed_none.pop(seq, None)
        T_world_ecm = np.asarray(ecm.T_world_ecm, float)
        inputs = _Inputs(int(ecm.stamp_ns), T_world_ecm, self._jaws_at(seq),
                         self._measurement(pose, T_world_ecm), self.sequences.get(seq))
        state = self._state() if self.p.replay else None
        out = self._advance(inputs, count=True)
        counted = self._count_outcome(out, ())
        if self.p.replay:
            self.history.put(seq, [state, inputs, counted])
        if out is None:
            self.count("no_pose.no_track")
            self.publish("no_pose", NoPoseNotice(seq, inputs.stamp_ns, self.p.method, "no_track"))
            return
        self._publish(seq, inputs.stamp_ns, T_world_ecm, out, inputs.sequence)

    def _advance(self, inputs: "_Inputs", count: bool):
        """The filter stepped over one frame (a new take first starts a new track)."""
        if self.p.reset_on_sequence and inputs.sequence is not None and inputs.sequence != self.sequence:
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

    def _late(self, msg: PoseEstimate):
        """A pose for a frame already stepped without it (predicted): within ``replay`` frames,
        the filter goes back to that frame and steps again to the newest with it (``replayed``);
        the frames published meanwhile stay as they were, the next ones carry it. Older, or for a
        frame stepped with a pose: dropped (``late_pose``)."""
        entry = self.history.get(msg.seq)
        if entry is None or entry[1].measurement is not None:
            self.count("late_pose")
            return
        measurement = self._measurement(msg, entry[1].T_world_ecm)
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
        unsure, cov = state(T_ecm_needle, cov, self.needle, out.end_identity)
        self.publish("pose", PoseEstimate(
            seq, stamp_ns, self.p.method, T_ecm_needle, out.T_world_needle, T_world_ecm,
            0.0 if out.nis != out.nis else float(out.nis), "chi2", 1, 0.5 * (cov + cov.T),
            ambiguous=bool(unsure), sequence=sequence, end_identity=out.end_identity, mode=out.mode))
        if out.mode == "held":
            self.publish("in_hand", InHandPose(
                out.holder, seq, stamp_ns, jaw_frame_id(out.holder), out.T_jaw_needle,
                0.5 * (out.jaw_covariance + out.jaw_covariance.T), out.end_identity))


NODE = TrackerNode
if __name__ == "__main__":
    run(NODE)
