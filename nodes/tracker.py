"""Tracker node: the needle followed through grasp, handover and tissue
(``common.geometry.needle_tracker``, docs/tracking.md); its frame step is
``common.pose.tracker_step.TrackerStep``.

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
the track may explain better. ``one_camera`` (the refine node's poses fitted to one camera's view,
its covariance wide in depth): a measurement as the others, but one that starts no track unless
``start_one_camera`` (a monocular endoscope, graphs/monocular.yaml); a ``no_pose`` notice of
reason ``one_camera`` then leaves the frame waiting for that pose.

Outputs: ``pose``, method ``params.method`` (``tracked``): ``T_ecm_needle`` with
``T_world_needle``, ``T_world_ecm`` and the covariance (ECM axes); ``residual`` the
measurement's Mahalanobis^2 against the prediction (unit ``chi2``; 0 when coasted);
``end_identity`` the track's, below 0.95 flagged ``ambiguous`` with the covariance spanning the
turn; ``mode`` the track's (``rest``, ``held``, ``free``): what the fusion node reads to fuse
only views of a needle at rest. ``in_hand``: while an instrument holds the needle,
``InHandPose`` (``T_jaw_needle`` and its covariance in the jaw frame ``<name>_jaw``). ``no_pose``:
a frame stepped without a track (none yet, or lost), ``NoPoseNotice`` (method ``params.method``,
reason ``no_track``, counted ``no_pose.no_track``): the fusion's ``untracked`` input, so that it
does not wait for that frame's mode. ``arm_correction`` (with the param ``arm_correction``; off:
the arms' reports taken as exact, nothing said): each arm's estimated kinematic error per frame
(``ArmCorrection``: the correction, the corrected jaw pose and its covariance); the held needle
is then carried by the corrected jaws and ``in_hand`` is in the corrected jaw frame. Counters: ``rejected`` (gated out), ``turned``
(read end for end), ``events.<event>`` (``grasp``, ``handover``, ``release``, ``ungrasp``,
``rest``, ``restart``, ``flip``), ``no_covariance`` (a pose without one is no measurement).
Params: every ``TrackerConfig`` field, ``max_wait``, ``replay``, ``instrument_max_age``, ``method``:
``needletrack describe tracker``.
"""
from __future__ import annotations

from dataclasses import dataclass

from common.constraints import at_least
from common.geometry.needle_tracker import TrackerConfig
from common.pose.tracker_step import TrackerStep
from common.runtime.messages import (
    Calibration,
    EcmPose,
    EndOfStream,
    GroundTruth,
    InstrumentState,
    NoPoseNotice,
    PoseEstimate,
)
from common.runtime.node import Node, NodeError, run
from common.runtime.params import config_from, merge_schemas


@dataclass
class _NodeParams:
    max_wait: at_least(1) = 1         # frames a frame waits for its pose (then it is predicted)
    replay: at_least(0) = 15          # frames back a late pose is still filtered in (stepping again)
    instrument_max_age: at_least(1) = 5   # frames an instrument's newest state stands for a later frame
    method: str = "tracked"           # the method name of the tracked poses
    reset_on_sequence: bool = True    # a new truth sequence label (a new take) starts a new track


class TrackerNode(Node):
    """Refined poses + instruments' states -> the tracked pose, and the needle in the jaws
    (``common.pose.tracker_step.TrackerStep``)."""

    INPUTS = {"pose": PoseEstimate, "ecm": EcmPose, "instruments": InstrumentState,
              "calib": Calibration, "truth": GroundTruth, "eos": EndOfStream, "no_pose": NoPoseNotice,
              "one_camera": PoseEstimate}
    OUTPUTS = ("pose", "in_hand", "no_pose", "arm_correction")
    KEEP_ALL = ("pose", "ecm", "instruments", "calib", "truth", "eos", "no_pose", "one_camera")

    Params = merge_schemas("TrackerParams", TrackerConfig, _NodeParams)

    def setup(self):
        try:
            config = config_from(TrackerConfig, self.p)
        except ValueError as exc:
            raise NodeError(str(exc)) from None
        if not self.wired("ecm"):
            raise NodeError("tracker: the ecm input is needed (each frame's endoscope pose, and the frame clock)")
        p = self.p
        self.step = TrackerStep(config, max_wait=p.max_wait, replay=p.replay, instrument_max_age=p.instrument_max_age,
                                method=p.method, reset_on_sequence=p.reset_on_sequence,
                                truth_wired=self.wired("truth"), one_camera_wired=self.wired("one_camera"),
                                count=self.count)

    def on_stream_reset(self):
        self.publish_all(self.step.reset())

    def on_calib(self, msg: Calibration):
        self.publish_all(self.step.on_calib(msg))

    def on_truth(self, msg: GroundTruth):
        self.publish_all(self.step.on_truth(msg))

    def on_instruments(self, msg: InstrumentState):
        self.publish_all(self.step.on_instruments(msg))

    def on_ecm(self, msg: EcmPose):
        self.publish_all(self.step.on_ecm(msg))

    def on_eos(self, msg: EndOfStream):
        self.publish_all(self.step.on_eos(msg))

    def on_pose(self, msg: PoseEstimate):
        self.publish_all(self.step.on_pose(msg))

    def on_no_pose(self, msg: NoPoseNotice):
        self.publish_all(self.step.on_no_pose(msg))

    def on_one_camera(self, msg: PoseEstimate):
        self.publish_all(self.step.on_pose(msg, one_camera=True))


NODE = TrackerNode
if __name__ == "__main__":
    run(NODE)
