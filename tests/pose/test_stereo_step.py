"""The stereo pose nodes' frame step (common/pose/stereo.py) driven directly, no Zenoh, no node:
pairing, the wait for the frame's ECM pose, the end identity read and stated."""
from dataclasses import replace

import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.end_identity import identity_covariance
from common.geometry.needle import NeedleModel
from common.geometry.oracle import Oracle, random_needle_pose
from common.geometry.pnp import pnp_joint
from common.geometry.transforms import make_T, rotvec_to_R
from common.pose.stereo import PnpStep, TriangulationStep, turn_keypoints
from common.runtime.messages import Calibration, EcmPose, Keypoints, NoPoseNotice, PoseEstimate

RIG = StereoRig.default()
MODEL = NeedleModel()
CALIB = Calibration(0, np.array([1920, 1080]), RIG.to_dict(), MODEL.to_dict())
T_WORLD_ECM = make_T(rotvec_to_R([0.1, 0.0, 0.2]), [0.1, 0.0, 0.3])


def frames(n, p_tip=None, seed=3):
    rng, oracle = np.random.default_rng(seed), Oracle(noise_px=0.5, seed=seed)
    out = []
    for seq in range(n):
        T = random_needle_pose(rng, RIG, MODEL)
        kps = [Keypoints(cam.name, seq, seq * 1000, True, *oracle.keypoints(cam, T, MODEL, seq), 1.0,
                         detector="oracle", end_identity=p_tip) for cam in RIG.cameras]
        out.append((T, *kps))
    return out


def counter():
    counts = {}

    def count(name, n=1):
        counts[name] = counts.get(name, 0) + n
    return counts, count


def test_a_pose_waits_for_its_frames_ecm_pose_then_goes_out_without_it():
    counts, count = counter()
    step = PnpStep("joint", max_wait=2, count=count)
    step.on_calib(CALIB)
    fr = frames(4)
    out = step.on_keypoints(fr[0][1]) + step.on_keypoints(fr[0][2])
    assert out == [] and counts["pairs"] == 1                   # solved, waiting for frame 0's ECM pose
    (o, pose), = step.on_ecm(EcmPose(0, 0, T_WORLD_ECM))
    assert o == "pose" and isinstance(pose, PoseEstimate) and pose.method == "pnp_joint"
    ref = pnp_joint({k.camera: k.uv for k in fr[0][1:]}, RIG, MODEL.keypoints(), {k.camera: k.scores for k in fr[0][1:]},
                    0.5, outlier_px=10.0, max_rms_px=20.0, min_sigma_px=0.25)
    assert np.array_equal(pose.T_ecm_needle, ref.T_ecm_needle)
    assert np.allclose(pose.T_world_needle, T_WORLD_ECM @ pose.T_ecm_needle)
    assert step.on_keypoints(fr[1][1]) + step.on_keypoints(fr[1][2]) == []
    for seq in (2, 3):                                          # frame 1's ECM pose never comes
        released = step.on_keypoints(fr[seq][1]) + step.on_keypoints(fr[seq][2])
    assert [p.seq for _, p in released] == [1] and released[0][1].T_world_needle is None
    assert counts["no_ecm_pose"] == 1


def test_without_an_ecm_input_a_pose_goes_out_at_once_and_a_frame_without_one_is_said():
    step = TriangulationStep(ecm_wired=False)
    _, left, right = frames(1)[0]
    assert [o for o, _ in step.on_keypoints(left) + step.on_keypoints(right)] == ["no_pose"]   # no calibration
    step.on_calib(CALIB)
    _, left, right = frames(2)[1]
    out = step.on_keypoints(left) + step.on_keypoints(right)
    assert [o for o, _ in out] == ["points", "pose"] and out[1][1].T_world_needle is None
    out = [m for cam in ("left", "right") for m in step.on_keypoints(Keypoints.not_found(cam, 5, 0, "oracle", "none"))]
    assert [o for o, _ in out] == ["no_pose", "points"]          # said at once; the points still published
    assert isinstance(out[0][1], NoPoseNotice) and out[0][1].method == "triangulation"


def test_an_unsure_tip_is_stated_flagged_and_its_covariance_widened_over_the_turn():
    counts, count = counter()
    step = PnpStep("joint", ecm_wired=False, count=count)
    step.on_calib(CALIB)
    sure = PnpStep("joint", ecm_wired=False)
    sure.on_calib(CALIB)
    _, left, right = frames(1, p_tip=0.8)[0]
    (_, pose), = step.on_keypoints(left) + step.on_keypoints(right)
    (_, plain), = sure.on_keypoints(replace(left, end_identity=None)) + sure.on_keypoints(replace(right, end_identity=None))
    assert 0.5 < pose.end_identity < 0.95 and pose.ambiguous and pose.identity_widened
    assert counts["end_identity.unsure"] == 1
    assert np.array_equal(pose.T_ecm_needle, plain.T_ecm_needle) and plain.identity_widened is False
    assert np.allclose(pose.covariance, identity_covariance(pose.T_ecm_needle, plain.covariance, MODEL, pose.end_identity))


def test_a_pair_whose_a_is_likelier_the_tail_is_solved_turned():
    counts, count = counter()
    step = PnpStep("joint", ecm_wired=False, count=count)
    step.on_calib(CALIB)
    _, left, right = frames(1, p_tip=0.01)[0]
    (_, pose), = step.on_keypoints(left) + step.on_keypoints(right)
    other = PnpStep("joint", ecm_wired=False)
    other.on_calib(CALIB)
    (_, turned), = other.on_keypoints(turn_keypoints(left)) + other.on_keypoints(turn_keypoints(right))
    assert counts["end_identity.turned"] == 1 and pose.end_identity > 0.95 and not pose.identity_widened
    assert np.array_equal(pose.T_ecm_needle, turned.T_ecm_needle)
