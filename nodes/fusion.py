"""Multi-view fusion node (common/geometry/fusion.py): the last k pose estimates, each mapped into
the current ECM frame through the ECM poses at which they were made, outliers removed, averaged.

Output ``pose``: method ``params.method``; ``n_views`` the estimates averaged; residual the RMS
distance of those to the fused position (m); the covariance when every input carried one, the
inputs' shared model error (``model_sigma_m``, ``model_sigma_rad``) taken out before weighing and
added back once; ``ambiguous`` when every averaged estimate was; ``end_identity`` voted by the
estimates, those turned end for end counting against it, a contested tip below 0.95 flagged
(``end_identity.contested``).

Only views of a needle at rest are fused, and whether it is comes from what the system
measures: ``motion``, optional, the tracker's poses (``tracker/pose``), read only for their
``mode`` (``PoseEstimate.mode``, docs/tracking.md). A frame whose needle the tracker says is
``held`` or ``free`` is fused with no other: the window starts again, the estimate passes alone
(``resets.needle_moves``), and the next frame at rest starts a new window. An estimate waits
for its frame's mode until the tracker has stated that frame or a later one (it steps frames
in order; one it skipped had no track) or, with ``untracked`` wired (``tracker/no_pose``), said
that it has no track for it; a frame without a track passes alone too
(``resets.motion_unknown``), as does one whose mode did not come within ``max_wait`` frames
(``no_motion``). While the tracker says ``rest`` the fusion is the same as without it. A needle
in the jaws is fused in the jaw frame by the tracker itself: its ``held`` state, ``T_jaw_needle``
filtered over frames (``tracker/in_hand``).

A view flagged ``ambiguous`` is read either as it is or as its mirror image, whichever the
group agrees on (``common.geometry.fusion.mirror_consensus``); ``calib``, optional, gives the
needle's shape for the mirror image and the end-for-end turn (default: the standard needle).

``truth`` is read for its ``sequence`` label (a new multi-view group resets the queue) and,
only where ``motion`` is not wired (a graph without the tracker, the static evaluation), for
``needle_at_rest``: a frame of a take whose needle moves is no multi-view group, its estimate
passes alone (``resets.moving_needle``). Command ``reset`` empties the queue. Params:
``needletrack describe fusion`` ([docs/nodes.md](../docs/nodes.md)).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry.fusion import FusionConfig, MultiViewFusion
from common.geometry.needle import NeedleModel
from common.runtime.messages import Calibration, EcmPose, GroundTruth, NoPoseNotice, PoseEstimate
from common.runtime.node import Node, run
from common.runtime.pairing import FrameJoin, SeqCache, Wait
from common.runtime.params import config_from, merge_schemas


@dataclass
class _NodeParams:
    method: str = "multiview"       # the method name of the fused poses
    reset_on_sequence: bool = True  # a new truth sequence label starts the queue again
    max_wait: int = 30              # frames an estimate waits for its ECM pose (else no_pose.no_ecm_pose), truth, mode


class FusionNode(Node):
    """Multi-view fusion of the last k estimates, in the current ECM frame."""

    INPUTS = {"pose": PoseEstimate, "ecm": EcmPose, "truth": GroundTruth, "motion": PoseEstimate,
              "untracked": NoPoseNotice, "calib": Calibration}
    OUTPUTS = ("pose",)
    KEEP_ALL = ("pose", "ecm", "truth", "motion", "untracked")

    # every FusionConfig field is a param of the same name, beside the node's own
    Params = merge_schemas("FusionParams", FusionConfig, _NodeParams)

    def setup(self):
        p = self.p
        self.fusion = self._fusion(NeedleModel())
        self.method = p.method
        self.reset_on_sequence = p.reset_on_sequence
        self.ecm_poses = SeqCache()
        self.sequences = SeqCache()
        self.moving = SeqCache()                              # seqs whose needle moves in its take (truth)
        self.modes = SeqCache()                               # seq -> the tracker's mode
        self.tracked = -1                                     # the newest frame the tracker stated
        self.after_move = False                               # the last estimate's needle was not at rest
        self.said_no_mode = False
        # views waiting for their ECM pose (dropped without it), truth (its sequence label), mode
        self.pending = FrameJoin([
            Wait("ecm", lambda seq, m: m.T_world_ecm is not None or not self.wired("ecm") or seq in self.ecm_poses,
                 needed=True, missing="no_pose.no_ecm_pose"),
            Wait("truth", lambda seq, m: not (self.reset_on_sequence and m.sequence is None and self.wired("truth"))
                 or seq in self.sequences, missing="no_sequence"),
            Wait("motion", lambda seq, m: not self.wired("motion") or seq in self.modes or self.tracked >= seq,
                 missing="no_motion"),
        ], p.max_wait, in_order=True)

    def _fusion(self, needle: NeedleModel) -> MultiViewFusion:
        return MultiViewFusion(config_from(FusionConfig, self.p), needle=needle)

    def on_stream_reset(self):
        """A new source stream: the window of views and every per-frame cache start again."""
        self.ecm_poses.clear()
        self.sequences.clear()
        self.moving.clear()
        self.modes.clear()
        self.tracked = -1
        self.after_move = False
        gone = self.pending.reset()
        if gone:
            self.count("no_pose.source_restart", len(gone))
        self.fusion.reset()

    # ---------------------------------------------------------------- inputs
    def on_calib(self, msg: Calibration):
        needle = NeedleModel.from_dict(msg.needle)
        if needle != self.fusion.needle:      # another needle: its turn and mirror image; a new window
            self.fusion = self._fusion(needle)

    def on_ecm(self, msg: EcmPose):
        self.ecm_poses.put(msg.seq, np.asarray(msg.T_world_ecm, dtype=float))
        self._drain()

    def on_truth(self, msg: GroundTruth):
        self.sequences.put(msg.seq, msg.sequence)
        if not self.wired("motion") and msg.multiview_group is None and msg.sequence is not None:
            self.moving.put(msg.seq, True)                    # the tracker decides where it runs
        self._drain()

    def on_motion(self, msg: PoseEstimate):
        if msg.mode is None:                                  # no tracker's: a frame without a track
            if not self.said_no_mode:
                self.log.warning("motion: seq %d: a pose without a mode (method %r): the input wants "
                                 "the tracker's poses (tracker/pose); counted motion.no_mode", msg.seq, msg.method)
                self.said_no_mode = True
            self.count("motion.no_mode")
        self.modes.put(msg.seq, msg.mode)
        self.tracked = max(self.tracked, msg.seq)
        self._drain()

    def on_untracked(self, msg: NoPoseNotice):
        """The tracker has no track at frame ``msg.seq``: its mode is known to be none."""
        self.modes.put(msg.seq, None)
        self._drain()

    def on_pose(self, msg: PoseEstimate):
        self.pending.hold(msg.seq, msg)
        self._drain()

    def on_command(self, msg):
        if msg.name == "reset":
            self.fusion.reset()
            self.count("resets.command")
        else:
            super().on_command(msg)

    # ---------------------------------------------------------------- fusion
    def _drain(self):
        for r in self.pending.due():
            for counter in r.counters:
                self.count(counter)
            if not r.dropped:
                self._fuse(r.item)

    def _moves(self, seq: int) -> str | None:
        """Why frame ``seq``'s needle is not taken as at rest (its counter), or None: the
        tracker's mode where it is wired, else the truth's take of a moving needle."""
        if self.wired("motion"):
            mode = self.modes.get(seq)
            if mode == "rest":
                return None
            return "resets.motion_unknown" if mode is None else "resets.needle_moves"
        if self.reset_on_sequence and self.moving.get(seq):
            return "resets.moving_needle"
        return None

    def _fuse(self, msg: PoseEstimate):
        T_world_ecm = msg.T_world_ecm
        if T_world_ecm is None:
            T_world_ecm = self.ecm_poses.get(msg.seq) if self.wired("ecm") else np.eye(4)
        sequence = msg.sequence
        if sequence is None and self.reset_on_sequence:
            sequence = self.sequences.get(msg.seq)
        moves = self._moves(msg.seq)
        if moves or self.after_move:
            self.fusion.reset()               # a moving needle, or the first view at rest after it
        if moves:
            self.count(moves)
        self.after_move = moves is not None
        out = self.fusion.add(msg.T_ecm_needle, T_world_ecm, msg.covariance, seq=msg.seq,
                              sequence=sequence if self.reset_on_sequence else None,
                              common_sigma_m=msg.model_sigma_m or 0.0, ambiguous=bool(msg.ambiguous),
                              common_sigma_rad=msg.model_sigma_rad or 0.0, end_identity=msg.end_identity,
                              identity_widened=msg.identity_widened)
        if out.reset:
            self.count("resets")
        self.count("outliers", int(out.n_queued - out.n_views))
        if out.turned:
            self.count("end_identity.contested")
        self.publish("pose", PoseEstimate(
            msg.seq, msg.stamp_ns, self.method, out.T_ecm_needle, out.T_world_needle,
            np.asarray(T_world_ecm, dtype=float), out.rms_m, "m", out.n_views, out.covariance,
            ambiguous=out.ambiguous, sequence=sequence, model_sigma_m=out.common_sigma_m or None,
            model_sigma_rad=out.common_sigma_rad or None, end_identity=out.end_identity,
            identity_widened=out.identity_widened))


NODE = FusionNode
if __name__ == "__main__":
    run(NODE)
