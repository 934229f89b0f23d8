"""The second renderer (common/sim/alt_render.py, common/sim/alt_generate.py): rasteriser exactness,
ground truth on the rendered needle, spec-conforming folders. Small images: fast."""
import json
import subprocess
import sys

import numpy as np
import pytest

from common.cli import dataset_main
from common.data.check import check_dataset
from common.data.dataset import Dataset
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T, make_T, rotvec_to_R, transform_points
from common.sim.alt_generate import (
    DISTANCE_RANGE_M,
    MULTIVIEW_STEP_RAD,
    aim_joints,
    alt_arm,
    plan_alt_sequence,
    view_direction,
)
from common.sim.alt_meshes import LABELS, Material, NeedleShape, box_mesh, needle_mesh
from common.sim.alt_raster import rasterise
from common.sim.alt_render import AltRenderer, AltScene
from common.sim.alt_tissue import Tissue, make_tissue_textures

METAL = Material((0.6, 0.6, 0.62), 0.4, 0.8, 60.0, env=0.5)


# ---------------------------------------------------------------- rasteriser

def _inside(P, x, y):
    """Signed distances (px) of point (x, y) to the three edges of 2D triangle P, positive inside."""
    out = []
    (x1, y1), (x2, y2) = P[1] - P[0], P[2] - P[0]
    area = x1 * y2 - y1 * x2
    for i in range(3):
        a, b = P[i], P[(i + 1) % 3]
        e = b - a
        out.append(np.sign(area) * (e[0] * (y - a[1]) - e[1] * (x - a[0])) / np.linalg.norm(e))
    return np.array(out)


@pytest.mark.slow
def test_rasterise_covers_exactly_the_pixel_centres_inside_with_exact_depth():
    K = np.array([[300.0, 0, 79.5], [0, 300.0, 59.5], [0, 0, 1]])
    # a slanted triangle: depth varies over it, so affine depth interpolation would be wrong
    V = np.array([[-0.02, -0.015, 0.10], [0.025, -0.01, 0.16], [-0.005, 0.02, 0.12]])
    face, depth, bary = rasterise(V, np.array([[0, 1, 2]]), K, 160, 120)
    uv = (V[:, :2] / V[:, 2:]) @ K[:2, :2].T + K[:2, 2]
    n_plane = np.cross(V[1] - V[0], V[2] - V[0])
    Ki = np.linalg.inv(K)
    checked = 0
    for y in range(120):
        for x in range(160):
            d = _inside(uv, x, y)
            if np.all(d > 1e-6):
                assert face[y, x] == 0, (x, y)
                ray = Ki @ [x, y, 1.0]
                z = (n_plane @ V[0]) / (n_plane @ ray)        # exact ray-plane depth
                assert abs(depth[y, x] - z) < 1e-6 * z
                p = ray * z                                   # barycentrics reproduce the 3D point
                assert np.allclose(bary[y, x] @ V, p, atol=1e-7)
                checked += 1
            elif np.any(d < -1e-6):
                assert face[y, x] == -1, (x, y)
    assert checked > 500


def test_zbuffer_keeps_the_nearest_surface_in_any_order():
    K = np.array([[200.0, 0, 49.5], [0, 200.0, 49.5], [0, 0, 1]])
    big = np.array([[-0.1, -0.1], [0.1, -0.1], [0.0, 0.1]])
    near = np.c_[big * 0.5, np.full(3, 0.2)]
    far = np.c_[big, np.full(3, 0.3)]
    for V, F, near_face in ((np.r_[near, far], [[0, 1, 2], [3, 4, 5]], 0), (np.r_[far, near], [[0, 1, 2], [3, 4, 5]], 1)):
        face, depth, _ = rasterise(V, np.array(F), K, 100, 100)
        assert face[50, 50] == near_face and abs(depth[50, 50] - 0.2) < 1e-9
    # a nearer depth already in the buffer (e.g. tissue) hides both
    face, depth, _ = rasterise(np.r_[near, far], np.array([[0, 1, 2], [3, 4, 5]]), K, 100, 100,
                               depth=np.full((100, 100), 0.1, np.float32))
    assert np.all(face == -1) and np.allclose(depth, 0.1)


# ---------------------------------------------------------------- the needle mesh

@pytest.mark.parametrize("tail", ["dome", "chamfer"])
def test_needle_mesh_follows_the_model_arc_tip_at_A_tail_at_E(tail):
    needle = NeedleModel()
    shape = NeedleShape(tail=tail, n_ring=7, n_arc=50)
    m = needle_mesh(needle, shape, METAL)
    A, E = needle.keypoints()[0], needle.keypoints()[4]
    # every vertex within the (swaged, flattened) wire radius of the arc's circle
    rho = np.hypot(m.V[:, 0], m.V[:, 1])
    off = np.hypot(rho - needle.radius_m, m.V[:, 2])
    assert off.max() <= shape.max_radius_m * 1.0001
    ang = np.degrees(np.arctan2(m.V[:, 1], m.V[:, 0]))
    assert ang.min() >= 30 - 1e-6 and ang.max() <= 150 + 1e-6     # nothing beyond A or E
    assert np.linalg.norm(m.V - A, axis=1).min() < 1e-12          # the sharp point is A
    assert np.linalg.norm(m.V - E, axis=1).min() < 1e-12          # the dome's end / the cap's centre is E
    # the outward normals point away from the centreline
    nearest = needle.arc_points(np.radians(np.clip(ang, 30, 150)))
    assert np.mean(np.sum(m.N * (m.V - nearest), axis=1) >= 0) > 0.97


# ---------------------------------------------------------------- scenes and ground truth

def _flat_tissue():
    alb, det = make_tissue_textures(np.random.default_rng(0), (0.5, 0.15, 0.13), size=64, detail_size=64)
    return Tissue(np.zeros((1, 4)), alb, 0.5, det, 0.02, np.zeros((0, 4)))


def _scene(T_world_needle, shape=NeedleShape(), extra=()):
    needle = NeedleModel()
    meshes = [needle_mesh(needle, shape, METAL).transformed(T_world_needle), *extra]
    return AltScene(needle=needle, needle_shape=shape, T_world_needle=T_world_needle, tissue=_flat_tissue(),
                    meshes=meshes, noise_sigma=0.0, blur_sigma_px=0.0)


def _looking_down(distance, roll=0.0):
    """T_world_ecm looking straight down at the origin from ``distance``, image right = world +x."""
    return make_T(rotvec_to_R([0, 0, roll]), [0, 0, distance])     # the cameras look along -z_ecm


@pytest.mark.slow
def test_ground_truth_keypoints_lie_on_the_rendered_needle():
    """Data as written (the spec's rig, 640x360): every visible keypoint on the needle's pixels,
    and the needle's pixels around the projected arc, in both cameras."""
    rig = StereoRig.default(640, 360)
    needle, arm = NeedleModel(), alt_arm()
    renderer = AltRenderer(rig)
    checked = 0
    for s in range(4):
        plan = plan_alt_sequence(11, s, 2, rig, needle, arm)
        for q in plan.joints:
            T = arm.T_world_ecm(q)
            renders = renderer.render(plan.scene, T)
            gt = renderer.ground_truth(plan.scene, T, renders)
            for cam in ("left", "right"):
                lab = renders[cam].label
                assert renders[cam].bgr.shape == (360, 640, 3) and renders[cam].bgr.dtype == np.uint8
                for k in range(5):
                    if gt["visible"][cam][k]:
                        u, v = np.round(gt["keypoints"][cam][k]).astype(int)
                        win = lab[max(v - 2, 0):v + 3, max(u - 2, 0):u + 3]
                        assert np.any(win == LABELS["needle"]), f"seq {s} {cam}: {'ABCDE'[k]} not on the needle"
                        checked += 1
                ys, xs = np.nonzero(lab == LABELS["needle"])
                assert len(xs) > 0
                assert gt["bbox"][cam] == [xs.min() - 0.5, ys.min() - 0.5, xs.max() + 0.5, ys.max() + 0.5]
                arc = rig[cam].project_from_ecm(transform_points(inv_T(T) @ plan.scene.T_world_needle,
                                                                 needle.sample_arc(400)))
                dist = np.min(np.linalg.norm(np.stack([xs, ys], 1)[:, None] - arc[None], axis=2), axis=1)
                width_px = plan.scene.needle_shape.max_radius_m * rig[cam].K[0, 0] / 0.1
                assert dist.max() <= width_px + 1.0, f"seq {s} {cam}: needle pixel {dist.max():.2f} px off the arc"
    assert checked >= 60


def test_tip_is_the_sharp_end():
    """Close up (a narrow field of view, the same rasteriser): the mask is thinner at A than at C
    and at E, for either tail and a short or a long taper."""
    rig = StereoRig.default(640, 360, fovy_rad=0.35)
    renderer = AltRenderer(rig, supersample=1)
    T_world_needle = make_T(rotvec_to_R([0, 0, 0.4]), [0, 0, 0.0008])
    T_world_ecm = _looking_down(0.12)
    for tail, tip in (("dome", 0.0009), ("chamfer", 0.003)):
        scene = _scene(T_world_needle, NeedleShape(tail=tail, tip_length_m=tip))
        renders = renderer.render(scene, T_world_ecm)
        gt = renderer.ground_truth(scene, T_world_ecm, renders)
        for cam in ("left", "right"):
            assert gt["visible"][cam].all()
            ys, xs = np.nonzero(renders[cam].label == LABELS["needle"])
            pix = np.stack([xs, ys], 1)
            uv = gt["keypoints"][cam]
            wire_px = 0.0008 * rig[cam].K[0, 0] / 0.12
            near = [int(np.sum(np.linalg.norm(pix - uv[k], axis=1) < 1.5 * wire_px)) for k in range(5)]
            assert near[0] < 0.8 * near[2] and near[0] < 0.8 * near[4], (tail, tip, cam, near)


def test_an_occluder_hides_a_keypoint():
    """A plate held 5 mm above keypoint C: C is not visible, the others are; the needle's box
    shrinks to the pixels left visible."""
    rig = StereoRig.default(640, 360)
    renderer = AltRenderer(rig)
    needle = NeedleModel()
    T_world_needle = make_T(np.eye(3), [0, 0, 0.0006])
    T_world_ecm = _looking_down(0.12)
    C = transform_points(T_world_needle, needle.keypoints())[2]
    c = C + [0, 0, 0.005]
    half = 0.0012
    corners = np.array([[c[0] - half, c[1] - half, c[2]], [c[0] + half, c[1] - half, c[2]],
                        [c[0] + half, c[1] + half, c[2]], [c[0] - half, c[1] + half, c[2]]])
    plate = box_mesh(np.r_[corners, corners + [0, 0, 0.001]], LABELS["instrument"], Material((0.1, 0.1, 0.1)))
    gt_free = renderer.ground_truth(_scene(T_world_needle), T_world_ecm,
                                    renderer.render(_scene(T_world_needle), T_world_ecm))
    scene = _scene(T_world_needle, extra=[plate])
    renders = renderer.render(scene, T_world_ecm)
    gt = renderer.ground_truth(scene, T_world_ecm, renders)
    for cam in ("left", "right"):
        assert gt_free["visible"][cam].all()
        assert gt["visible"][cam].tolist() == [True, True, False, True, True]
        u, v = np.round(gt["keypoints"][cam][2]).astype(int)
        assert renders[cam].label[v, u] == LABELS["instrument"]


def test_a_tip_dipped_into_the_tissue_is_hidden_the_rest_seen():
    """The needle tilted about B so that its sharp tip A lies 0.2 mm inside the (flat) tissue, less
    than the 1.5 wire radii the rule used to let through: A hidden in both cameras, B..E seen."""
    rig = StereoRig.default(640, 360)
    renderer = AltRenderer(rig)
    needle = NeedleModel()
    T0 = make_T(np.eye(3), [0, 0, 0.0006])
    A0, B = transform_points(T0, needle.keypoints()[:2])
    v = A0 - B
    tilt = np.arcsin(0.0008 / np.linalg.norm(v[:2]))                 # A from 0.6 mm above to 0.2 mm under
    R = rotvec_to_R(np.cross([0.0, 0.0, 1.0], v) / np.linalg.norm(v[:2]) * tilt)
    T_world_needle = make_T(R, B - R @ B) @ T0
    P = transform_points(T_world_needle, needle.keypoints())
    assert P[0, 2] == pytest.approx(-0.0002, abs=1e-9) and np.all(P[1:, 2] >= 0.0006 - 1e-12)
    for T_world_ecm in (_looking_down(0.12), _looking_down(0.1, roll=1.0)):
        scene = _scene(T_world_needle)
        gt = renderer.ground_truth(scene, T_world_ecm, renderer.render(scene, T_world_ecm))
        for cam in ("left", "right"):
            assert gt["visible"][cam].tolist() == [False, True, True, True, True], cam


def test_one_renderer_follows_each_scene_it_is_given():
    rig = StereoRig.default(320, 180)
    T_world_ecm = _looking_down(0.12)
    scenes = [_scene(make_T(rotvec_to_R([0, 0, a]), [0.004 * a, 0, 0.0006])) for a in (0.0, 2.0)]
    shared = AltRenderer(rig)
    for sc in scenes + scenes[::-1]:
        got = shared.render(sc, T_world_ecm)["left"]
        want = AltRenderer(rig).render(sc, T_world_ecm)["left"]
        assert np.array_equal(got.label, want.label) and np.array_equal(got.bgr, want.bgr)


def test_aim_joints_points_the_scope_at_the_target():
    arm = alt_arm()
    rng = np.random.default_rng(5)
    for _ in range(20):
        target = np.append(rng.uniform(-0.05, 0.05, 2), rng.uniform(0, 0.02))
        d = rng.uniform(*DISTANCE_RANGE_M)
        q = aim_joints(arm, target, rng.uniform(-0.5, 0.5), d)
        o = arm.T_world_ecm(q)[:3, 3]
        assert np.linalg.norm(target - o) == pytest.approx(d, abs=1e-9)
        assert np.allclose((target - o) / d, view_direction(arm, q), atol=1e-9)


FIRST_RENDERER = ("common.sim.scene", "common.sim.scene_meshes", "common.sim.scene_textures", "common.sim.render",
                  "common.sim.randomise", "common.sim.generate", "common.sim.live", "common.sim.scene_looks",
                  "common.sim.look_textures", "common.sim.instrument_kinds", "common.sim.random_looks",
                  "common.sim.image_effects")


def test_renderer_shares_no_code_with_the_first():
    """The second renderer (and generate-alt's command) imports neither MuJoCo nor any module of
    the first renderer, in a fresh interpreter; and the check can fail (the first renderer's live
    frames do import them)."""
    def imported(module: str) -> list:
        code = (f"import sys, {module}; "
                f"print(' '.join(m for m in sys.modules if m == 'mujoco' or m in {FIRST_RENDERER!r}))")
        out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True,
                             cwd=str(__import__("pathlib").Path(__file__).parents[2]))
        return out.stdout.split()
    assert imported("common.sim.alt_generate") == []
    assert imported("common.sim.cli") == []
    assert "common.sim.render" in imported("common.sim.live")


# ---------------------------------------------------------------- folders

def _lines(folder):
    return (folder / "frames.jsonl").read_text().splitlines()


@pytest.mark.slow
def test_generate_alt_folder_passes_check_and_reads(tmp_path):
    out = tmp_path / "alt"
    args = ["generate-alt", "--out", str(out), "--steps", "3", "--seed", "4", "--width", "320", "--height", "180",
            "--quiet"]
    assert dataset_main(args + ["--sequences", "1"]) == 0
    assert dataset_main(args + ["--sequences", "2"]) == 0          # extends the folder
    ds = Dataset(str(out))
    rep = check_dataset(ds)
    assert rep.ok, rep.errors
    assert rep.with_truth == 6 and rep.images_checked == 12 and rep.max_reproj_px < 1e-6
    assert len(ds) == 6 and sorted(ds.sequences()) == [0, 1]
    assert ds.arm is not None and "generate-alt" in ds.meta.source
    for seq, frames in ds.sequences().items():
        assert [f.step for f in frames] == [0, 1, 2]
        centre = transform_points(frames[0].T_world_needle, ds.needle.keypoints()).mean(axis=0)
        dist = np.linalg.norm(centre - frames[0].T_world_ecm[:3, 3])
        assert DISTANCE_RANGE_M[0] - 1e-9 <= dist <= DISTANCE_RANGE_M[1] + 1e-9
        for a, b in zip(frames, frames[1:]):
            assert np.array_equal(a.T_world_needle, b.T_world_needle)
            dq = np.abs(b.ecm_joints - a.ecm_joints)
            assert np.sum(dq > 1e-12) == 1 and dq[2] == 0 and dq.max() == pytest.approx(MULTIVIEW_STEP_RAD)
        for f in frames:
            assert ds.image(f, "left").shape == (180, 320, 3)
            assert f.visible["left"].any() and f.bbox["left"] is not None
    # one run of 2 sequences writes the same frames as 1 + an extension (determinism)
    out2 = tmp_path / "alt2"
    assert dataset_main(["generate-alt", "--out", str(out2), "--sequences", "2", "--steps", "3", "--seed", "4",
                         "--width", "320", "--height", "180", "--quiet"]) == 0
    assert _lines(out) == _lines(out2)
    # other settings in the same folder are refused
    assert dataset_main(["generate-alt", "--out", str(out), "--sequences", "2", "--steps", "2", "--quiet"]) == 1
    # and the contact sheet reads it
    assert dataset_main(["show", str(out), "--out", str(tmp_path / "sheet.png"), "--frames", "4"]) == 0
    assert json.loads(_lines(out)[0])["left"].startswith("images/left/")
