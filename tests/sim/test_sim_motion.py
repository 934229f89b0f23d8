"""Instruments that pick the needle up, hand it over and drive it through the tissue: the motion
scripts (speeds, rigid grasps, where the jaws hold the arc, the tip under the tissue), and the
moving takes `dataset generate --motion` writes, read back by `dataset check` and by an
independent reader (plain yaml + numpy) with the keypoints re-projected from the stored poses."""
import json

import numpy as np
import pytest
import yaml

from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T, pose_error, transform_points
from common.sim.motion import FPS, MAX_SPEED_M_S, MAX_TURN_RAD_S, MOTIONS, grasp_pose, minimum_jerk, script_take
from common.sim.scene import T_BODY_JAW, Instrument
from common.sim.scene_meshes import phantom_height, under_phantom

NEEDLE = NeedleModel()


def _holders(frame):
    return tuple(n for n, (_, _, h) in frame.instruments.items() if h)


def _changes(frames):
    seq = [_holders(f) for f in frames]
    return [seq[0]] + [h for i, h in enumerate(seq[1:]) if h != seq[i]]


def _grasp_angle_deg(T_jaw_needle):
    """Where on the arc the jaws hold the needle: the arc angle nearest the jaws' centre line."""
    p = transform_points(inv_T(T_jaw_needle), np.array([[0.0, 0.0, 0.0035]]))[0]   # the jaws' middle, needle frame
    return float(np.rad2deg(np.arctan2(p[1], p[0])))


def test_the_grasp_pose_puts_the_wire_between_the_jaws_and_the_jaw_frame_matches_the_body():
    T_jn = grasp_pose(NEEDLE, np.deg2rad(90), 0.003, 0.0, 0.0)
    c = transform_points(T_jn, NEEDLE.arc_points([np.deg2rad(90)]))[0]
    assert np.allclose(c, [0, 0, 0.003], atol=1e-12)                  # the grasp point on the jaws' z axis
    t = T_jn[:3, :3] @ np.array([-1.0, 0.0, 0.0])                      # the arc's tangent at 90 deg
    assert abs(t @ [1, 0, 0]) < 1e-12 and abs(t @ [0, 0, 1]) < 1e-12   # across the jaw faces (along y)
    ins = Instrument.from_jaw(inv_T(T_jn), 0.3)
    assert np.allclose(ins.T_world_jaw, inv_T(T_jn), atol=1e-12)
    R = T_BODY_JAW[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(T_BODY_JAW[:3, 2], [0, 0, -1]) and np.allclose(T_BODY_JAW[:3, 1], [1, 0, 0])
    assert minimum_jerk(0.0) == 0.0 and minimum_jerk(1.0) == 1.0 and np.isclose(minimum_jerk(0.5), 0.5)


@pytest.mark.parametrize("motion", MOTIONS)
def test_scripts_are_smooth_within_the_speed_limits_and_the_grasps_rigid(motion):
    for seed in range(3):
        take = script_take(motion, np.random.default_rng([seed, 1]), NEEDLE, 0.0004)
        fr = take.frames
        assert 60 <= len(fr) <= 900
        for a, b in zip(fr[:-1], fr[1:]):
            for name in a.instruments:
                (Ta, ja, ha), (Tb, jb, hb) = a.instruments[name], b.instruments[name]
                dt, da = pose_error(Ta, Tb)
                assert dt * FPS <= MAX_SPEED_M_S * 1.02 and da * FPS <= MAX_TURN_RAD_S * 1.02, (motion, seed, name)
                assert abs(jb - ja) * FPS < 3.0 and 0 <= jb <= np.pi
                if ha and hb:                                          # T_world_needle = T_world_jaw @ T_jaw_needle
                    e = pose_error(inv_T(Ta) @ a.T_world_needle, inv_T(Tb) @ b.T_world_needle)
                    assert e[0] < 1e-12 and e[1] < 1e-9
            if not _holders(a) and not _holders(b):
                assert np.array_equal(a.T_world_needle, b.T_world_needle)   # nobody holds it: it rests
        # the needle moves only in someone's jaws, and it moves
        assert sum(pose_error(a.T_world_needle, b.T_world_needle)[0] for a, b in zip(fr[:-1], fr[1:])) > 0.005
        expect = {"pickup": [(), ("psm1",)], "handover": [("psm1",), ("psm1", "psm2"), ("psm2",)],
                  "throw": [("psm1",), ()],
                  "suture": [(), ("psm1",), ("psm1", "psm2"), ("psm2",), ()]}[motion]
        assert _changes(fr) == expect, (seed, _changes(fr))
        for name, where in take.grasps.items():
            held = next(f for f in fr if name in _holders(f))
            T, _, _ = held.instruments[name]
            a = _grasp_angle_deg(inv_T(T) @ held.T_world_needle)
            lo, hi = {"middle": (70, 110), "tail": (112, 142)}[where]
            assert lo <= a <= hi, (motion, seed, name, where, a)


@pytest.mark.parametrize("motion", ["throw", "suture"])
def test_a_throw_takes_the_tip_through_the_tissue_and_out_while_the_jaws_hold_the_tail(motion):
    for seed in range(3):
        fr = script_take(motion, np.random.default_rng([seed, 2]), NEEDLE, 0.0004).frames
        kp = np.array([transform_points(f.T_world_needle, NEEDLE.keypoints()) for f in fr])     # (n, 5, 3)
        under = kp[..., 2] < phantom_height(kp[..., 0], kp[..., 1])
        tip = np.flatnonzero(under[:, 0])
        assert len(tip) >= 10, seed                                     # the tip goes in ...
        assert not under[-1, 0] and under[-1, 2]                        # ... and out, the middle still in
        assert not under[:, 4].any()                                    # the tail never
        assert all(not under[i, 0] for i in range(tip[0]))
        for f in fr:
            for T, _, _ in f.instruments.values():                       # the jaws' pivot above the tissue
                assert T[2, 3] > phantom_height(T[0, 3], T[1, 3])


def test_scripts_are_deterministic():
    a = script_take("suture", np.random.default_rng(5), NEEDLE, 0.0004).frames
    b = script_take("suture", np.random.default_rng(5), NEEDLE, 0.0004).frames
    assert len(a) == len(b) and all(np.array_equal(x.T_world_needle, y.T_world_needle) for x, y in zip(a, b))


# ---------------------------------------------------------------- generated takes

def _independent_reader(folder):
    """Reads a folder with yaml and numpy only (not the project's reader), checks the spec's
    ground truth and returns (meta, frames)."""
    meta = yaml.safe_load((folder / "dataset.yaml").read_text())
    assert meta["format"] == "needle-dataset" and meta["version"] == 1
    frames = [json.loads(ln) for ln in (folder / "frames.jsonl").read_text().splitlines() if ln.strip()]
    r = meta["needle"]["radius_m"]
    a = np.deg2rad(meta["needle"]["keypoint_angles_deg"])
    P = np.stack([r * np.cos(a), r * np.sin(a), np.zeros(5), np.ones(5)])                # 4x5 needle frame
    worst = 0.0
    for i, f in enumerate(frames):
        assert f["index"] == i and (folder / f["left"]).is_file() and (folder / f["right"]).is_file()
        T_wn, T_we = np.array(f["T_world_needle"]), np.array(f["T_world_ecm"])
        for cam in ("left", "right"):
            c = meta["cameras"][cam]
            p = np.linalg.inv(np.array(c["T_ecm_cam"])) @ np.linalg.inv(T_we) @ T_wn @ P
            uv = (np.array(c["K"]) @ (p[:3] / p[2]))[:2].T
            worst = max(worst, float(np.abs(uv - np.array(f["keypoints"][cam])).max()))
        assert f["needle_at_rest"] is False
        for name, inst in f["instruments"].items():
            T = np.array(inst["T_world_jaw"])
            assert T.shape == (4, 4) and np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-9)
            assert 0 <= inst["jaw_rad"] <= np.pi and isinstance(inst["holds_needle"], bool)
    assert worst < 0.01, worst
    return meta, frames


@pytest.fixture(scope="module")
def throw_take(tmp_path_factory):
    from common.cli import dataset_main
    out = tmp_path_factory.mktemp("motion") / "throw"
    assert dataset_main(["generate", "--out", str(out), "--sequences", "1", "--motion", "throw", "--width", "160",
                         "--height", "120", "--msaa", "0", "--seed", "7", "--randomise", "test", "--thread", "none",
                         "--jobs", "1", "--quiet"]) == 0
    return out


@pytest.mark.slow                 # renders a throw take first (about 7 s)
def test_generate_motion_writes_a_take_that_check_and_an_independent_reader_accept(throw_take, capsys):
    from common.cli import dataset_main
    from common.data.dataset import Dataset
    assert dataset_main(["check", str(throw_take)]) == 0
    assert "OK" in capsys.readouterr().out
    meta, frames = _independent_reader(throw_take)
    assert "motion=throw" in meta["source"]
    assert {f["sequence"] for f in frames} == {0} and [f["step"] for f in frames] == list(range(len(frames)))
    # held frames: the needle rigid in the holder's jaws, from what the folder stores
    held = [(f, np.array(f["instruments"]["psm1"]["T_world_jaw"])) for f in frames
            if f["instruments"]["psm1"]["holds_needle"]]
    assert len(held) > 30
    T_jn = [np.linalg.inv(T) @ np.array(f["T_world_needle"]) for f, T in held]
    assert max(pose_error(T_jn[0], T)[0] for T in T_jn) < 1e-9
    # what the tissue covers is not visible: the tip under the pad, however shallow, is never
    # marked seen (common.sim.visibility)
    tip_under = 0
    for f in frames:
        T = np.array(f["T_world_needle"])
        A = T @ np.array([*(NEEDLE.keypoints()[0]), 1.0])
        if under_phantom(A[None, :3])[0]:
            tip_under += 1
            assert not f["visible"]["left"][0] and not f["visible"]["right"][0], f["index"]
    assert tip_under >= 5
    assert any(any(f["visible"]["left"]) for f in frames)               # and the rest of it is seen
    ds = Dataset(throw_take)
    assert ds.multiview_groups() == {} and ds[0].multiview_group is None and not ds[0].at_rest


def test_jaws_hide_what_they_cover(tmp_path):
    """A keypoint inside the closed jaws, in front of the camera, is marked not visible."""
    import common.sim.render  # noqa: F401
    from dataclasses import replace

    from common.geometry.camera import StereoRig
    from common.sim.randomise import default_arm, get_preset
    from common.sim.render import SceneRenderer
    from common.sim.takes import plan_take
    rig = StereoRig.default(320, 240)
    arm = default_arm()
    plan = plan_take(4, 0, "pickup", get_preset("none"), rig, NEEDLE, arm, 256, 0, thread=False)
    fr = next(f for f in plan.script.frames if _holders(f))
    T_wj = fr.instruments["psm1"][0]
    # the needle turned so that keypoint C lies at the jaws' middle, the endoscope looking down on it
    T_jn = grasp_pose(NEEDLE, np.deg2rad(90), 0.0035, 0.0, 0.0)
    T_wn = T_wj @ T_jn
    spec = replace(plan.spec, T_world_needle=T_wn, instruments=[Instrument.from_jaw(T_wj, 0.0)])
    r = SceneRenderer(spec)
    from common.sim.randomise import aim_joints
    C = transform_points(T_wn, NEEDLE.keypoints())[2]
    seen_through = 0
    for d in (0.08, 0.1, 0.12):
        T_we = arm.T_world_ecm(aim_joints(arm, C, 0.0, d))
        gt = r.ground_truth(T_we, r.render(T_we))
        for cam in ("left", "right"):
            seen_through += bool(gt["visible"][cam][2])
    assert seen_through == 0


@pytest.mark.slow                 # renders a throw take first (about 7 s)
def test_arc_visible_is_the_seen_share_of_the_arc_and_agrees_with_the_keypoints(throw_take):
    """``arc_visible`` (needletrack's own field): a share in [0, 1], that of ``arc_seen``'s points; all five keypoints hidden
    means less than the whole arc seen, all five seen means more than none of it."""
    from common.data.dataset import Dataset
    frames = [json.loads(ln) for ln in (throw_take / "frames.jsonl").read_text().splitlines() if ln.strip()]
    shares = []
    for f in frames:
        for cam in ("left", "right"):
            a, v = f["arc_visible"][cam], f["visible"][cam]
            assert 0.0 <= a <= 1.0
            assert len(f["arc_seen"][cam]) == 49 and a == pytest.approx(np.mean(f["arc_seen"][cam]))
            if not any(v):
                assert a < 1.0
            if all(v):
                assert a > 0.0
            shares.append(a)
    assert max(shares) - min(shares) > 0.3           # the tissue hides more of it as the tip goes in
    assert Dataset(throw_take)[0].arc_visible["left"] == frames[0]["arc_visible"]["left"]


@pytest.mark.slow                 # renders a throw take first (about 7 s)
def test_take_every_keeps_every_kth_frame_of_the_same_take(throw_take, tmp_path):
    from common.cli import dataset_main
    out = tmp_path / "every"
    assert dataset_main(["generate", "--out", str(out), "--sequences", "1", "--motion", "throw", "--width", "160",
                         "--height", "120", "--msaa", "0", "--seed", "7", "--randomise", "test", "--thread", "none",
                         "--jobs", "1", "--quiet", "--take-every", "5"]) == 0
    assert dataset_main(["check", str(out)]) == 0
    full = [json.loads(ln) for ln in (throw_take / "frames.jsonl").read_text().splitlines() if ln.strip()]
    some = [json.loads(ln) for ln in (out / "frames.jsonl").read_text().splitlines() if ln.strip()]
    assert [f["index"] for f in some] == list(range(len(some))) and len(some) == -(-len(full) // 5)
    for f in some:                                   # the same frames of the same take, step kept
        g = full[f["step"]]
        assert f["step"] % 5 == 0 and np.allclose(f["T_world_needle"], g["T_world_needle"])
        assert f["keypoints"] == g["keypoints"]
    assert dataset_main(["generate", "--out", str(tmp_path / "bad"), "--sequences", "1", "--take-every", "3",
                         "--quiet"]) == 1                # a multi-view set has no take to thin out
