"""A second, independent renderer of stereo needle scenes: numpy/OpenCV, no MuJoCo, no GL.

Why: everything the project learns and tunes is seen through the built-in MuJoCo scene
(``common/sim/scene.py``, ``render.py``). This renderer shares none of its code paths, meshes, textures or shading,
only the data contract (the spec's cameras, ECM and needle model), so figures measured on its
images tell whether a model or a method overfits the built-in look.

How it draws, per camera (OpenCV pinhole, pixel (0, 0) the centre of the top-left pixel):
- the tissue is an analytic height field ``z = sum a sin(k . xy + phase)`` (metres, world z up),
  ray-cast per sample (fixed-point iterations on the ray's depth), with its own procedural
  albedo texture, a tiled detail texture chosen by pixel footprint, and red marks;
- the needle, thread and instruments are triangle meshes rasterised with a z-buffer (edge
  functions over each triangle's pixel box, perspective-correct depth and barycentrics, the
  nearest sample per pixel kept) and depth-tested against the tissue;
- shading: Lambert + Blinn-Phong from two lights on the scope tip (inverse-square fall-off, a
  spot cone along the optical axis), a fake environment reflection on metal, gamma 2.2;
- anti-aliasing: the needle's region is rendered again at 3x3 samples per pixel and averaged;
  elsewhere object edges are blended with their neighbours;
- optics blur and sensor noise last.

Ground truth: keypoints are the pinhole projections of the needle model's A..E; a keypoint is
visible when the needle's surface there is seen (``common.sim.visibility``, the built-in
renderer's rule): inside the image, in front of the camera, not inside the tissue deeper than the
needle's radius there, and its pixel shows the needle or nothing nearer than the needle's surface
there (the z-buffer against the keypoint's depth minus that radius, 0 at the sharp tip, and a
pixel's footprint), on a stretch of the arc that shows in the image; ``bbox`` is the box of the
needle's pixels (pixel centres covered by the needle), edges included.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import cv2
import numpy as np

from common.frames import CAMERAS
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T, transform_points
from common.sim.alt_meshes import LABELS, NeedleShape
from common.sim.alt_raster import NEAR_M, rasterise
from common.sim.alt_tissue import Tissue
from common.sim.visibility import LENGTH_SAMPLES, arc_angles, visible_along_arc

SUPERSAMPLE = 3            # samples per pixel side in the needle's region


# ---------------------------------------------------------------- the scene

@dataclass
class Light:
    """A light on the scope tip: position in the ECM frame (m), linear RGB, intensity."""

    offset_ecm: tuple
    rgb: tuple = (1.0, 1.0, 1.0)
    intensity: float = 1.0


@dataclass
class AltScene:
    """Everything one sequence needs to be rendered (the needle at rest, the ECM moving)."""

    needle: NeedleModel
    needle_shape: NeedleShape
    T_world_needle: np.ndarray
    tissue: Tissue
    meshes: list                      # world-frame Mesh objects, the needle first
    lights: list = field(default_factory=lambda: [Light((0.0, 0.003, 0.0))])
    spot_exponent: float = 2.0        # cos^k fall-off of the lights around the optical axis
    ambient: float = 0.04
    exposure: float = 1.0             # 1: tissue facing the light at the needle's distance ~ albedo
    env_low: tuple = (0.35, 0.08, 0.07)    # what metal mirrors below / above it (linear RGB)
    env_high: tuple = (0.55, 0.5, 0.48)
    blur_sigma_px: float = 0.5
    noise_sigma: float = 1.5          # grey levels
    noise_seed: int = 0

    @property
    def needle_centre(self) -> np.ndarray:
        return transform_points(self.T_world_needle, self.needle.keypoints()).mean(axis=0)


@dataclass
class AltRender:
    """One camera's render: ``bgr`` (h, w, 3) uint8, ``label`` (h, w) int8 (``LABELS``),
    ``depth`` (h, w) float32 (m along the optical axis, inf where nothing)."""

    bgr: np.ndarray
    label: np.ndarray
    depth: np.ndarray


# ---------------------------------------------------------------- the renderer

_GAMMA_LUT = (np.linspace(0.0, 1.0, 65536) ** (1 / 2.2) * 255.0 + 0.5).astype(np.uint8)


def _lin_to_bgr8(rgb: np.ndarray) -> np.ndarray:
    """Linear RGB in [0, 1] -> sRGB-like (gamma 2.2) 8-bit BGR."""
    q = (np.clip(rgb[..., ::-1], 0.0, 1.0) * 65535.0 + 0.5).astype(np.uint16)
    return _GAMMA_LUT[q]


class AltRenderer:
    """Renders an ``AltScene`` through a ``StereoRig`` at the ECM pose ``T_world_ecm``."""

    def __init__(self, rig: StereoRig, supersample: int = SUPERSAMPLE):
        self.rig = rig
        self.supersample = int(supersample)
        self._scene = None

    def _prepare(self, scene: AltScene) -> None:
        """Concatenate the scene's meshes once per scene."""
        if self._scene is scene:     # a reference, not an id: a freed scene's id can be reused
            return
        V, F, N, lab, mat = [], [], [], [], []
        n = 0
        for i, m in enumerate(scene.meshes):
            V.append(m.V)
            N.append(m.N)
            F.append(m.F + n)
            lab.append(np.full(len(m.F), m.label, np.int8))
            mat.append(np.full(len(m.F), i, np.int32))
            n += len(m.V)
        self._V = np.concatenate(V) if V else np.zeros((0, 3))
        self._N = np.concatenate(N) if N else np.zeros((0, 3))
        self._F = np.concatenate(F) if F else np.zeros((0, 3), np.int64)
        self._face_label = np.concatenate(lab) if lab else np.zeros(0, np.int8)
        self._face_mesh = np.concatenate(mat) if mat else np.zeros(0, np.int32)
        self._needle_V = scene.meshes[0].V if scene.meshes and scene.meshes[0].label == LABELS["needle"] else None
        self._scene = scene

    def render(self, scene: AltScene, T_world_ecm: np.ndarray) -> dict[str, AltRender]:
        """Both cameras' images, labels and depths."""
        self._prepare(scene)
        return {c: self._render_camera(scene, T_world_ecm, self.rig[c]) for c in CAMERAS}

    def _render_camera(self, scene: AltScene, T_world_ecm: np.ndarray, cam) -> AltRender:
        w, h = cam.width, cam.height
        T_world_cam = T_world_ecm @ cam.T_ecm_cam
        rgb, label, depth = self._samples(scene, T_world_ecm, T_world_cam, cam.K, w, h)
        rgb = _smooth_object_edges(rgb, label)
        box = self._needle_window(T_world_cam, cam)
        if box is not None and self.supersample > 1:
            x0, y0, x1, y1 = box
            s = self.supersample
            Ks = np.array([[s, 0, s * (0.5 - x0) - 0.5], [0, s, s * (0.5 - y0) - 0.5], [0, 0, 1.0]]) @ cam.K
            ss, _, _ = self._samples(scene, T_world_ecm, T_world_cam, Ks, s * (x1 - x0 + 1), s * (y1 - y0 + 1))
            rgb[y0:y1 + 1, x0:x1 + 1] = ss.reshape(y1 - y0 + 1, s, x1 - x0 + 1, s, 3).mean(axis=(1, 3))
        if scene.blur_sigma_px > 0.05:
            rgb = cv2.GaussianBlur(rgb, (0, 0), scene.blur_sigma_px)
        bgr = _lin_to_bgr8(rgb)
        if scene.noise_sigma > 0:
            # the same frame always gets the same noise
            rng = np.random.default_rng([scene.noise_seed, CAMERAS.index(cam.name),
                                         zlib.crc32(np.ascontiguousarray(T_world_ecm, float).tobytes())])
            noise = rng.standard_normal((h, w, 1), np.float32) * 0.6 + rng.standard_normal((h, w, 3), np.float32) * 0.8
            bgr = np.clip(bgr + noise * np.float32(scene.noise_sigma), 0, 255).astype(np.uint8)
        return AltRender(bgr, label, depth)

    def _needle_window(self, T_world_cam, cam):
        """Pixel box [x0, y0, x1, y1] (inclusive) around the projected needle mesh, or None."""
        if self._needle_V is None:
            return None
        p = transform_points(inv_T(T_world_cam), self._needle_V)
        p = p[p[:, 2] > NEAR_M]
        if len(p) == 0:
            return None
        uv = cam.project(p)
        x0 = int(max(np.floor(uv[:, 0].min()) - 4, 0))
        y0 = int(max(np.floor(uv[:, 1].min()) - 4, 0))
        x1 = int(min(np.ceil(uv[:, 0].max()) + 4, cam.width - 1))
        y1 = int(min(np.ceil(uv[:, 1].max()) + 4, cam.height - 1))
        if x1 < x0 or y1 < y0:
            return None
        return x0, y0, x1, y1

    def _samples(self, scene: AltScene, T_world_ecm, T_world_cam, K, w: int, h: int):
        """Linear RGB (h, w, 3), label (h, w) int8 and depth (h, w) of the sample grid of ``K``."""
        R = T_world_cam[:3, :3]
        o = T_world_cam[:3, 3].astype(np.float32)
        Ki = np.linalg.inv(K)

        def rays(xs, ys):
            """World ray directions (component arrays), scaled to unit depth along the optical axis."""
            xs = (Ki[0, 0] * xs + Ki[0, 2]).astype(np.float32)[None, :]
            ys = (Ki[1, 1] * ys + Ki[1, 2]).astype(np.float32)[:, None]
            return tuple(xs * np.float32(R[i, 0]) + ys * np.float32(R[i, 1]) + np.float32(R[i, 2]) for i in range(3))

        tissue = scene.tissue
        d = rays(np.arange(w), np.arange(h))
        # coarse-to-fine: the smooth surface is solved on a 4x coarser grid (sample centres at
        # 4a + 1.5, which a linear resize maps back exactly), then refined at every sample
        c = 4
        wc, hc = -(-w // c), -(-h // c)
        t_c = tissue.raycast(o, *rays(c * np.arange(wc) + 1.5, c * np.arange(hc) + 1.5))
        t0 = cv2.resize(np.where(np.isfinite(t_c), t_c, 0.0).astype(np.float32), (wc * c, hc * c),
                        interpolation=cv2.INTER_LINEAR)[:h, :w]
        t = tissue.raycast(o, *d, t0=t0, iterations=2)
        hit = np.isfinite(t)
        tt = np.where(hit, t, 0.0).astype(np.float32)
        P = tuple(o[i] + tt * d[i] for i in range(3))
        fp = float(np.linalg.norm(scene.needle_centre - T_world_cam[:3, 3])) / K[0, 0]
        alb = tissue.albedo_at(P[0], P[1], fp)
        rgb = self._shade(scene, T_world_ecm, o, P, tissue.normal(P[0], P[1]), alb,
                          np.full(3, tissue.ks, np.float32), tissue.shininess, 0.0)
        rgb[~hit] = 0.0
        label = np.where(hit, LABELS["tissue"], LABELS["none"]).astype(np.int8)
        depth = t
        if len(self._F):
            V_cam = transform_points(inv_T(T_world_cam), self._V)
            face, depth, bary = rasterise(V_cam, self._F, K, w, h, depth=t)
            js, is_ = np.nonzero(face >= 0)
            if len(js):
                f = face[js, is_]
                b = bary[js, is_]
                nv = np.einsum("nk,nkc->nc", b, self._N[self._F[f]]).astype(np.float32)
                nv /= np.maximum(np.linalg.norm(nv, axis=1, keepdims=True), 1e-12)
                dd = np.stack([d[i][js, is_] for i in range(3)], axis=1)
                Po = o + depth[js, is_, None] * dd
                # an interpolated normal facing away from the camera (at a silhouette) is
                # mirrored about the plane facing the viewer
                vdir = -dd / np.linalg.norm(dd, axis=1, keepdims=True)
                vn = np.sum(nv * vdir, axis=1, keepdims=True)
                nv = np.where(vn < 0, nv - 2 * vn * vdir, nv)
                label[js, is_] = self._face_label[f]
                out = np.empty((len(f), 3), np.float32)
                mesh_of = self._face_mesh[f]
                for mi in np.unique(mesh_of):
                    sel = mesh_of == mi
                    m = scene.meshes[mi].material
                    Ps, ns = Po[sel], nv[sel]
                    out[sel] = self._shade(scene, T_world_ecm, o, (Ps[:, 0], Ps[:, 1], Ps[:, 2]),
                                           (ns[:, 0], ns[:, 1], ns[:, 2]),
                                           np.asarray(m.rgb, np.float32) * np.float32(m.kd),
                                           np.asarray(m.spec_rgb, np.float32) * np.float32(m.ks), m.shininess, m.env)
                rgb[js, is_] = out
        return rgb, label, depth

    def _shade(self, scene: AltScene, T_world_ecm, eye, P: tuple, n: tuple, albedo, ks_rgb, shininess: float,
               env: float) -> np.ndarray:
        """Linear RGB (..., 3) of surface points P with unit normals n (both as three component
        arrays), seen from ``eye``: ambient + Lambert + Blinn-Phong per light (inverse-square
        fall-off, cos^k cone about the optical axis), plus, for ``env`` > 0, the surroundings
        mirrored (``env_low`` below the horizon, ``env_high`` above) lit like the point."""
        f32 = np.float32
        axis = (-T_world_ecm[:3, 2]).astype(np.float32)
        ref = float(np.linalg.norm(scene.needle_centre - T_world_ecm[:3, 3]))
        vx, vy, vz = eye[0] - P[0], eye[1] - P[1], eye[2] - P[2]
        inv = 1.0 / np.sqrt(np.maximum(vx * vx + vy * vy + vz * vz, f32(1e-18)))  # a point at the eye: no view direction
        vx, vy, vz = vx * inv, vy * inv, vz * inv
        diff = [0.0, 0.0, 0.0]
        spec = [0.0, 0.0, 0.0]
        irr = 0.0
        for L in scene.lights:
            lp = transform_points(T_world_ecm, np.asarray(L.offset_ecm, float)[None])[0].astype(np.float32)
            lx, ly, lz = lp[0] - P[0], lp[1] - P[1], lp[2] - P[2]
            d2 = lx * lx + ly * ly + lz * lz
            inv = 1.0 / np.sqrt(d2)
            lx, ly, lz = lx * inv, ly * inv, lz * inv
            cone = np.clip(-(lx * axis[0] + ly * axis[1] + lz * axis[2]), 0.0, 1.0) ** f32(scene.spot_exponent)
            e = f32(L.intensity * scene.exposure * ref * ref) * cone / d2
            ndl = np.clip(n[0] * lx + n[1] * ly + n[2] * lz, 0.0, None)
            hx, hy, hz = lx + vx, ly + vy, lz + vz
            ndh = np.clip((n[0] * hx + n[1] * hy + n[2] * hz) / np.sqrt(hx * hx + hy * hy + hz * hz + f32(1e-12)),
                          0.0, 1.0)
            ed = e * ndl
            es = np.where(ndl > 0, e * ndh ** f32(shininess), f32(0.0))
            for ch in range(3):
                diff[ch] = diff[ch] + ed * f32(L.rgb[ch])
                spec[ch] = spec[ch] + es * f32(L.rgb[ch])
            irr = irr + e
        albedo = np.asarray(albedo, np.float32)
        amb = f32(scene.ambient)
        if env > 0:
            nv = n[0] * vx + n[1] * vy + n[2] * vz
            rz = 2 * nv * n[2] - vz                          # world z of the mirrored view ray
            k = np.clip(0.5 + 0.5 * rz, 0.0, 1.0)
            lo, hi = np.asarray(scene.env_low, np.float32), np.asarray(scene.env_high, np.float32)
        out = np.empty(np.shape(P[0]) + (3,), np.float32)
        for ch in range(3):
            a = albedo[..., ch]
            v = a * (amb + diff[ch]) + f32(ks_rgb[ch]) * spec[ch]
            if env > 0:
                v = v + f32(env * ks_rgb[ch]) * (lo[ch] + k * (hi[ch] - lo[ch])) * irr
            out[..., ch] = v
        return out

    # ------------------------------------------------------------ ground truth

    def ground_truth(self, scene: AltScene, T_world_ecm: np.ndarray, renders: dict) -> dict:
        """keypoints / visible / bbox per camera (the spec's fields) from the exact projection
        of the needle model's A..E and the renders' z-buffers and labels."""
        needle = scene.needle
        a0, a1 = needle.arc_span_rad
        T_ecm_needle = inv_T(T_world_ecm) @ scene.T_world_needle
        coarse = []
        for c in CAMERAS:
            p = transform_points(self.rig[c].T_cam_ecm @ T_ecm_needle, needle.sample_arc(LENGTH_SAMPLES))
            coarse.append(np.where(p[:, 2:] > 0, self.rig[c].project(p), np.nan))
        angles, at = arc_angles((a0, a1), coarse, needle.keypoint_angles_rad)
        radii = scene.needle_shape.radius_at(needle, needle.radius_m * np.abs(angles - a0))
        arc_m = needle.radius_m * (angles - angles[0])
        at_thread = needle.radius_m * np.abs(angles - a1) <= scene.needle_shape.swage_length_m
        p_needle = needle.arc_points(angles)
        p_world = transform_points(scene.T_world_needle, p_needle)
        buried = p_world[:, 2] < scene.tissue.height(p_world[:, 0], p_world[:, 1]) - radii
        kps, vis, boxes = {}, {}, {}
        for c in CAMERAS:
            cam = self.rig[c]
            p = transform_points(cam.T_cam_ecm @ T_ecm_needle, p_needle)
            uv = cam.project(p)
            inside = cam.in_image(uv) & (p[:, 2] > 0)
            r = renders[c]
            seen = visible_along_arc(uv, p[:, 2], arc_m, radii, inside, buried, r.label, LABELS["needle"], r.depth,
                                     cam.K[0, 0], LABELS["thread"], at_thread)
            ys, xs = np.nonzero(r.label == LABELS["needle"])
            boxes[c] = None if len(xs) == 0 else [float(xs.min()) - 0.5, float(ys.min()) - 0.5,
                                                  float(xs.max()) + 0.5, float(ys.max()) + 0.5]
            kps[c], vis[c] = uv[at], seen[at]
        return {"keypoints": kps, "visible": vis, "bbox": boxes}


def _smooth_object_edges(rgb: np.ndarray, label: np.ndarray) -> np.ndarray:
    """Cheap anti-aliasing: pixels on a label boundary take a 3x3 mean of their neighbourhood."""
    edge = np.zeros(label.shape, bool)
    edge[:, 1:] |= label[:, 1:] != label[:, :-1]
    edge[:, :-1] |= label[:, 1:] != label[:, :-1]
    edge[1:] |= label[1:] != label[:-1]
    edge[:-1] |= label[1:] != label[:-1]
    if edge.any():
        blur = cv2.blur(rgb, (3, 3))
        rgb = rgb.copy()
        rgb[edge] = 0.5 * rgb[edge] + 0.5 * blur[edge]
    return rgb
