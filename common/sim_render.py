"""Offscreen rendering of the suturing scene and its per-frame ground truth.

One OpenGL context per process (EGL, headless); a new scene only rebuilds MuJoCo's render
context. Per camera there are two passes: the lit colour image, and a segmentation pass that
also reads the depth buffer. Ground truth follows ``../shared/specs/dataset.md``:

- ``keypoints``: exact pinhole projections of A..E (pixel (0, 0) = centre of the top-left pixel);
- ``visible``: inside the image and not occluded: the pixel holding the projection shows the
  needle itself, or nothing nearer than the keypoint minus a wire diameter (from the segmentation
  and depth render; the sharp tip is thinner than a pixel, so its pixel may show what lies behind);
- ``bbox``: [x0, y0, x1, y1] of the needle's visible pixels, pixel edges included
  (a single pixel (u, v) gives [u-0.5, v-0.5, u+0.5, v+0.5]); None when none are seen.
"""
from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

from dataclasses import dataclass  # noqa: E402

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from common.camera import StereoRig  # noqa: E402
from common.sim_scene import SceneSpec, build_mjcf  # noqa: E402
from common.transforms import R_to_quat, inv_T, transform_points  # noqa: E402

LABELS = {"other": 0, "needle": 1, "thread": 2, "instrument": 3}
CAMERAS = ("left", "right")


@dataclass
class CameraRender:
    """One camera's render: ``bgr`` (h, w, 3) uint8, ``label`` (h, w) uint8 of LABELS,
    ``depth`` (h, w) float32 distance along the optical axis (m), ``geom`` (h, w) int32 MuJoCo
    geom id (-1 where nothing is)."""

    bgr: np.ndarray
    label: np.ndarray
    depth: np.ndarray
    geom: np.ndarray


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

    ``load(spec)`` builds the MuJoCo model; ``render(T_world_ecm)`` returns both cameras'
    ``CameraRender``; ``ground_truth(T_world_ecm, renders)`` the spec's per-frame fields.
    """

    def __init__(self, spec: SceneSpec | None = None):
        self.spec = None
        self.model = None
        self._ctx = None
        if spec is not None:
            self.load(spec)

    def load(self, spec: SceneSpec) -> None:
        xml, assets = build_mjcf(spec)
        model = mujoco.MjModel.from_xml_string(xml, assets)
        w, h = spec.rig.left.width, spec.rig.left.height
        _gl_context(w, h)
        self.close()
        self.model, self.data, self.spec = model, mujoco.MjData(model), spec
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
        self._mocap = {b: int(model.body_mocapid[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, b)])
                       for b in ("needle", "ecm")}
        self._rgb = np.empty((h, w, 3), np.uint8)
        self._ids = np.empty((h, w, 3), np.uint8)
        self._zbuf = np.empty((h, w), np.float32)
        self.set_needle(spec.T_world_needle)

    def close(self) -> None:
        if self._ctx is not None:
            self._ctx.free()
            self._ctx = None

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    # -- poses
    def _set_mocap(self, body: str, T: np.ndarray) -> None:
        i = self._mocap[body]
        self.data.mocap_pos[i] = T[:3, 3]
        self.data.mocap_quat[i] = R_to_quat(T[:3, :3])

    def set_needle(self, T_world_needle: np.ndarray) -> None:
        """Move the needle body (the thread is part of the static scene and does not follow)."""
        self._T_world_needle = np.asarray(T_world_needle, dtype=float)
        self._set_mocap("needle", self._T_world_needle)

    # -- rendering
    def render(self, T_world_ecm: np.ndarray, cameras=CAMERAS) -> dict[str, CameraRender]:
        """Colour, labels and depth of each camera at the ECM pose ``T_world_ecm``."""
        _gl_context(self._rect.width, self._rect.height)
        self._set_mocap("ecm", np.asarray(T_world_ecm, dtype=float))
        mujoco.mj_forward(self.model, self.data)
        out = {}
        m = self.model
        near = m.vis.map.znear * m.stat.extent
        far = m.vis.map.zfar * m.stat.extent
        for name in cameras:
            mujoco.mjv_updateScene(m, self.data, self._opt, None, self._cams[name],
                                   mujoco.mjtCatBit.mjCAT_ALL, self._scene)
            flags = self._scene.flags
            flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 1
            flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = 0
            flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = 0
            mujoco.mjr_render(self._rect, self._scene, self._ctx)
            mujoco.mjr_readPixels(self._rgb, None, self._rect, self._ctx)
            bgr = np.ascontiguousarray(self._rgb[::-1, :, ::-1])
            flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = 1
            flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = 1
            mujoco.mjr_render(self._rect, self._scene, self._ctx)
            mujoco.mjr_readPixels(self._ids, self._zbuf, self._rect, self._ctx)
            seg = (self._ids[::-1, :, 0].astype(np.int32) + (self._ids[::-1, :, 1].astype(np.int32) << 8)
                   + (self._ids[::-1, :, 2].astype(np.int32) << 16))
            lut = np.zeros(self._scene.ngeom + 2, np.uint8)
            gid = np.full(self._scene.ngeom + 2, -1, np.int32)
            for g in range(self._scene.ngeom):
                sg = self._scene.geoms[g]
                if sg.segid >= 0 and sg.objtype == mujoco.mjtObj.mjOBJ_GEOM:
                    lut[sg.segid + 1] = self._geom_label[sg.objid]
                    gid[sg.segid + 1] = sg.objid
            seg = np.clip(seg, 0, len(lut) - 1)
            out[name] = CameraRender(bgr, lut[seg], _linear_depth(self._zbuf[::-1], near, far), gid[seg])
        return out

    def ground_truth(self, T_world_ecm: np.ndarray, renders: dict[str, CameraRender]) -> dict:
        """The spec's ``keypoints``, ``visible`` and ``bbox`` for both cameras."""
        return frame_ground_truth(self.spec.rig, self.spec.needle, self._T_world_needle,
                                  np.asarray(T_world_ecm, float), renders,
                                  self.spec.appearance.wire_diameter_m / 2)


def _linear_depth(zbuf: np.ndarray, near: float, far: float) -> np.ndarray:
    """MuJoCo's reversed-Z depth buffer -> distance along the optical axis (m)."""
    zfar, znear = np.float32(far), np.float32(near)
    c = -(zfar + znear) / (zfar - znear)
    d = -(np.float32(2) * zfar * znear) / (zfar - znear)
    c = np.float32(-0.5) * c - np.float32(0.5)
    d = np.float32(-0.5) * d
    return (d / (zbuf.astype(np.float64) + c)).astype(np.float32)


def needle_keypoints_cam(rig: StereoRig, needle, T_world_needle, T_world_ecm) -> dict[str, np.ndarray]:
    """(5, 3) keypoints A..E in each camera frame (m)."""
    T_ecm_needle = inv_T(T_world_ecm) @ T_world_needle
    p_ecm = transform_points(T_ecm_needle, needle.keypoints())
    return {c: transform_points(rig[c].T_cam_ecm, p_ecm) for c in CAMERAS}


def frame_ground_truth(rig: StereoRig, needle, T_world_needle, T_world_ecm, renders,
                       wire_radius_m: float) -> dict:
    """keypoints / visible / bbox per camera from the exact projection and the renders."""
    p_cam = needle_keypoints_cam(rig, needle, T_world_needle, T_world_ecm)
    kps, vis, boxes = {}, {}, {}
    for c in CAMERAS:
        cam = rig[c]
        uv = cam.project(p_cam[c])
        inside = cam.in_image(uv) & (p_cam[c][:, 2] > 0)
        r = renders.get(c)
        v = np.zeros(5, bool)
        if r is not None:
            h, w = r.label.shape
            for k in np.flatnonzero(inside):
                u0 = min(max(int(round(uv[k, 0])), 0), w - 1)
                v0 = min(max(int(round(uv[k, 1])), 0), h - 1)
                v[k] = bool(r.label[v0, u0] == LABELS["needle"]
                            or r.depth[v0, u0] > p_cam[c][k, 2] - 2 * wire_radius_m)
            ys, xs = np.nonzero(r.label == LABELS["needle"])
            boxes[c] = (None if len(xs) == 0 else
                        [float(xs.min()) - 0.5, float(ys.min()) - 0.5, float(xs.max()) + 0.5, float(ys.max()) + 0.5])
        else:
            boxes[c] = None
        kps[c], vis[c] = uv, v
    return {"keypoints": kps, "visible": vis, "bbox": boxes}
