"""MuJoCo renders with exactly the intrinsics and extrinsics written to data (issue 3, section 1)."""
import mujoco
import numpy as np
import pytest

import common.sim.render  # noqa: F401  (sets MUJOCO_GL before mujoco is imported)
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T, make_T, rotvec_to_R, transform_points
from common.sim.randomise import default_arm
from common.sim.render import LABELS, SceneRenderer
from common.sim.scene import SceneSpec


def _sphere_image_centre(K, c_cam, radius):
    """Exact centre (px) of the elliptical silhouette of a sphere (centre c_cam, camera frame):
    the cone of rays at angle alpha = asin(r/|c|) around c, cut by the image plane z = 1."""
    d = c_cam / np.linalg.norm(c_cam)
    cos2 = 1.0 - (radius / np.linalg.norm(c_cam)) ** 2
    Q = np.outer(d, d) - cos2 * np.eye(3)  # conic over homogeneous (x, y, 1)
    xy = -np.linalg.solve(Q[:2, :2], Q[:2, 2])
    return K[:2, :2] @ xy + K[:2, 2]


def _marker_centroids(renderer, render, n):
    out = []
    for i in range(n):
        gid = mujoco.mj_name2id(renderer.model, mujoco.mjtObj.mjOBJ_GEOM, f"marker{i}")
        ys, xs = np.nonzero(render.geom == gid)
        out.append((xs.mean(), ys.mean(), len(xs)) if len(xs) else (np.nan, np.nan, 0))
    return np.array(out)


@pytest.mark.parametrize("size", [(640, 360), (1920, 1080)])
def test_known_points_render_at_K_projection(size):
    """Spheres at known world points render where K, T_ecm_cam and T_world_ecm project them,
    in both cameras, for a tilted and rolled endoscope (x right and y down: no flips)."""
    w, h = size
    rig = StereoRig.default(w, h)
    T_world_ecm = make_T(rotvec_to_R([0.3, -0.2, 0.7]), [0.01, -0.02, 0.16])
    # points spread over the left image: centre, corners region, off-axis both ways
    uv_targets = np.array([[0.5, 0.5], [0.15, 0.2], [0.85, 0.2], [0.2, 0.8], [0.8, 0.75], [0.6, 0.35]])
    depths = np.array([0.10, 0.12, 0.14, 0.13, 0.11, 0.09])
    Kinv = np.linalg.inv(rig.left.K)
    pts_cam = [(Kinv @ [u * (w - 1), v * (h - 1), 1.0]) * d for (u, v), d in zip(uv_targets, depths)]
    T_world_left = T_world_ecm @ rig.left.T_ecm_cam
    pts_world = transform_points(T_world_left, np.array(pts_cam))
    radii = depths * 8.0 / rig.left.K[0, 0]  # about 8 px in the image
    spec = SceneSpec(rig=rig, T_world_needle=make_T(np.eye(3), [0, 0, -1.0]),
                     markers=[(*p, rad) for p, rad in zip(pts_world, radii)])
    r = SceneRenderer(spec, full_segmentation=True)
    renders = r.render(T_world_ecm)
    for cam in ("left", "right"):
        c = rig[cam]
        p_cam = transform_points(inv_T(T_world_ecm @ c.T_ecm_cam), pts_world)
        centre_proj = c.project(p_cam)
        expect = np.array([_sphere_image_centre(c.K, p, rad) for p, rad in zip(p_cam, radii)])
        # the silhouette's centre is the projected centre pushed outwards (perspective)
        assert np.linalg.norm(expect - centre_proj, axis=1).max() < 0.5
        got = _marker_centroids(r, renders[cam], len(pts_world))
        assert np.all(got[:, 2] > 100), f"{cam}: a marker is missing from the render: {got[:, 2]}"
        err = np.linalg.norm(got[:, :2] - expect, axis=1)
        # pixel quantisation and MuJoCo's sphere tessellation move an ~8 px disc's centroid by
        # up to ~0.15 px, at random; a wrong K would show as a common scale or offset
        assert err.max() < 0.25, f"{cam} {w}x{h}: marker centroids off by {err.round(3)} px"
        A = np.zeros((2 * len(got), 3))
        A[0::2, 0], A[1::2, 0] = expect[:, 0] - c.K[0, 2], expect[:, 1] - c.K[1, 2]
        A[0::2, 1], A[1::2, 2] = 1.0, 1.0
        scale_m1, ox, oy = np.linalg.lstsq(A, (got[:, :2] - expect).reshape(-1), rcond=None)[0]
        assert abs(scale_m1) < 1e-3, f"{cam}: focal length off by {scale_m1 * 100:.3f}%"
        assert np.hypot(ox, oy) < 0.06, f"{cam}: principal point off by ({ox:.3f}, {oy:.3f}) px"
    r.close()


def test_rig_and_arm_conventions():
    """Built-in ECM: image right is world +x at q = 0 and the scope looks down at the pad."""
    arm = default_arm()
    T = arm.T_world_ecm([0, 0, 0.1, 0])
    view = -T[:3, 2]
    assert view[2] < -0.8  # looking down
    rig = StereoRig.default()
    T_world_left = T @ rig.left.T_ecm_cam
    assert T_world_left[:3, 0] @ [1, 0, 0] > 0.99  # camera x = world x
    assert np.allclose(T_world_left[:3, 2], view)


def test_ground_truth_keypoints_lie_on_the_needle_mask():
    """Every visible ground-truth keypoint lies on the rendered needle; A is the sharp end."""
    from common.sim.randomise import get_preset, plan_sequence
    rig = StereoRig.default(640, 360)
    needle, arm = NeedleModel(), default_arm()
    checked = 0
    for s in range(3):
        plan = plan_sequence(7, s, 2, get_preset("none"), rig, needle, arm, texture_size=256)
        r = SceneRenderer(plan.spec)
        for q in plan.joints:
            T = arm.T_world_ecm(q)
            renders = r.render(T)
            gt = r.ground_truth(T, renders)
            for cam in ("left", "right"):
                lab = renders[cam].label
                for k in range(5):
                    if not gt["visible"][cam][k]:
                        continue
                    u, v = np.round(gt["keypoints"][cam][k]).astype(int)
                    win = lab[max(v - 2, 0):v + 3, max(u - 2, 0):u + 3]
                    assert np.any(win == LABELS["needle"]), f"seq {s} {cam} keypoint {'ABCDE'[k]} not on the needle"
                    checked += 1
                # A is the sharp end: the needle is thinner around A than around C
                uv = gt["keypoints"][cam]
                ys, xs = np.nonzero(lab == LABELS["needle"])
                pix = np.stack([xs, ys], 1)

                def near(p, rad=3.0):
                    return int(np.sum(np.linalg.norm(pix - p, axis=1) < rad))
                if gt["visible"][cam][0] and gt["visible"][cam][2]:
                    assert near(uv[0]) < near(uv[2]), f"seq {s} {cam}: the needle is not thinner at A than at C"
        r.close()
    assert checked > 30
