"""The ``random`` looks and the held-out ``unseen`` family: seeded and reproducible, the other
presets' draws untouched, the held-out pool disjoint from the training pool, the image effects
clear of the needle, needle-free frames without a needle."""
import dataclasses
import hashlib
from dataclasses import replace

import numpy as np
import pytest

import common.sim.render  # noqa: F401  (headless GL before mujoco)
from common.data.dataset import Dataset
from common.geometry.camera import StereoRig
from common.sim import random_looks
from common.sim.generate import generate_needle_free, needle_free_scene, scene_meta
from common.sim.image_effects import draw_effects, look_effects
from common.sim.instrument_kinds import GRASPING, KINDS, kind_parts
from common.sim.look_textures import PATTERNS, PHOTOS, TextureLook, look_texture, photos_available
from common.sim.random_looks import POOLS
from common.sim.randomise import PRESETS, degrade_stereo, get_preset, plan_sequence
from common.sim.render import LABELS, SceneRenderer
from common.sim.scene import build_mjcf
from common.sim.takes import plan_take

META = scene_meta(320, 240, "")

# Fingerprints of what the presets that existed before the random looks draw (appearance, poses,
# instruments, seeds, joints, MJCF, the draws of the sensor model, a take's appearance), taken
# from the code before the random looks were added (f784231): existing seeds must give the same
# datasets. Computed poses and joints are hashed rounded to 1e-9 (m, rad): their last bits follow
# the machine's numpy/BLAS/MuJoCo build, which the first fingerprints (raw bytes) did not survive.
BEFORE_RANDOM_LOOKS = {"none": "32c1e44ef07ce404", "test": "83386763b087a3a0", "train": "83b8411bb4fac67e",
                       "wide": "45703cdf014641ea", "silicone": "20cb26ea6632cc63", "liver": "3c87a2feed6ecdd5"}


def _rounded(a) -> bytes:
    return (np.round(np.asarray(a, float), 9) + 0.0).tobytes()   # + 0.0: no negative zeros


def _rounded_repr(v) -> str:
    """repr with every float rounded to 1e-9 (tuples and lists walked)."""
    if isinstance(v, (tuple, list)):
        return "(" + ",".join(_rounded_repr(x) for x in v) + ")"
    if isinstance(v, (float, np.floating)):
        return repr(round(float(v), 9) + 0.0)
    return repr(v)


def _fingerprint(name: str, seed: int = 5) -> str:
    h = hashlib.sha256()
    preset = get_preset(name)
    for s in range(3):
        plan = plan_sequence(seed, s, 2, preset, META.rig, META.needle, META.arm, 256, 0)
        sp = plan.spec
        assert sp.appearance.look is None
        h.update(repr({k: v for k, v in dataclasses.asdict(sp.appearance).items() if k != "look"}).encode())
        h.update(_rounded(sp.T_world_needle))
        h.update(_rounded_repr([dataclasses.astuple(i) for i in sp.instruments]).encode())
        h.update(repr((sp.thread_seed, plan.image_seed)).encode())
        for q in plan.joints:
            h.update(_rounded(q))
        h.update(build_mjcf(sp).encode())
    rng = np.random.default_rng(3)
    img = np.random.default_rng(1).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    degrade_stereo({"left": img, "right": img.copy()}, rng, preset, jpeg=False)
    h.update(rng.random(4).tobytes())         # what the sensor model drew
    tp = plan_take(seed, 1, "pickup", preset, META.rig, META.needle, META.arm, 256, 0)
    h.update(repr({k: v for k, v in dataclasses.asdict(tp.spec.appearance).items() if k != "look"}).encode())
    return h.hexdigest()[:16]


@pytest.mark.parametrize("name", sorted(BEFORE_RANDOM_LOOKS))
def test_the_other_presets_draw_what_they_drew_before(name):
    assert _fingerprint(name) == BEFORE_RANDOM_LOOKS[name]


def test_pools_split_every_texture_photo_and_instrument_kind():
    train, unseen = POOLS["train"], POOLS["unseen"]
    for key, every in (("patterns", PATTERNS), ("photos", PHOTOS), ("instruments", KINDS)):
        assert not set(train[key]) & set(unseen[key]), key
        assert set(train[key]) | set(unseen[key]) == set(every), key
        assert train[key] and unseen[key]
    # either pool has a kind that can hold the needle
    assert set(train["instruments"]) & set(GRASPING) and set(unseen["instruments"]) & set(GRASPING)


def _uses(plan) -> tuple[set, set]:
    look = plan.spec.appearance.look
    textures = {look.tissue.kind, look.table.kind}
    return ({t.removeprefix("photo:") for t in textures},
            {il.kind for il in look.instruments[:len(plan.spec.instruments)]})


@pytest.mark.parametrize("preset,pool", [("random", "train"), ("unseen", "unseen")])
def test_each_preset_uses_only_its_pool(preset, pool):
    textures, kinds = set(), set()
    for s in range(40):
        t, k = _uses(plan_sequence(11, s, 1, PRESETS[preset], META.rig, META.needle, META.arm, 256, 0))
        textures |= t
        kinds |= k
    allowed = set(POOLS[pool]["patterns"]) | set(POOLS[pool]["photos"])
    assert textures <= allowed and kinds <= set(POOLS[pool]["instruments"])
    assert set(POOLS[pool]["patterns"]) <= textures and kinds == set(POOLS[pool]["instruments"])
    if photos_available():
        assert textures & set(POOLS[pool]["photos"])


def test_random_looks_are_seeded_and_vary():
    p = PRESETS["random"]
    a = plan_sequence(4, 2, 2, p, META.rig, META.needle, META.arm, 256, 0)
    b = plan_sequence(4, 2, 2, p, META.rig, META.needle, META.arm, 256, 0)
    c = plan_sequence(4, 3, 2, p, META.rig, META.needle, META.arm, 256, 0)
    assert a.spec.appearance == b.spec.appearance and a.spec.appearance.look is not None
    assert [dataclasses.astuple(i) for i in a.spec.instruments] == [dataclasses.astuple(i) for i in b.spec.instruments]
    assert a.spec.appearance.look != c.spec.appearance.look
    t = a.spec.appearance.look.tissue
    assert np.array_equal(look_texture(t, 128), look_texture(t, 128))
    # across sequences: every light count, dark coated and bright needles, threads and none
    aps = [plan_sequence(4, s, 1, p, META.rig, META.needle, META.arm, 256, 0).spec.appearance for s in range(40)]
    assert {len(ap.look.lights) for ap in aps} == {1, 2, 3, 4}
    v = [np.mean(ap.needle_rgb) for ap in aps]
    assert min(v) < 0.3 and max(v) > 0.7
    assert any(not ap.thread_visible for ap in aps) and sum(ap.thread_visible for ap in aps) > 20


def test_random_images_are_reproducible_and_render_every_kind():
    cfg_spec = plan_sequence(9, 0, 1, PRESETS["random"], META.rig, META.needle, META.arm, 256, 0).spec
    r = SceneRenderer(full_segmentation=True)
    shots = []
    for kind in KINDS:   # every kind's parts render as instrument pixels in front of the camera
        look = cfg_spec.appearance.look
        look = replace(look, instruments=tuple(replace(il, kind=kind) for il in look.instruments))
        spec = replace(cfg_spec, appearance=replace(cfg_spec.appearance, look=look))
        r.load(spec)
        out = r.render(META.arm.T_world_ecm(np.zeros(4)))
        shots.append(out["left"].bgr)
        assert np.isin(np.unique(out["left"].label), list(LABELS.values())).all()
        assert len(kind_parts(kind, 0.004)[0]) > 0
    r.load(cfg_spec)
    T = META.arm.T_world_ecm(plan_sequence(9, 0, 1, PRESETS["random"], META.rig, META.needle, META.arm).joints[0])
    first = r.render(T)["left"].bgr
    again = r.render(T)["left"].bgr
    assert np.array_equal(first, again)


def test_image_effects_keep_clear_of_the_needle():
    h, w = 270, 480
    kp = {"left": np.array([[100.0, 100], [140, 90], [180, 100], [200, 130], [205, 170]])}
    drawn = 0
    for seed in range(60):
        fx = draw_effects(np.random.default_rng(seed), h, w, kp, p_streaks=1.0)
        pts = np.round(np.vstack([kp["left"], 0.5 * (kp["left"][1:] + kp["left"][:-1])])).astype(int)
        if fx.streaks is not None:
            drawn += int(fx.streaks.any())
            assert not fx.streaks[pts[:, 1], pts[:, 0]].any()
        if fx.blobs is not None:
            low = fx.blobs[pts[:, 1] // 8, pts[:, 0] // 8]
            assert low.max() < 0.05
    assert drawn > 30
    img = np.full((h, w, 3), 120, np.uint8)
    a = look_effects({"left": img, "right": img}, np.random.default_rng(1), kp)
    b = look_effects({"left": img, "right": img}, np.random.default_rng(1), kp)
    assert np.array_equal(a["left"], b["left"]) and np.array_equal(a["left"], a["right"])


def test_without_scikit_image_the_looks_use_patterns_only(monkeypatch):
    monkeypatch.setattr(random_looks, "photos_available", lambda: False)
    for s in range(30):
        plan = plan_sequence(2, s, 1, PRESETS["random"], META.rig, META.needle, META.arm, 256, 0)
        look = plan.spec.appearance.look
        assert not look.tissue.kind.startswith("photo:") and not look.table.kind.startswith("photo:")


def test_photographs_become_textures():
    pytest.importorskip("skimage")
    for name in ("immunohistochemistry", "brick"):
        t = TextureLook(f"photo:{name}", 1, ((0.2, 0, 0), (0.7, 0.3, 0.3), (1, 0.9, 0.9)), photo_hue=True, hue_turn=0.3)
        img = look_texture(t, 256)
        assert img.shape == (256, 256, 3) and img.std() > 10


def test_hard_negatives_have_no_needle_and_every_instrument_kind(tmp_path):
    pre = replace(PRESETS["random"], p_near=0.6, p_streaks=0.8, near_over_needle=True)
    kinds, near = set(), 0
    small = StereoRig.default(320, 180)
    r = SceneRenderer(full_segmentation=True)
    for i in range(24):
        spec, T_world_ecm = needle_free_scene(21, i, pre, META)
        look = spec.appearance.look
        kinds |= {il.kind for il in look.instruments[:len(spec.instruments)]}
        cam = T_world_ecm @ META.rig["left"].T_ecm_cam
        near += any(np.linalg.norm(np.asarray(ins.tip) - cam[:3, 3]) < 0.07 for ins in spec.instruments)
        if i < 3:
            r.load(replace(spec, rig=small, texture_size=256))
            out = r.render(T_world_ecm)
            for c in out.values():
                assert not (c.label == LABELS["needle"]).any()
    assert kinds == set(POOLS["train"]["instruments"])
    assert near >= 8
    folder = tmp_path / "neg"
    generate_needle_free(folder, 2, 21, "random", progress=False, width=320, height=240)
    ds = Dataset(str(folder))
    assert len(ds) == 2
    for fr in ds:
        assert not any(v.any() for v in fr.visible.values()) and all(b is None for b in fr.bbox.values())
        assert 2 <= len(fr.instruments) <= 4
        assert ds.image(fr, "left").shape == (240, 320, 3)
