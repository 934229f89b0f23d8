"""``tracking.mp4`` (common/evaluation/take_video.py): the shown take's frames drawn from a run's
poses, written as MP4 and read back by OpenCV."""
import cv2
import numpy as np
import pytest

from common.evaluation.collect import Collected, evaluate
from common.evaluation.take_video import take_frames, write_take_video
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import make_T, rotvec_to_R
from common.runtime.messages import GroundTruth, InHandPose, InstrumentState, PoseEstimate
from common.viewer.draw import method_bgr


def _take(n=12, sequence=0, first=0):
    """A moving take before the default rig (the cameras look along -z_ecm; ECM = world): the
    needle 10 cm in front, turning; tracked on every frame but the 4th, held from the 6th."""
    col = Collected()
    for k in range(n):
        seq = first + k
        T = make_T(rotvec_to_R([0.0, 0.0, 0.05 * k]), [0.002 * k, 0.0, -0.1])
        col.add_truth(GroundTruth(seq, seq, sequence=sequence, T_world_ecm=np.eye(4), T_world_needle=T,
                                  needle_at_rest=False), seq)
        col.add_instrument(InstrumentState("psm1", seq, seq, make_T(np.eye(3), [0.012, 0.0, -0.1]), 0.1, k >= 5))
        if k != 3:
            off = make_T(np.eye(3), [0.0005, 0.0, 0.0])       # 0.5 mm off
            col.add_pose("tracked", PoseEstimate(seq, seq, "tracked", T @ off, T_world_needle=T @ off,
                                                 T_world_ecm=np.eye(4), mode="held" if k >= 5 else "rest"), seq)
        if k >= 5:
            col.add_in_hand(InHandPose("psm1", seq, seq, "psm1_jaw", np.eye(4), np.eye(6) * 1e-8), seq)
    return col


def read_video(path):
    """(frames, frames/s) of a video file, every frame decoded by OpenCV."""
    cap = cv2.VideoCapture(str(path))
    assert cap.isOpened()
    frames = []
    while True:
        ok, f = cap.read()
        if not ok:
            break
        frames.append(f)
    fps = cap.get(cv2.CAP_PROP_FPS)
    cap.release()
    return frames, fps


def test_the_video_has_a_frame_per_frame_of_the_longest_take_at_30_hz(tmp_path):
    col = _take(12)
    for gt in _take(5, sequence=1, first=100).truths.values():     # a shorter take: not shown
        col.add_truth(gt, 0)
    ev = evaluate(col, ["tracked"])
    path = tmp_path / "tracking.mp4"
    assert write_take_video(path, col, ev, StereoRig.default(), NeedleModel(), None, {}, width=640) == 12
    frames, fps = read_video(path)
    assert len(frames) == 12 and frames[0].shape == (360, 640, 3) and fps == pytest.approx(30.0)
    assert write_take_video(path, col, ev, StereoRig.default(), NeedleModel(), None, {}, width=320, every=2) == 6
    frames, fps = read_video(path)
    assert len(frames) == 6 and frames[0].shape == (180, 320, 3) and fps == pytest.approx(15.0)


def test_each_frame_draws_the_tracked_arc_where_posed_and_captions_it():
    col = _take(8)
    ev = evaluate(col, ["tracked"])
    images = lambda seq: {"left": np.full((1080, 1920, 3), 40, np.uint8)}
    pics = dict(take_frames(col, ev, StereoRig.default(), NeedleModel(), images, {s: 0.5 for s in col.truths}))
    assert sorted(pics) == list(range(8))
    colour = np.array(method_bgr("tracked"))
    drawn = {s: int(np.all(np.abs(p.astype(int) - colour) <= 8, axis=2).sum()) for s, p in pics.items()}
    assert drawn[3] == 0 and all(drawn[s] > 200 for s in pics if s != 3)
    # the caption differs where the frame is held (the mode, the tracker's InHandPose)
    assert not np.array_equal(pics[0][:90, :300], pics[6][:90, :300])


def test_no_moving_take_writes_no_file(tmp_path):
    col = _take(4)
    for gt in col.truths.values():
        gt.needle_at_rest = True
    ev = evaluate(col, ["tracked"])
    path = tmp_path / "tracking.mp4"
    path.write_bytes(b"stale")
    assert write_take_video(path, col, ev, StereoRig.default(), NeedleModel()) == 0
    assert not path.exists()
