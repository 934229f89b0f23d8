"""Scene randomisation (no rendering) and dataset generation: determinism, resume, CLI."""
import json

import numpy as np
import pytest

import common.sim.render  # noqa: F401  (headless GL before mujoco)
from common.cli import dataset_main
from common.data.check import check_dataset
from common.data.dataset import Dataset
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import transform_points
from common.sim.generate import GenerateConfig, generate
from common.sim.randomise import (
    DISTANCE_RANGE_M,
    MULTIVIEW_STEP_RAD,
    PRESETS,
    default_arm,
    keypoints_in_view,
    plan_sequence,
    rotate_with_keypoints,
    sample_appearance,
)
from common.sim.scene_meshes import PHANTOM_SIZE, needle_mesh, phantom_height


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_planned_sequences_are_physical_and_in_view(preset):
    rig, needle, arm = StereoRig.default(), NeedleModel(), default_arm()
    held_seen = rest_seen = 0
    for s in range(25):
        plan = plan_sequence(3, s, 5, PRESETS[preset], rig, needle, arm)
        T = plan.spec.T_world_needle
        wire_r = plan.spec.appearance.wire_diameter_m / 2
        arc = transform_points(T, needle.sample_arc(64))
        assert np.all(np.abs(arc[:, 0]) < PHANTOM_SIZE[0] / 2) and np.all(np.abs(arc[:, 1]) < PHANTOM_SIZE[1] / 2)
        gap = arc[:, 2] - phantom_height(arc[:, 0], arc[:, 1])
        assert gap.min() >= wire_r - 2e-6, "the needle sinks into the tissue"
        if gap.min() < wire_r + 2e-6:
            rest_seen += 1  # resting: touching the surface
        else:
            held_seen += 1
            assert gap.min() <= 0.025 + wire_r + 1e-6
        centre = transform_points(T, needle.keypoints()).mean(axis=0)
        T0 = arm.T_world_ecm(plan.joints[0])
        d = np.linalg.norm(centre - T0[:3, 3])
        assert DISTANCE_RANGE_M[0] - 1e-6 <= d <= DISTANCE_RANGE_M[1] + 1e-6
        assert keypoints_in_view(rig, needle, T, T0, margin=0.1)
        assert len(plan.joints) == 5
        for qa, qb in zip(plan.joints, plan.joints[1:]):
            dq = np.abs(qb - qa)
            assert np.sum(dq > 1e-12) == 1 and np.isclose(dq.max(), MULTIVIEW_STEP_RAD)
            assert dq[2] == 0  # insertion never moves
    assert rest_seen > 0
    if PRESETS[preset].p_held > 0:
        assert held_seen > 0


def test_a_small_step_makes_a_video_of_the_same_scene():
    rig, needle, arm = StereoRig.default(), NeedleModel(), default_arm()
    base = plan_sequence(5, 2, 30, PRESETS["test"], rig, needle, arm)
    video = plan_sequence(5, 2, 30, PRESETS["test"], rig, needle, arm, step_rad=0.003)
    assert np.allclose(video.spec.T_world_needle, base.spec.T_world_needle)
    assert np.allclose(video.joints[0], base.joints[0])
    for qa, qb in zip(video.joints, video.joints[1:]):
        dq = np.abs(qb - qa)
        assert np.sum(dq > 1e-12) == 1 and np.isclose(dq.max(), 0.003)
    with pytest.raises(ValueError, match="step-rad"):
        generate("/nonexistent/never-made", GenerateConfig(1, 2, step_rad=-0.1), jobs=1, progress=False)


def test_rotate_with_keypoints_maps_pixels_along():
    img = np.zeros((90, 160, 3), np.uint8)
    img[30, 100] = 255
    out, uv = rotate_with_keypoints(img, [[100, 30]], 0.4)
    v, u = np.unravel_index(np.argmax(out[..., 0]), out.shape[:2])
    assert np.hypot(u - uv[0, 0], v - uv[0, 1]) < 1.0


def _lines(folder):
    return (folder / "frames.jsonl").read_text().splitlines()


@pytest.mark.slow
def test_generate_is_deterministic_resumable_and_parallel(tmp_path):
    cfg = GenerateConfig(sequences=2, steps=2, seed=5, randomise="train", width=320, height=180)
    a, b = tmp_path / "a", tmp_path / "b"
    assert generate(str(a), cfg, jobs=1, progress=False) == 4
    # interrupted run: one sequence done, a torn line after it; then the full command again
    assert generate(str(b), GenerateConfig(1, 2, 5, "train", 320, 180), jobs=1, progress=False) == 2
    with open(b / "frames.jsonl", "a") as f:
        f.write('{"index": 2, "stamp_ns": 6666')
    assert generate(str(b), cfg, jobs=2, progress=False) == 4  # resumes with 2 processes
    assert _lines(a) == _lines(b)
    for i in range(4):
        for cam in ("left", "right"):
            pa = a / "images" / cam / f"{i:06d}.jpg"
            pb = b / "images" / cam / f"{i:06d}.jpg"
            assert pa.read_bytes() == pb.read_bytes()
    ds = Dataset(a)
    rep = check_dataset(ds)
    assert rep.ok, rep.errors
    assert rep.with_truth == 4 and rep.max_reproj_px < 1e-6
    assert [(f.sequence, f.step) for f in ds] == [(0, 0), (0, 1), (1, 0), (1, 1)]
    # other settings in the same folder are refused
    with pytest.raises(ValueError):
        generate(str(a), GenerateConfig(2, 3, 5, "train", 320, 180), jobs=1, progress=False)


def test_dataset_cli_generate_check_show(tmp_path, capsys):
    out = tmp_path / "d"
    assert dataset_main(["generate", "--out", str(out), "--sequences", "1", "--steps", "2", "--width", "320",
                         "--height", "180", "--randomise", "none", "--format", "png", "--jobs", "1", "--quiet"]) == 0
    assert dataset_main(["check", str(out)]) == 0
    assert "OK" in capsys.readouterr().out
    sheet = tmp_path / "sheet.png"
    assert dataset_main(["show", str(out), "--out", str(sheet), "--frames", "2"]) == 0
    import cv2
    img = cv2.imread(str(sheet))
    assert img is not None and img.shape[0] > 100
    # a broken ground truth fails the check with the line named
    lines = _lines(out)
    obj = json.loads(lines[1])
    obj["T_world_needle"][2][3] += 0.002
    lines[1] = json.dumps(obj)
    (out / "frames.jsonl").write_text("\n".join(lines) + "\n")
    assert dataset_main(["check", str(out), "--no-images"]) == 1
    text = capsys.readouterr().out
    assert "frames.jsonl:2: keypoints" in text and "FAILED" in text
    # an unreadable folder is an error, not a traceback
    assert dataset_main(["check", str(tmp_path / "nope")]) == 1


@pytest.mark.slow
def test_needle_free_frames_see_no_needle(tmp_path):
    from common.sim.generate import generate_needle_free
    folder = generate_needle_free(tmp_path / "neg", 1, seed=3, preset="train", progress=False)
    ds = Dataset(folder)
    rep = check_dataset(ds)
    assert rep.ok, rep.errors
    (frame,) = list(ds)
    assert all(not frame.visible[c].any() and frame.bbox[c] is None for c in ("left", "right"))


@pytest.mark.slow
def test_needle_free_frames_can_lay_the_pale_thread_on_purpose(tmp_path, monkeypatch):
    from common.sim import render as sim_render
    from common.sim.generate import generate_needle_free
    from common.sim.randomise import PALE_THREAD_RGB
    colours, load = [], sim_render.SceneRenderer.load

    def spy(self, spec, *a, **kw):
        colours.append(tuple(spec.appearance.thread_rgb))
        return load(self, spec, *a, **kw)

    monkeypatch.setattr(sim_render.SceneRenderer, "load", spy)
    for share in (1.0, 0.0):
        generate_needle_free(tmp_path / f"neg{share}", 2, seed=3, preset="train", progress=False,
                             pale_thread=share)
    assert colours[:2] == [PALE_THREAD_RGB] * 2
    assert all(c != PALE_THREAD_RGB for c in colours[2:]) and len(colours) == 4


def test_the_wide_preset_adds_looks_and_leaves_the_others_draws_alone():
    train, wide = PRESETS["train"], PRESETS["wide"]
    tissue_hues, flat, tips = set(), 0, []
    for seed in range(60):
        a = sample_appearance(np.random.default_rng(seed), train)
        b = sample_appearance(np.random.default_rng(seed), wide)
        assert a.wire_diameter_m == b.wire_diameter_m and a.texture_seed == b.texture_seed
        assert (a.tip_length_m, a.swage_scale) == (0.0018, 1.08)     # train keeps the one needle
        tips.append(b.tip_length_m)
        flat += b.ambient >= 0.35
        r, g, bl = b.tissue_rgb
        tissue_hues.add("yellowish" if g > 0.6 and bl < 0.55 else "purple" if bl > g and bl > 0.4 * r else "red")
    assert min(tips) < 0.0012 and max(tips) > 0.0035
    assert 8 <= flat <= 35
    assert tissue_hues == {"yellowish", "purple", "red"}


def test_needle_meshes_of_any_taper_fit_the_compiled_slots():
    needle = NeedleModel()
    n = len(needle_mesh(needle, 0.0008)[0])
    for tip, expo, swage in [(0.0006, 0.5, 1.0), (0.0045, 1.2, 1.35)]:
        v, _, _ = needle_mesh(needle, 0.0008, tip, tip_exponent=expo, swage_scale=swage)
        assert len(v) == n


def test_the_cli_offers_every_preset():
    from common.sim.cli import PRESET_NAMES
    assert sorted(PRESET_NAMES) == sorted(PRESETS)
