"""Offscreen rendering of the suturing scene and its per-frame ground truth.

One OpenGL context per process (EGL, headless); a new scene only rebuilds MuJoCo's render
context. Per camera there are two passes: the lit colour image, and a segmentation pass that
also reads the depth buffer. Ground truth follows ``docs/dataset.md``:

- ``keypoints``: exact pinhole projections of A..E (pixel (0, 0) = centre of the top-left pixel);
- ``visible``: the needle's surface at the keypoint is seen (``common.sim.visibility``): inside
  the image, not inside the tissue deeper than the wire's radius there (``under_phantom``), and
  the pixel holding the projection shows the needle itself (on the swage, the thread leaving it)
  or nothing nearer than the needle's surface there (from the segmentation and depth render; the
  sharp tip is thinner than a pixel, so its pixel may show what lies behind it, never what lies
  in front), on a stretch of the arc that shows in the image (a tip out of the tissue or past a
  jaw by less than a pixel is not seen);
- ``bbox``: [x0, y0, x1, y1] of the needle's visible pixels, pixel edges included
  (a single pixel (u, v) gives [u-0.5, v-0.5, u+0.5, v+0.5]); None when none are seen.
"""
from __future__ import annotations

import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

from dataclasses import dataclass  # noqa: E402

import cv2  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from common.frames import CAMERAS
from common.geometry.camera import StereoRig  # noqa: E402
from common.geometry.transforms import inv_T, transform_points  # noqa: E402
from common.sim.scene import Appearance, SceneModel, SceneSpec, structure_key  # noqa: E402
from common.sim.scene_meshes import SWAGE_LENGTH_M, needle_radii, under_phantom  # noqa: E402
from common.sim.visibility import arc_angles, visible_along_arc  # noqa: E402

LABELS = {"other": 0, "needle": 1, "thread": 2, "instrument": 3}


@dataclass
class CameraRender:
    """One camera's render: ``bgr`` (h, w, 3) uint8, ``label`` (h, w) uint8 of LABELS,
    ``depth`` (h, w) float32 distance along the optical axis (m), ``geom`` (h, w) int32 MuJoCo
    geom id (-1 where nothing is). Outside ``window`` labels are 0, depth inf, geom -1."""

    bgr: np.ndarray
    label: np.ndarray
    depth: np.ndarray
    geom: np.ndarray
    window: tuple | None = None  # [x0, y0, x1, y1) where label/depth/geom were rendered


_GL = {}


def _gl_context(width: int, height: int):
    """The process's single offscreen GL context (created on first use)."""
    ctx = _GL.get("ctx")
    if ctx is None or _GL["size"][0] < width or _GL["size"][1] < height:
        if ctx is not None:
            ctx.free()
        from mujoco.gl_context import GLContext
        ctx = GLContext(max(width, 1920), max(height, 1080))
        _GL["ctx"], _GL["size"] = ctx, (max(width, 1920), max(height, 1080))
    ctx.make_current()
    return ctx


class SceneRenderer:
    """Renders a ``SceneSpec`` from the stereo endoscope at any ECM pose.

    ``load(spec)`` sets the scene (a spec with the same structure reuses the compiled model and
    render context: only meshes, textures, colours and poses change); ``render(T_world_ecm)``
    returns both cameras' ``CameraRender``; ``ground_truth(T_world_ecm, renders)`` the spec's
    per-frame fields. The segmentation/depth pass covers only the window around the needle
    (``CameraRender.window``) unless ``full_segmentation`` is set.
    """

    def __init__(self, spec: SceneSpec | None = None, full_segmentation: bool = False):
        self.spec = None
        self.scene = None
        self._ctx = None
        self.full_segmentation = full_segmentation
        if spec is not None:
            self.load(spec)

    @property
    def model(self):
        return self.scene.model if self.scene is not None else None

    def load(self, spec: SceneSpec) -> None:
        w, h = spec.rig.left.width, spec.rig.left.height
        _gl_context(w, h)
        if self.scene is not None and self.scene.key == structure_key(spec):
            meshes, textures = self.scene.apply(spec)
            for k in meshes:
                mujoco.mjr_uploadMesh(self.model, self._ctx, k)
            for k in textures:
                mujoco.mjr_uploadTexture(self.model, self._ctx, k)
        else:
            self.close()
            self.scene = SceneModel(spec)
            self.scene.apply(spec)
            model = self.model
            self.data = mujoco.MjData(model)
            self._ctx = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
            mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._ctx)
            self._ctx.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
            self._scene = mujoco.MjvScene(model, maxgeom=256)
            self._opt = mujoco.MjvOption()
            self._rect = mujoco.MjrRect(0, 0, w, h)
            self._cams = {}
            for name in CAMERAS:
                cam = mujoco.MjvCamera()
                cam.type = mujoco.mjtCamera.mjCAMERA_FIXED
                cam.fixedcamid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
                self._cams[name] = cam
            self._geom_label = np.zeros(model.ngeom, np.uint8)
            for g in range(model.ngeom):
                name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or ""
                for key in ("needle", "thread", "instrument"):
                    if name.startswith(key):
                        self._geom_label[g] = LABELS[key]
            self._rgb = np.empty((h, w, 3), np.uint8)
        self.spec = spec
        self.scene.set_poses(self.data, spec)
        self._T_world_needle = np.asarray(spec.T_world_needle, dtype=float)

    def close(self) -> None:
        if self._ctx is not None:
            self._ctx.free()
            self._ctx = None
        self.scene = None

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    def set_needle(self, T_world_needle: np.ndarray) -> None:
        """Move the needle body (the thread is part of the static scene and does not follow)."""
        self._T_world_needle = np.asarray(T_world_needle, dtype=float)
        self.scene.set_mocap(self.data, "needle", self._T_world_needle)

    def needle_window(self, camera: str, T_world_ecm: np.ndarray, margin_px: int = 4):
        """Pixel window [x0, y0, x1, y1) (exclusive ends) holding the needle's image, or None."""
        cam = self.spec.rig[camera]
        needle = self.spec.needle
        p = transform_points(cam.T_cam_ecm @ inv_T(T_world_ecm) @ self._T_world_needle,
                             needle.sample_arc(64))
        if np.any(p[:, 2] <= 1e-3):
            return (0, 0, cam.width, cam.height)  # partly behind the camera: everything
        uv = cam.project(p)
        pad = margin_px + self.spec.appearance.wire_diameter_m * cam.K[0, 0] / p[:, 2].min()
        x0 = int(np.floor(uv[:, 0].min() - pad))
        y0 = int(np.floor(uv[:, 1].min() - pad))
        x1 = int(np.ceil(uv[:, 0].max() + pad)) + 1
        y1 = int(np.ceil(uv[:, 1].max() + pad)) + 1
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, cam.width), min(y1, cam.height)
        if x1 <= x0 or y1 <= y0:
            return None
        return (x0, y0, x1, y1)

    def render(self, T_world_ecm: np.ndarray, cameras=CAMERAS) -> dict[str, CameraRender]:
        """Colour, labels and depth of each camera at the ECM pose ``T_world_ecm``."""
        _gl_context(self._rect.width, self._rect.height)
        T_world_ecm = np.asarray(T_world_ecm, dtype=float)
        self.scene.set_mocap(self.data, "ecm", T_world_ecm)
        mujoco.mj_forward(self.model, self.data)
        out = {}
        m = self.model
        W, H = self._rect.width, self._rect.height
        flags = self._scene.flags
        self.last_timings = {"colour": 0.0, "window": 0.0}
        for name in cameras:
            mujoco.mjv_updateScene(m, self.data, self._opt, None, self._cams[name],
                                   mujoco.mjtCatBit.mjCAT_ALL, self._scene)
            t0 = time.perf_counter()
            flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(bool(self.spec.appearance.shadows))
            flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = 0
            flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = 0
            mujoco.mjr_render(self._rect, self._scene, self._ctx)
            mujoco.mjr_readPixels(self._rgb, None, self._rect, self._ctx)
            bgr = cv2.flip(cv2.cvtColor(self._rgb, cv2.COLOR_RGB2BGR), 0)
            t1 = time.perf_counter()
            label = np.zeros((H, W), np.uint8)
            depth = np.full((H, W), np.inf, np.float32)
            geom = np.full((H, W), -1, np.int32)
            win = (0, 0, W, H) if self.full_segmentation else self.needle_window(name, T_world_ecm)
            if win is not None:
                self._window_pass(win, label, depth, geom)
            self.last_timings["colour"] += t1 - t0
            self.last_timings["window"] += time.perf_counter() - t1
            out[name] = CameraRender(bgr, label, depth, geom, win)
        return out

    def _window_pass(self, win, label, depth, geom) -> None:
        """Segmentation + depth of the pixel window [x0, x1) x [y0, y1) into the full-size arrays."""
        m = self.model
        W, H = self._rect.width, self._rect.height
        near = m.vis.map.znear * m.stat.extent
        far = m.vis.map.zfar * m.stat.extent
        x0, y0, x1, y1 = win
        # off-axis frustum of the window: pixel edges at integers in GL window coordinates
        ht = self._scene.camera[0].frustum_top
        hw = ht * W / H
        for c in self._scene.camera:
            left, right = -hw + 2 * hw * x0 / W, -hw + 2 * hw * x1 / W
            c.frustum_center = (left + right) / 2
            c.frustum_width = (right - left) / 2
            c.frustum_bottom = -ht + 2 * ht * (H - y1) / H
            c.frustum_top = -ht + 2 * ht * (H - y0) / H
        flags = self._scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = 1
        flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = 1
        rect = mujoco.MjrRect(0, 0, x1 - x0, y1 - y0)
        ids = np.empty((y1 - y0, x1 - x0, 3), np.uint8)
        zbuf = np.empty((y1 - y0, x1 - x0), np.float32)
        mujoco.mjr_render(rect, self._scene, self._ctx)
        mujoco.mjr_readPixels(ids, zbuf, rect, self._ctx)
        ids, zbuf = ids[::-1], zbuf[::-1]
        seg = (ids[..., 0].astype(np.int32) + (ids[..., 1].astype(np.int32) << 8)
               + (ids[..., 2].astype(np.int32) << 16))
        lut = np.zeros(self._scene.ngeom + 2, np.uint8)
        gid = np.full(self._scene.ngeom + 2, -1, np.int32)
        for g in range(self._scene.ngeom):
            sg = self._scene.geoms[g]
            if sg.segid >= 0 and sg.objtype == mujoco.mjtObj.mjOBJ_GEOM:
                lut[sg.segid + 1] = self._geom_label[sg.objid]
                gid[sg.segid + 1] = sg.objid
        seg = np.clip(seg, 0, len(lut) - 1)
        label[y0:y1, x0:x1] = lut[seg]
        geom[y0:y1, x0:x1] = gid[seg]
        depth[y0:y1, x0:x1] = _linear_depth(zbuf, near, far)

    def ground_truth(self, T_world_ecm: np.ndarray, renders: dict[str, CameraRender]) -> dict:
        """The spec's ``keypoints``, ``visible`` and ``bbox`` for both cameras."""
        return frame_ground_truth(self.spec.rig, self.spec.needle, self._T_world_needle,
                                  np.asarray(T_world_ecm, float), renders, self.spec.appearance)


def _linear_depth(zbuf: np.ndarray, near: float, far: float) -> np.ndarray:
    """MuJoCo's reversed-Z depth buffer -> distance along the optical axis (m)."""
    zfar, znear = np.float32(far), np.float32(near)
    c = -(zfar + znear) / (zfar - znear)
    d = -(np.float32(2) * zfar * znear) / (zfar - znear)
    c = np.float32(-0.5) * c - np.float32(0.5)
    d = np.float32(-0.5) * d
    return (d / (zbuf.astype(np.float64) + c)).astype(np.float32)


ARC_VISIBLE_SAMPLES = 49
"""Points along the arc (A..E, equally spaced) whose visibility gives ``arc_visible``."""


def frame_ground_truth(rig: StereoRig, needle, T_world_needle, T_world_ecm, renders,
                       appearance: Appearance) -> dict:
    """keypoints / visible / bbox per camera from the exact projection and the renders,
    ``arc_seen``: whether each of ``ARC_VISIBLE_SAMPLES`` points along the arc (A..E, equally
    spaced) is seen, and ``arc_visible``: their seen share. Seen: ``common.sim.visibility``, for
    the needle's shape (its radius along the arc) that ``appearance`` draws."""
    a0, a1 = needle.arc_span_rad
    T_ecm_needle = inv_T(T_world_ecm) @ T_world_needle
    coarse = []
    for c in CAMERAS:
        p = transform_points(rig[c].T_cam_ecm @ T_ecm_needle, needle.sample_arc(ARC_VISIBLE_SAMPLES))
        coarse.append(np.where(p[:, 2:] > 0, rig[c].project(p), np.nan))
    wanted = np.concatenate([needle.keypoint_angles_rad, np.linspace(a0, a1, ARC_VISIBLE_SAMPLES)])
    angles, at = arc_angles((a0, a1), coarse, wanted)
    radii = needle_radii(needle, needle.radius_m * np.abs(angles - a0), appearance.wire_diameter_m,
                         appearance.tip_length_m, appearance.tip_exponent, appearance.swage_scale)
    arc_m = needle.radius_m * (angles - angles[0])
    at_thread = needle.radius_m * np.abs(angles - a1) <= SWAGE_LENGTH_M
    p_needle = needle.arc_points(angles)
    buried = under_phantom(transform_points(T_world_needle, p_needle), radii)
    kps, vis, boxes, arc_vis, arc_seen = {}, {}, {}, {}, {}
    for c in CAMERAS:
        cam = rig[c]
        p = transform_points(cam.T_cam_ecm @ T_ecm_needle, p_needle)
        uv = cam.project(p)
        kps[c] = uv[at[:5]]
        r = renders.get(c)
        seen = np.zeros(len(angles), bool)
        boxes[c] = None
        if r is not None:
            inside = cam.in_image(uv) & (p[:, 2] > 0)
            seen = visible_along_arc(uv, p[:, 2], arc_m, radii, inside, buried, r.label, LABELS["needle"], r.depth,
                                     cam.K[0, 0], LABELS["thread"], at_thread)
            ys, xs = np.nonzero(r.label == LABELS["needle"])
            if len(xs):
                boxes[c] = [float(xs.min()) - 0.5, float(ys.min()) - 0.5, float(xs.max()) + 0.5, float(ys.max()) + 0.5]
        vis[c] = seen[at[:5]]
        arc_seen[c] = seen[at[5:]]
        arc_vis[c] = float(arc_seen[c].mean())
    return {"keypoints": kps, "visible": vis, "bbox": boxes, "arc_visible": arc_vis, "arc_seen": arc_seen}
