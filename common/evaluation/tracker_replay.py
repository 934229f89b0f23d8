"""The tracker replayed offline on a run's refined poses: tracker work without the detectors.

``needletrack eval --record FILE`` keeps each refined pose of a run, and each pose fitted to one
camera's view (the ``recorder`` node's
file, ``common.evaluation.recording.read_recording``). ``replay_tracker`` steps the tracker's frame
step (``common.pose.tracker_step.TrackerStep``, the node's own) over the dataset's frames with
those poses, the frames' ECM poses, instruments and truth, at the frames' recorded time, and
gathers what it publishes as the evaluator would (``Collected``), so that
``common.evaluation.moving`` scores it as ``needletrack eval`` does. A run of the moving test set
takes seconds instead of the detectors' minutes; the figures match the graph's (the refine
node's lock check reads the track the recording was made with, and the ECM pose is the folder's,
not the ``ecm`` node's: differences of micrometres). Everything here is a tool for changing the
tracker: the documented figures come from ``needletrack eval``.
"""
from __future__ import annotations

from dataclasses import fields

import numpy as np

from common.evaluation.recording import read_recording
from common.data.dataset import Dataset
from common.evaluation.collect import Collected
from common.evaluation.moving import moving_summary, stereo_visible
from common.geometry.needle_tracker import TrackerConfig
from common.pose.tracker_step import TrackerStep
from common.runtime.messages import Calibration, EcmPose, GroundTruth, InstrumentState, NoPoseNotice, PoseEstimate

METHOD = "tracked"


def recorded_pose(rec: dict) -> PoseEstimate:
    """A recorder file's pose line (``read_recording``'s dict) as the ``PoseEstimate`` it was."""
    names = {f.name for f in fields(PoseEstimate)} - {"points_ecm"}
    return PoseEstimate(**{k: v for k, v in rec.items() if k in names})


def replay_tracker(ds: Dataset, recording: str, config: TrackerConfig = TrackerConfig()) -> Collected:
    """The tracker over the folder ``ds``'s frames with the refined poses of ``recording`` (module
    docstring): what it publishes, with the frames' truth and instruments, as a ``Collected``."""
    outputs = read_recording(recording)
    col = Collected()
    meta = ds.meta
    col.calib = Calibration(stamp_ns=0, image_size=np.array(meta.image_size), cameras=meta.rig.to_dict(),
                            needle=meta.needle.to_dict(), ecm=None if meta.arm is None else meta.arm.to_dict())
    step = TrackerStep(config, max_wait=1, one_camera_wired=True)
    taken = step.on_calib(col.calib)

    def take(msgs):
        for out, msg in msgs:
            if out == "pose":
                col.add_pose(METHOD, msg, 0)
            elif out == "in_hand":
                col.add_in_hand(msg, 0)
            elif out == "arm_correction":
                col.add_arm_correction(msg, 0)
    take(taken)
    for seq, fr in enumerate(ds.frames):
        stamp = int(fr.stamp_ns)
        truth = GroundTruth.from_frame(fr, seq, stamp)
        if truth is not None:
            col.add_truth(truth, stamp)
            take(step.on_truth(truth))
        for name, pose in (fr.instruments or {}).items():
            msg = InstrumentState.from_pose(name, pose, seq, stamp)
            col.add_instrument(msg)
            take(step.on_instruments(msg))
        take(step.on_ecm(EcmPose(seq, stamp, np.asarray(fr.T_world_ecm, float))))
        rec = outputs.get(seq)
        given = None if rec is None else rec.pose if rec.pose is not None else rec.one_camera
        if given is not None:
            pose = recorded_pose(given)
            pose.stamp_ns = stamp
            take(step.on_pose(pose, one_camera=rec.pose is None))
        else:
            take(step.on_no_pose(NoPoseNotice(seq, stamp, "refined", "not_recorded")))
    return col


def replay_summary(ds: Dataset, col: Collected) -> dict:
    """``common.evaluation.moving``'s figures of the replayed track (``moving_summary``) over the
    folder ``ds`` it was replayed on."""
    from common.evaluation.collect import evaluate
    visible = {seq: stereo_visible(fr) for seq, fr in enumerate(ds.frames)}
    ev = evaluate(col, [METHOD])
    return moving_summary(ev, col.truths, col.instruments, col.in_hand, visible, [METHOD], col.poses,
                          col.arm_corrections)
