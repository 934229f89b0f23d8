"""Instruments reported as a dVRK reports them (common/sim/arm_error.py): the error's parts, their
bounds and shapes, the truth written beside the report, the rendered take unchanged, and the
reader's rigidity check made against the truth."""
from dataclasses import replace

import numpy as np
import pytest

from common.data.check import GRASP_TOL_M, GRASP_TOL_RAD, check_take
from common.data.dataset import Frame, parse_frame
from common.data.instruments import InstrumentPose, T_jaw_needle
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import R_to_rotvec, inv_T, pose_error
from common.runtime.messages import InstrumentState, MessageError, decode, encode
from common.sim.arm_error import ARM_ERRORS, DRAW_LOW, ArmErrorConfig, arm_error_config
from common.sim.randomise import default_arm, get_preset
from common.sim.takes import frame_instruments, plan_take, take_spec

NEEDLE = NeedleModel()
RIG = StereoRig.default(320, 240)
ARM = default_arm()
NAMES = ("psm1", "psm2")


def _plan(arm_error=None, seed=11, take=0, motion="suture"):
    return plan_take(seed, take, motion, get_preset("test"), RIG, NEEDLE, ARM, 256, 0, thread=False,
                     arm_error=None if arm_error is None else arm_error_config(arm_error))


def _reports(plan):
    """Per frame: {name: InstrumentPose as reported}."""
    return [frame_instruments(fr, plan.arm_errors, k) for k, fr in enumerate(plan.script.frames)]


def _errors(plan, name):
    """Per frame: (true T_world_jaw, E = inv(T_true) @ T_reported, reported - true jaw_rad)."""
    out = []
    for k, fr in enumerate(plan.script.frames):
        T, jaw, _ = fr.instruments[name]
        p = frame_instruments(fr, plan.arm_errors, k)[name]
        out.append((T, inv_T(T) @ p.T_world_jaw, p.jaw_rad - jaw))
    return out


ONLY = {k: ArmErrorConfig(**v) for k, v in {
    "registration": dict(registration_mm=4.0, registration_deg=3.0),
    "drift": dict(drift_mm=1.5, drift_deg=1.5, drift_length_m=0.015, drift_turn_deg=45.0),
    "noise": dict(noise_mm=0.2, noise_deg=0.3, jaw_noise_deg=0.5),
    "jaw": dict(jaw_offset_deg=5.0),
}.items()}


# ---------------------------------------------------------------- the config

def test_config_presets_overrides_and_bad_specs():
    assert arm_error_config("exact").exact and arm_error_config(None).exact
    dvrk = arm_error_config("dvrk")
    assert dvrk == ARM_ERRORS["dvrk"] and not dvrk.exact and dvrk.spec() == "dvrk"
    more = arm_error_config("dvrk:registration_mm=5, noise_mm=0.2")
    assert more.registration_mm == 5.0 and more.noise_mm == 0.2 and more.drift_mm == dvrk.drift_mm
    assert arm_error_config(more.spec()) == more                 # the canonical spec round-trips
    assert arm_error_config("dvrk:noise_mm=0.1").spec() == "dvrk"
    assert arm_error_config("exact:jaw_offset_deg=2").spec() == "exact:jaw_offset_deg=2"
    for bad, says in (("dvr", "unknown preset"), ("dvrk:noise=1", "not field=value"), ("dvrk:noise_mm", "not field=value"),
                      ("dvrk:noise_mm=x", "not a number"), ("dvrk:noise_mm=-1", "finite number >= 0"),
                      ("exact:drift_length_m=0", "> 0")):
        with pytest.raises(ValueError, match=says):
            arm_error_config(bad)


# ---------------------------------------------------------------- exact is today's behaviour

def test_exact_reports_the_script_with_no_truth_fields_as_before():
    plan = _plan("exact")
    assert plan.arm_errors == {}
    for k, fr in enumerate(plan.script.frames):
        got = {n: p.to_json() for n, p in frame_instruments(fr, plan.arm_errors, k).items()}
        before = {n: InstrumentPose(T.copy(), jaw, bool(h)).to_json() for n, (T, jaw, h) in fr.instruments.items()}
        assert got == before
        assert all("T_world_jaw_truth" not in v and "jaw_rad_truth" not in v for v in got.values())


def test_an_arm_error_leaves_the_rendered_take_as_it_was():
    """The scene (jaws where the script puts them), the needle, the endoscope and the image seed
    do not depend on the arm error: the pixels follow the truth."""
    a, b = _plan("exact"), _plan("dvrk")
    assert a.image_seed == b.image_seed and len(a) == len(b)
    assert all(np.array_equal(qa, qb) for qa, qb in zip(a.joints, b.joints))
    for fa, fb in zip(a.script.frames[::7], b.script.frames[::7]):
        sa, sb = take_spec(a, fa), take_spec(b, fb)
        assert np.array_equal(sa.T_world_needle, sb.T_world_needle) and sa.instruments == sb.instruments
        assert sa.appearance == sb.appearance and sa.thread_seed == sb.thread_seed


# ---------------------------------------------------------------- the parts of the error

def test_the_registration_is_one_rigid_transform_per_arm_and_take_within_its_bounds():
    cfg = ONLY["registration"]
    plan = _plan(cfg)
    for name in NAMES:
        T_reg = plan.arm_errors[name].T_reg
        reports = [(T, T @ E) for T, E, _ in _errors(plan, name)]
        for T, T_rep in reports:                                  # T_rep = T_reg @ T in every frame
            assert np.allclose(T_rep @ inv_T(T), T_reg, atol=1e-12)
        T0, T0_rep = reports[0]
        dt, da = pose_error(T0_rep, T0)                           # at the tool's first pose: the drawn sizes
        assert DRAW_LOW * 4e-3 - 1e-12 <= dt <= 4e-3 + 1e-12
        assert np.deg2rad(DRAW_LOW * 3.0) - 1e-12 <= da <= np.deg2rad(3.0) + 1e-12
    assert not np.allclose(plan.arm_errors["psm1"].T_reg, plan.arm_errors["psm2"].T_reg)
    other = _plan(cfg, take=1)
    assert not np.allclose(other.arm_errors["psm1"].T_reg, plan.arm_errors["psm1"].T_reg)


def test_the_configuration_part_is_bounded_smooth_and_drifts_as_the_arm_moves():
    cfg = ONLY["drift"]
    plan = _plan(cfg)
    moved = 0
    for name in NAMES:
        errs = _errors(plan, name)
        ts = np.array([E[:3, 3] for _, E, _ in errs])
        rs = np.array([R_to_rotvec(E[:3, :3]) for _, E, _ in errs])
        assert np.linalg.norm(ts, axis=1).max() <= 1.5e-3 and np.linalg.norm(rs, axis=1).max() <= np.deg2rad(1.5)
        for (T0, E0, _), (T1, E1, _) in zip(errs, errs[1:]):
            dp, dR = np.linalg.norm(T1[:3, 3] - T0[:3, 3]), np.abs(T1[:3, :3] - T0[:3, :3]).max()
            step_t, step_r = pose_error(E1, E0)
            if dp == 0 and dR == 0:                               # the arm still: the error still
                assert step_t == 0 and step_r == 0
            # smooth: a frame's change is small against the part's size, in proportion to the move
            assert step_t <= 1.5e-3 * 0.15 and step_r <= np.deg2rad(1.5) * 0.15
            assert step_t <= 1.5e-3 * 6 * (dp / 0.015 + dR / np.deg2rad(45)) + 1e-12
            assert step_r <= np.deg2rad(1.5) * 6 * (dp / 0.015 + dR / np.deg2rad(45)) + 1e-12
        span_t = np.ptp(ts, axis=0).max()
        moved += span_t > 0.2e-3                                  # it drifts over the take
    assert moved >= 1


def test_the_noise_is_per_frame_zero_mean_of_its_size_and_deterministic():
    cfg = ONLY["noise"]
    plan = _plan(cfg)
    d = np.array([np.concatenate([E[:3, 3] * 1e3, np.rad2deg(R_to_rotvec(E[:3, :3])), [np.rad2deg(j)]])
                  for name in NAMES for _, E, j in _errors(plan, name)])
    assert len(d) > 600
    for cols, sigma in (((0, 1, 2), 0.2), ((3, 4, 5), 0.3)):
        x = d[:, cols]
        assert abs(x.mean()) < 0.1 * sigma and 0.9 * sigma < x.std() < 1.1 * sigma
        lag1 = np.mean([np.corrcoef(x[1:, i], x[:-1, i])[0, 1] for i in range(3)])
        assert abs(lag1) < 0.1                                    # frame to frame: independent
    jaws = d[:, 6][np.abs(d[:, 6]) > 0]                            # (clipped at a closed jaw's 0)
    assert 0.35 < jaws.std() < 0.65
    again = _plan(cfg)
    assert all(np.array_equal(a[n].T_world_jaw, b[n].T_world_jaw) for a, b in zip(_reports(plan), _reports(again))
               for n in NAMES)


def test_the_jaw_offset_is_constant_per_arm_and_within_its_bound():
    plan = _plan(ONLY["jaw"])
    for name in NAMES:
        off = plan.arm_errors[name].jaw_offset_rad
        assert 0 < abs(off) <= np.deg2rad(5.0)
        for k, fr in enumerate(plan.script.frames):
            T, jaw, _ = fr.instruments[name]
            p = frame_instruments(fr, plan.arm_errors, k)[name]
            assert p.jaw_rad == pytest.approx(np.clip(jaw + off, 0.0, np.pi), abs=1e-15)
            assert np.array_equal(p.T_world_jaw, T) and p.T_world_jaw_truth is None   # the pose: exact
            assert (p.jaw_rad_truth is None) == (p.jaw_rad == jaw)


def test_the_dvrk_preset_errs_by_millimetres_and_degrees_and_writes_the_truth():
    plan = _plan("dvrk")
    for name in NAMES:
        e = []
        for k, fr in enumerate(plan.script.frames):
            T, jaw, holds = fr.instruments[name]
            p = frame_instruments(fr, plan.arm_errors, k)[name]
            assert np.array_equal(p.T_world_jaw_truth, T) and p.jaw_rad_truth == jaw and p.holds_needle == holds
            e.append(pose_error(p.T_world_jaw, T))
        e = np.array(e)
        assert 1e-3 < e[:, 0].mean() < 6.5e-3 and np.deg2rad(0.7) < e[:, 1].mean() < np.deg2rad(5.5)


# ---------------------------------------------------------------- the reader and the messages

def _frames(plan):
    return [parse_frame(Frame(index=k, stamp_ns=k, left=f"l{k}.png", right=f"r{k}.png", sequence=0, step=k,
                              T_world_needle=fr.T_world_needle, needle_at_rest=False,
                              instruments=frame_instruments(fr, plan.arm_errors, k)).to_json(), k + 1)
            for k, fr in enumerate(plan.script.frames)]


def test_the_reader_checks_a_held_needle_against_the_true_jaws_not_the_reported_ones():
    frames = _frames(_plan("dvrk"))
    held = [(a, b) for a, b in zip(frames, frames[1:]) for n in NAMES
            if a.instruments[n].holds_needle and b.instruments[n].holds_needle]
    assert len(held) > 30
    assert all(check_take(frames[0], a, b) == [] for a, b in zip(frames, frames[1:]))
    moved = 0
    for a, b in zip(frames, frames[1:]):
        for n in NAMES:
            if not (a.instruments[n].holds_needle and b.instruments[n].holds_needle):
                continue
            true = pose_error(T_jaw_needle(a.instruments[n], a.T_world_needle, truth=True),
                              T_jaw_needle(b.instruments[n], b.T_world_needle, truth=True))
            rep = pose_error(T_jaw_needle(a.instruments[n], a.T_world_needle),
                             T_jaw_needle(b.instruments[n], b.T_world_needle))
            assert true[0] < 1e-9 and true[1] < 1e-9                # rigid in the true jaws
            moved += rep[0] > GRASP_TOL_M or rep[1] > GRASP_TOL_RAD  # not in the reported ones
    assert moved > 0.9 * len(held)
    # the same folder without its truths (as if the report were exact) is refused
    bare = [replace(f, instruments={n: replace(p, T_world_jaw_truth=None) for n, p in f.instruments.items()})
            for f in frames]
    assert any(check_take(bare[0], a, b) for a, b in zip(bare, bare[1:]))


def test_instrument_state_carries_the_truth_and_checks_it():
    plan = _plan("dvrk")
    pose = frame_instruments(plan.script.frames[3], plan.arm_errors, 3)["psm1"]
    msg = decode(encode(InstrumentState.from_pose("psm1", pose, 3, 4)))
    assert np.array_equal(msg.T_world_jaw, pose.T_world_jaw) and np.array_equal(msg.T_world_jaw_truth, pose.T_world_jaw_truth)
    assert msg.jaw_rad_truth == pose.jaw_rad_truth and np.array_equal(msg.T_world_jaw_true, pose.T_world_jaw_truth)
    exact = decode(encode(InstrumentState.from_pose("psm1", InstrumentPose(np.eye(4), 0.2), 3, 4)))
    assert exact.T_world_jaw_truth is None and exact.jaw_rad_truth is None and np.array_equal(exact.T_world_jaw_true, np.eye(4))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(MessageError, match="T_world_jaw_truth"):
        decode(encode(InstrumentState("psm1", 3, 4, np.eye(4), 0.2, T_world_jaw_truth=bad)))
    with pytest.raises(MessageError, match="jaw_rad_truth"):
        decode(encode(InstrumentState("psm1", 3, 4, np.eye(4), 0.2, jaw_rad_truth=4.0)))


# ---------------------------------------------------------------- rendered

@pytest.mark.slow                 # renders a short take twice (a few seconds)
def test_generate_with_an_arm_error_renders_the_same_pixels_and_the_reader_accepts_it(tmp_path):
    import json

    from common.cli import dataset_main
    from common.data.dataset import Dataset
    args = ["--sequences", "1", "--motion", "handover", "--width", "160", "--height", "120", "--msaa", "0",
            "--seed", "7", "--randomise", "test", "--thread", "none", "--jobs", "1", "--quiet", "--take-every", "6"]
    assert dataset_main(["generate", "--out", str(tmp_path / "exact"), *args]) == 0
    assert dataset_main(["generate", "--out", str(tmp_path / "dvrk"), *args, "--arm-error", "dvrk"]) == 0
    assert dataset_main(["check", str(tmp_path / "dvrk")]) == 0
    a = [json.loads(ln) for ln in (tmp_path / "exact" / "frames.jsonl").read_text().splitlines()]
    b = [json.loads(ln) for ln in (tmp_path / "dvrk" / "frames.jsonl").read_text().splitlines()]
    assert len(a) == len(b) > 5
    for fa, fb in zip(a, b):
        for k in ("keypoints", "visible", "bbox", "arc_visible", "T_world_needle", "T_world_ecm"):
            assert fa[k] == fb[k], k
        for c in ("left", "right"):
            assert (tmp_path / "exact" / fa[c]).read_bytes() == (tmp_path / "dvrk" / fb[c]).read_bytes()
        for n in NAMES:
            assert fb["instruments"][n]["T_world_jaw_truth"] == fa["instruments"][n]["T_world_jaw"]
            assert fb["instruments"][n]["T_world_jaw"] != fa["instruments"][n]["T_world_jaw"]
    ds = Dataset(tmp_path / "dvrk")
    assert ds[0].instruments["psm1"].T_world_jaw_truth is not None
    assert "arm_error=dvrk" in ds.meta.source
    assert dataset_main(["generate", "--out", str(tmp_path / "bad"), "--sequences", "1", "--arm-error", "dvrk",
                         "--quiet"]) == 1                # a multi-view folder states no instruments
