"""The built-in suturing scene: an MJCF model with procedurally generated meshes and textures.

World frame: the table top at z = 0, z up; a tissue phantom pad centred on the origin. The
needle, the endoscope (ECM) and the two instruments are mocap bodies, so their poses are set
per frame without simulating dynamics. The ECM body carries the left/right cameras and the
endoscope's lights. A MuJoCo camera looks along its -z with y up; the OpenCV camera frame
(x right, y down, z forward) is that frame rotated by pi about x. Since the built-in rig has
``T_ecm_cam = diag(1, -1, -1)`` (plus the baseline offset), the MuJoCo cameras are simply the
ECM frame shifted along x. All lengths in metres.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import R_to_quat, make_T, transform_points

# Phantom pad: size (x, y) and nominal top height above the table (m).
PHANTOM_SIZE = (0.12, 0.10)
PHANTOM_TOP = 0.012
PHANTOM_BUMP = 0.0006  # amplitude of the surface undulation (m)


# ---------------------------------------------------------------- geometry helpers

def phantom_height(x, y) -> np.ndarray:
    """Height (m, world z) of the phantom's top surface at world (x, y): a gentle undulation."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    return (PHANTOM_TOP
            + PHANTOM_BUMP * 0.6 * np.sin(x * 55.0 + 0.4) * np.cos(y * 47.0 - 0.4)
            + PHANTOM_BUMP * 0.4 * np.sin(x * 23.0 - y * 31.0 + 0.8))


def _perp(v: np.ndarray) -> np.ndarray:
    a = np.array([1.0, 0, 0]) if abs(v[0]) < 0.9 else np.array([0, 1.0, 0])
    p = np.cross(v, a)
    return p / np.linalg.norm(p)


def sweep_tube(points: np.ndarray, radii: np.ndarray, n_ring: int = 16,
               cap_start: bool = True, cap_end: bool = True):
    """Triangle mesh of a tube of varying radius swept along a polyline (parallel transport).

    A zero radius at either end makes a sharp apex there; otherwise the end is closed with a
    flat cap if asked. Returns (vertices (N,3), normals (N,3), faces (M,3) int).
    """
    P = np.asarray(points, dtype=float)
    r = np.asarray(radii, dtype=float)
    n = len(P)
    T = np.gradient(P, axis=0)
    T /= np.linalg.norm(T, axis=1, keepdims=True)
    N = np.empty_like(P)
    N[0] = _perp(T[0])
    for i in range(1, n):  # parallel transport of the normal
        v = N[i - 1] - np.dot(N[i - 1], T[i]) * T[i]
        N[i] = v / np.linalg.norm(v)
    B = np.cross(T, N)
    phi = np.linspace(0, 2 * np.pi, n_ring, endpoint=False)
    verts, norms, faces = [], [], []
    ring_index = []
    for i in range(n):
        if r[i] <= 0:
            ring_index.append(len(verts))
            verts.append(P[i])
            norms.append(T[i] * (1 if i == n - 1 else -1))
            continue
        d = np.cos(phi)[:, None] * N[i] + np.sin(phi)[:, None] * B[i]
        ring_index.append(len(verts))
        verts.extend(P[i] + r[i] * d)
        norms.extend(d)
    for i in range(n - 1):
        a, b = ring_index[i], ring_index[i + 1]
        for j in range(n_ring):
            j1 = (j + 1) % n_ring
            if r[i] <= 0:
                faces.append((a, b + j1, b + j))
            elif r[i + 1] <= 0:
                faces.append((a + j, a + j1, b))
            else:
                faces.append((a + j, a + j1, b + j1))
                faces.append((a + j, b + j1, b + j))
    for end, flag in ((0, cap_start), (n - 1, cap_end)):
        if not flag or r[end] <= 0:
            continue
        sgn = -1.0 if end == 0 else 1.0
        c = len(verts)
        verts.append(P[end])
        norms.append(sgn * T[end])
        base = len(verts)
        d = np.cos(phi)[:, None] * N[end] + np.sin(phi)[:, None] * B[end]
        verts.extend(P[end] + r[end] * d)
        norms.extend([sgn * T[end]] * n_ring)
        for j in range(n_ring):
            j1 = (j + 1) % n_ring
            faces.append((c, base + j1, base + j) if end == 0 else (c, base + j, base + j1))
    return np.asarray(verts), np.asarray(norms), np.asarray(faces, dtype=np.int64)


def needle_mesh(needle: NeedleModel, wire_diameter_m: float | None = None, tip_length_m: float = 0.0018,
                n_arc: int = 120, n_ring: int = 16, tip_exponent: float = 0.75, swage_scale: float = 1.08):
    """The needle body in the needle frame: a wire swept along the arc from A (tip) to E (tail).

    The last ``tip_length_m`` before A taper to a sharp point exactly at A (radius ~ distance **
    ``tip_exponent``: < 1 a convex, blunter taper); the tail at E is a blunt swage ``swage_scale``
    x thicker over its last 1.5 mm, closed by a flat cap exactly at E.
    """
    rw = 0.5 * (wire_diameter_m or needle.wire_diameter_m)
    a0, a1 = needle.arc_span_rad
    arc_len = needle.radius_m * abs(a1 - a0)
    s = np.linspace(0.0, 1.0, n_arc) ** 1.0
    # denser sampling near the tip so the taper is smooth
    s = np.unique(np.concatenate([s, np.linspace(0, min(1.0, 2 * tip_length_m / arc_len), 30)]))
    ang = a0 + s * (a1 - a0)
    pts = needle.arc_points(ang)
    dist = s * arc_len
    radii = np.full(len(s), rw)
    tip = dist < tip_length_m
    radii[tip] = rw * (dist[tip] / tip_length_m) ** tip_exponent
    radii[dist > arc_len - 0.0015] = rw * swage_scale
    return sweep_tube(pts, radii, n_ring, cap_start=False, cap_end=True)


def smooth_polyline(ctrl: np.ndarray, step: float, n_points: int = 0) -> np.ndarray:
    """Chaikin-smoothed polyline through control points (m), resampled evenly every ``step``
    or, if given, at exactly ``n_points`` points."""
    P = np.asarray(ctrl, dtype=float)
    for _ in range(4):
        Q = 0.75 * P[:-1] + 0.25 * P[1:]
        R = 0.25 * P[:-1] + 0.75 * P[1:]
        P = np.vstack([P[:1], np.stack([Q, R], 1).reshape(-1, 3), P[-1:]])
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    s = np.concatenate([[0], np.cumsum(seg)])
    n = n_points if n_points >= 2 else max(2, int(s[-1] / step) + 1)
    t = np.linspace(0, s[-1], n)
    return np.stack([np.interp(t, s, P[:, k]) for k in range(3)], axis=1)


def thread_path(T_world_needle: np.ndarray, needle: NeedleModel, rng: np.random.Generator,
                length_m: float = 0.06, radius_m: float = 0.00018, n_points: int = 0) -> np.ndarray:
    """World-frame centreline of the suture thread: leaves the tail E along the arc's tangent,
    falls to the phantom and meanders over it."""
    a_e = needle.arc_span_rad[1]
    E = transform_points(T_world_needle, needle.arc_points([a_e]))[0]
    t_n = np.array([-np.sin(a_e), np.cos(a_e), 0.0])  # tangent pointing away from the arc
    t_w = T_world_needle[:3, :3] @ t_n
    ctrl = [E, E + 0.003 * t_w]
    heading = np.arctan2(t_w[1], t_w[0]) + rng.uniform(-0.6, 0.6)
    p = E + 0.003 * t_w + np.array([np.cos(heading), np.sin(heading), 0]) * 0.006
    hx, hy = PHANTOM_SIZE[0] / 2 - 0.004, PHANTOM_SIZE[1] / 2 - 0.004
    travelled = 0.009
    while travelled < length_m:
        p = p.copy()
        p[0], p[1] = np.clip(p[0], -hx, hx), np.clip(p[1], -hy, hy)
        p[2] = float(phantom_height(p[0], p[1])) + radius_m
        ctrl.append(p)
        heading += rng.normal(0, 0.7)
        step = rng.uniform(0.006, 0.012)
        nxt = p + step * np.array([np.cos(heading), np.sin(heading), 0])
        if abs(nxt[0]) > hx or abs(nxt[1]) > hy:  # turn back towards the pad's centre
            heading = np.arctan2(-p[1], -p[0]) + rng.uniform(-0.5, 0.5)
            nxt = p + step * np.array([np.cos(heading), np.sin(heading), 0])
        p = nxt
        travelled += step
    path = smooth_polyline(np.asarray(ctrl), 0.0005, n_points)
    # keep the part on the pad above the (undulating) surface
    zmin = phantom_height(path[:, 0], path[:, 1]) + radius_m
    path[:, 2] = np.maximum(path[:, 2], zmin)
    return path


def phantom_mesh(nx: int = 97, ny: int = 81):
    """The phantom's top surface (world frame) with texture coordinates: (verts, texcoords, faces)."""
    sx, sy = PHANTOM_SIZE
    xs = np.linspace(-sx / 2, sx / 2, nx)
    ys = np.linspace(-sy / 2, sy / 2, ny)
    X, Y = np.meshgrid(xs, ys)
    Z = phantom_height(X, Y)
    # round the rim down to the pad's sides
    edge = np.minimum.reduce([X + sx / 2, sx / 2 - X, Y + sy / 2, sy / 2 - Y])
    Z = np.where(edge < 0.003, Z - (0.003 - edge) * 1.5, Z)
    verts = np.stack([X, Y, Z], -1).reshape(-1, 3)
    uv = np.stack([(X + sx / 2) / sx, 1.0 - (Y + sy / 2) / sy], -1).reshape(-1, 2)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return verts, uv, faces


# ---------------------------------------------------------------- textures

def _noise(rng, shape, scale):
    """Smooth value noise in [0, 1] of the given shape, feature size ~ ``scale`` pixels."""
    h, w = shape
    small = rng.random((max(2, int(h / scale)) + 1, max(2, int(w / scale)) + 1)).astype(np.float32)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)


def tissue_texture(seed: int, size: int = 1024, vessels: int = 6) -> np.ndarray:
    """Procedural tissue texture (RGB uint8, size x size), near white: the material's colour tints
    it. Shading noise, fibres, darker-red vessels and red square entry/exit marks.

    Row 0 lies along the pad's +y edge, column 0 along its -x edge.
    """
    rng = np.random.default_rng(seed)
    n = (0.45 * _noise(rng, (size, size), 160 * size / 1024) + 0.3 * _noise(rng, (size, size), 40 * size / 1024)
         + 0.25 * _noise(rng, (size, size), 8 * size / 1024))
    fib = cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), sigmaX=9 * size / 1024,
                           sigmaY=1.2 * size / 1024)
    fib = (fib - fib.mean()) / (fib.std() + 1e-6)
    shade = 0.95 + 0.3 * (n - 0.5) + 0.035 * fib
    vess = np.zeros((size, size), np.float32)
    step = 12 * size / 1024
    for _ in range(vessels):
        p = rng.uniform(0, size, 2)
        ang = rng.uniform(0, 2 * np.pi)
        pts = []
        for _ in range(30):
            pts.append(p.copy())
            ang += rng.normal(0, 0.25)
            p = p + step * np.array([np.cos(ang), np.sin(ang)])
        cv2.polylines(vess, [np.int32(pts)], False, float(rng.uniform(0.3, 0.7)),
                      thickness=max(1, int(rng.integers(1, 4) * size / 1024)), lineType=cv2.LINE_AA)
    vess = cv2.GaussianBlur(vess, (0, 0), 1.2 * size / 1024)
    img = shade[..., None] * (1 - vess[..., None] * np.array([0.25, 0.55, 0.5], np.float32))
    img = (np.clip(img, 0, 1) * 255).astype(np.uint8)
    m = max(3, int(round(size * 0.003 / PHANTOM_SIZE[0])))  # 3 mm squares
    for r in np.linspace(0.25, 0.75, 3):
        for cx in (0.3, 0.7):
            x = int((cx + rng.uniform(-0.03, 0.03)) * size)
            y = int((r + rng.uniform(-0.03, 0.03)) * size)
            cv2.rectangle(img, (x - m // 2, y - m // 2), (x + m // 2, y + m // 2), (215, 30, 36), -1, cv2.LINE_AA)
            h = max(1, m // 5)
            cv2.rectangle(img, (x - h, y - h), (x + h, y + h), (110, 12, 18), -1)
    return img


def table_texture(seed: int, size: int = 256) -> np.ndarray:
    """Drape-like background texture (RGB uint8, near white: tinted by the material)."""
    rng = np.random.default_rng(seed)
    n = 0.7 + 0.3 * _noise(rng, (size, size), 30) + 0.1 * (rng.random((size, size)) - 0.5)
    return (np.clip(np.repeat(n[..., None], 3, axis=2), 0, 1) * 255).astype(np.uint8)


_TEXTURE_CACHE: dict = {}
TEXTURE_VARIANTS = 16  # distinct tissue patterns a process keeps (generating one takes ~0.3 s)


def cached_texture(kind: str, seed: int, size: int) -> np.ndarray:
    key = (kind, seed % TEXTURE_VARIANTS, size)
    if key not in _TEXTURE_CACHE:
        fn = tissue_texture if kind == "tissue" else table_texture
        _TEXTURE_CACHE[key] = fn(seed % TEXTURE_VARIANTS, size)
    return _TEXTURE_CACHE[key]


# ---------------------------------------------------------------- scene description

@dataclass
class Appearance:
    """Everything about how the scene looks (colours 0..1, lengths in m)."""

    tissue_rgb: tuple = (0.86, 0.52, 0.50)
    tissue_specular: float = 0.35
    tissue_shininess: float = 0.25
    table_rgb: tuple = (0.12, 0.16, 0.14)
    needle_rgb: tuple = (0.78, 0.78, 0.80)
    needle_specular: float = 0.9
    needle_shininess: float = 0.85
    needle_reflectance: float = 0.0
    wire_diameter_m: float = 0.0008
    tip_length_m: float = 0.0018
    tip_exponent: float = 0.75
    swage_scale: float = 1.08
    thread_rgb: tuple = (0.35, 0.15, 0.55)
    thread_diameter_m: float = 0.00035
    thread_length_m: float = 0.06
    thread_visible: bool = True  # False: no thread drawn (the threadless looks)
    light_diffuse: float = 0.75
    light_rgb: tuple = (1.0, 0.97, 0.92)
    light_offset: tuple = (0.0, 0.004, 0.0)  # position of the scope's light in the ECM frame
    ambient: float = 0.12
    shadows: bool = False  # cast shadows: about 3x the rendering time on the CPU
    texture_seed: int = 0


JAW_PIVOT_M = 0.0045
"""Distance of the jaws' pivot from the instrument body's origin (m), along the shaft."""

T_BODY_JAW = np.array([[0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, JAW_PIVOT_M], [0, 0, 0, 1.0]])
"""The jaw frame of ``docs/dataset.md`` in the instrument body (whose z runs up the shaft and whose
x the jaws turn about): origin at the pivot, z along the closed jaws towards their tips, y the
axis they open about, x = y cross z."""


@dataclass
class Instrument:
    """A patient-side instrument: the body's origin near the jaw tips (world), shaft direction from
    there towards the trocar (world unit vector), roll about the shaft (rad) and jaw opening (rad,
    0 closed). ``T_world_jaw`` is its jaw frame (``T_BODY_JAW``); ``from_jaw`` the inverse."""

    tip: tuple
    shaft_dir: tuple
    roll: float = 0.0
    jaw_open: float = 0.3

    @property
    def T_world_body(self) -> np.ndarray:
        return make_T(_frame_from_z(np.asarray(self.shaft_dir, float), self.roll), self.tip)

    @property
    def T_world_jaw(self) -> np.ndarray:
        return self.T_world_body @ T_BODY_JAW

    @classmethod
    def from_jaw(cls, T_world_jaw: np.ndarray, jaw_rad: float) -> "Instrument":
        """The instrument whose jaw frame is ``T_world_jaw`` (4x4, world), opened ``jaw_rad``."""
        T_wb = np.asarray(T_world_jaw, float) @ np.linalg.inv(T_BODY_JAW)
        z = T_wb[:3, 2]
        x0 = _perp(z)
        y0 = np.cross(z, x0)
        x = T_wb[:3, 0]
        return cls(tuple(T_wb[:3, 3]), tuple(z), float(np.arctan2(x @ y0, x @ x0)), float(jaw_rad))


@dataclass
class SceneSpec:
    """A complete scene: rig, needle model, needle pose, appearance, up to two instruments."""

    rig: StereoRig = field(default_factory=StereoRig.default)
    needle: NeedleModel = field(default_factory=NeedleModel)
    T_world_needle: np.ndarray = field(default_factory=lambda: make_T(np.eye(3), [0, 0, 0.02]))
    appearance: Appearance = field(default_factory=Appearance)
    instruments: list = field(default_factory=list)
    thread_seed: int = 0
    markers: list = field(default_factory=list)  # (x, y, z, radius) world spheres, for calibration tests
    texture_size: int = 1024
    msaa: int = 4  # multisample anti-aliasing (0 = off: ~2.5x faster on the CPU, jagged thin wires)


MAX_INSTRUMENTS = 2
THREAD_POINTS = 240
_HIDDEN = np.array([0.0, 0.0, -5.0])  # where unused instruments wait, out of sight under the table


def _fmt(a) -> str:
    return " ".join(f"{v:.9g}" for v in np.asarray(a, dtype=float).reshape(-1))


def _frame_from_z(z: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """Rotation of a frame whose z axis is ``z`` (unit), rolled about it."""
    z = np.asarray(z, dtype=float)
    z = z / np.linalg.norm(z)
    x = _perp(z)
    y = np.cross(z, x)
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    return np.stack([x, y, z], axis=1)


def _quat_from_z(z: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """Quaternion [w,x,y,z] of a frame whose z axis is ``z`` (unit), rolled about it."""
    return R_to_quat(_frame_from_z(z, roll))


def rig_check(rig: StereoRig) -> None:
    """The MuJoCo cameras render an ideal centred pinhole along -z: refuse rigs they cannot render."""
    for cam in rig.cameras:
        K = cam.K
        w, h = cam.width, cam.height
        if (abs(K[0, 0] - K[1, 1]) > 1e-9 * K[0, 0] or abs(K[0, 2] - (w - 1) / 2) > 1e-9
                or abs(K[1, 2] - (h - 1) / 2) > 1e-9 or K[0, 1] != 0 or np.any(cam.dist)):
            raise ValueError(f"sim: camera {cam.name} must be an undistorted centred pinhole with "
                             f"square pixels (got K={K.tolist()})")
        R = cam.T_ecm_cam[:3, :3]
        if not np.allclose(R, np.diag([1.0, -1.0, -1.0]), atol=1e-9):
            raise ValueError(f"sim: camera {cam.name} must look along -z_ecm (T_ecm_cam rotation "
                             f"diag(1,-1,-1)), got {R.tolist()}")


def _mesh_xml(name: str, v, n, f, uv=None) -> str:
    tex = f' texcoord="{_fmt(uv)}"' if uv is not None else ""
    return (f'<mesh name="{name}" inertia="shell" vertex="{_fmt(v)}" normal="{_fmt(n)}"{tex} '
            f'face="{" ".join(map(str, np.asarray(f).reshape(-1)))}"/>')


def structure_key(spec: SceneSpec) -> tuple:
    """What fixes the compiled model; scenes with the same key share it (see SceneModel.apply)."""
    rig = spec.rig
    return (rig.left.width, rig.left.height, float(rig.left.K[1, 1]),
            tuple(rig.left.T_ecm_cam[:3, 3]), tuple(rig.right.T_ecm_cam[:3, 3]),
            len(spec.markers), spec.texture_size, spec.needle, int(spec.msaa))


def build_mjcf(spec: SceneSpec) -> str:
    """MJCF of the scene's structure. Everything that varies between scenes (poses, meshes of the
    needle and thread, colours, textures, lights) is written into the compiled model by
    ``SceneModel.apply``; the values here are placeholders."""
    rig = spec.rig
    rig_check(rig)
    w, h = rig.left.width, rig.left.height
    fovy_deg = np.rad2deg(2 * np.arctan((h / 2) / rig.left.K[1, 1]))
    nv, nn, nf = needle_mesh(spec.needle, spec.needle.wire_diameter_m)
    line = np.stack([np.linspace(0, 0.05, THREAD_POINTS), np.zeros(THREAD_POINTS), np.zeros(THREAD_POINTS)], 1)
    tv, tn, tf = sweep_tube(line, np.full(THREAD_POINTS, 0.0002), 8)
    pv, puv, pf = phantom_mesh()
    sx, sy = PHANTOM_SIZE
    ts = spec.texture_size
    inst = []
    for i in range(MAX_INSTRUMENTS):
        inst.append(f"""
    <body name="instrument{i}" mocap="true" pos="{_fmt(_HIDDEN)}">
      <geom name="instrument{i}_shaft" type="cylinder" fromto="0 0 0.011 0 0 0.25" size="0.0042" material="shaft"/>
      <geom name="instrument{i}_wrist" type="cylinder" fromto="0 0 {JAW_PIVOT_M} 0 0 0.011" size="0.0032" material="jaw"/>
      <geom name="instrument{i}_pin" type="cylinder" fromto="-0.0028 0 {JAW_PIVOT_M} 0.0028 0 {JAW_PIVOT_M}" size="0.0012" material="jaw"/>
      <body name="instrument{i}_jawbody0" pos="0 0 {JAW_PIVOT_M}"><geom name="instrument{i}_jaw0" type="box" pos="0 0.0006 -0.0035" size="0.0011 0.0005 0.0036" material="jaw"/></body>
      <body name="instrument{i}_jawbody1" pos="0 0 {JAW_PIVOT_M}"><geom name="instrument{i}_jaw1" type="box" pos="0 -0.0006 -0.0035" size="0.0011 0.0005 0.0036" material="jaw"/></body>
    </body>""")
    markers = [f"""
    <geom name="marker{i}" type="sphere" pos="0 0 -5" size="0.001" rgba="0.1 0.9 0.2 1"/>"""
               for i in range(len(spec.markers))]
    cams = "\n".join(f'      <camera name="{c.name}" pos="{_fmt(c.T_ecm_cam[:3, 3])}" fovy="{fovy_deg:.12g}"/>'
                     for c in rig.cameras)
    return f"""<mujoco model="needletrack_suturing">
  <compiler angle="radian" inertiafromgeom="false"/>
  <statistic extent="1" center="0 0 0.05"/>
  <visual>
    <global offwidth="{w}" offheight="{h}"/>
    <map znear="0.002" zfar="3"/>
    <quality shadowsize="2048" offsamples="{int(spec.msaa)}"/>
    <headlight ambient="0.1 0.1 0.1" diffuse="0 0 0" specular="0 0 0"/>
  </visual>
  <asset>
    <texture name="tissue" type="2d" builtin="flat" rgb1="1 1 1" width="{ts}" height="{ts}"/>
    <texture name="table" type="2d" builtin="flat" rgb1="1 1 1" width="256" height="256"/>
    <material name="tissue" texture="tissue"/>
    <material name="tissue_side"/>
    <material name="table" texture="table" texrepeat="4 4" specular="0.05"/>
    <material name="needle"/>
    <material name="thread"/>
    <material name="shaft" rgba="0.08 0.08 0.09 1" specular="0.5" shininess="0.6"/>
    <material name="jaw" rgba="0.62 0.63 0.66 1" specular="0.8" shininess="0.8"/>
    {_mesh_xml("needle", nv, nn, nf)}
    {_mesh_xml("thread", tv, tn, tf)}
    {_mesh_xml("phantom", pv, np.tile([0.0, 0.0, 1.0], (len(pv), 1)), pf, puv)}
  </asset>
  <worldbody>
    <geom name="table" type="box" size="0.4 0.3 0.002" pos="0 0 -0.002" material="table"/>
    <geom name="phantom_body" type="box" size="{sx / 2 - 0.003:.6f} {sy / 2 - 0.003:.6f} {PHANTOM_TOP / 2 - 0.001:.6f}" pos="0 0 {PHANTOM_TOP / 2 - 0.001:.6f}" material="tissue_side"/>
    <geom name="phantom" type="mesh" mesh="phantom" material="tissue"/>
    <geom name="thread" type="mesh" mesh="thread" material="thread"/>
    <body name="needle" mocap="true">
      <geom name="needle" type="mesh" mesh="needle" material="needle"/>
    </body>
    <body name="ecm" mocap="true" pos="0 0 0.3">
{cams}
      <light name="scope_light" pos="0 0.004 0" dir="0 0 -1" castshadow="true" cutoff="70" exponent="2"/>
      <light name="scope_fill" pos="0 -0.004 0" dir="0 0 -1" specular="0 0 0" castshadow="false" cutoff="80" exponent="1"/>
    </body>{''.join(inst)}{''.join(markers)}
  </worldbody>
</mujoco>
"""


class SceneModel:
    """A compiled scene whose varying parts are rewritten in place by ``apply(spec)``, so one model
    (and one render context) serves every scene with the same ``structure_key``."""

    def __init__(self, spec: SceneSpec):
        import mujoco
        self._mj = mujoco
        self.key = structure_key(spec)
        self.model = mujoco.MjModel.from_xml_string(build_mjcf(spec))
        m = self.model
        ids = lambda kind, name: mujoco.mj_name2id(m, kind, name)  # noqa: E731
        G, B, M, T, MAT, L = (mujoco.mjtObj.mjOBJ_GEOM, mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_MESH,
                              mujoco.mjtObj.mjOBJ_TEXTURE, mujoco.mjtObj.mjOBJ_MATERIAL, mujoco.mjtObj.mjOBJ_LIGHT)
        self.mesh = {n: ids(M, n) for n in ("needle", "thread", "phantom")}
        self.tex = {n: ids(T, n) for n in ("tissue", "table")}
        self.mat = {n: ids(MAT, n) for n in ("tissue", "tissue_side", "table", "needle", "thread")}
        self.light = {n: ids(L, n) for n in ("scope_light", "scope_fill")}
        self.mocap = {n: int(m.body_mocapid[ids(B, n)]) for n in
                      ["needle", "ecm"] + [f"instrument{i}" for i in range(MAX_INSTRUMENTS)]}
        self.jaws = [(ids(B, f"instrument{i}_jawbody0"), ids(B, f"instrument{i}_jawbody1"))
                     for i in range(MAX_INSTRUMENTS)]
        self.markers = [ids(G, f"marker{i}") for i in range(len(spec.markers))]
        # needle and thread vertices are written in their body frames: undo the compiler's
        # re-centring of those meshes
        for name in ("needle", "thread"):
            g = ids(G, name)
            m.geom_pos[g] = 0.0
            m.geom_quat[g] = [1.0, 0.0, 0.0, 0.0]
            m.geom_rbound[g] = 1.0
            m.geom_aabb[g] = [0, 0, 0, 1, 1, 1]
        self._tex_state = {}
        self._mesh_state = {}

    def _write_mesh(self, name: str, verts, normals, state) -> bool:
        if self._mesh_state.get(name) == state:
            return False
        m, k = self.model, self.mesh[name]
        va, vn = m.mesh_vertadr[k], m.mesh_vertnum[k]
        na, nn = m.mesh_normaladr[k], m.mesh_normalnum[k]
        if len(verts) != vn or len(normals) != nn:
            raise AssertionError(f"mesh {name}: {len(verts)} vertices for {vn} slots")
        m.mesh_vert[va:va + vn] = verts
        m.mesh_normal[na:na + nn] = normals
        self._mesh_state[name] = state
        return True

    def _write_texture(self, name: str, rgb: np.ndarray, state) -> bool:
        if self._tex_state.get(name) == state:
            return False
        m, k = self.model, self.tex[name]
        adr, n = m.tex_adr[k], m.tex_width[k] * m.tex_height[k] * m.tex_nchannel[k]
        m.tex_data[adr:adr + n] = rgb.reshape(-1)
        self._tex_state[name] = state
        return True

    def apply(self, spec: SceneSpec) -> tuple[list, list]:
        """Write the scene's varying parts; returns (mesh ids, texture ids) to re-upload."""
        if structure_key(spec) != self.key:
            raise ValueError("scene: structure differs from the compiled model")
        m, ap = self.model, spec.appearance
        meshes, textures = [], []
        shape = (ap.wire_diameter_m, ap.tip_length_m, ap.tip_exponent, ap.swage_scale)
        if self._write_mesh("needle", *needle_mesh(spec.needle, ap.wire_diameter_m, ap.tip_length_m,
                                                   tip_exponent=ap.tip_exponent,
                                                   swage_scale=ap.swage_scale)[:2], state=shape):
            meshes.append(self.mesh["needle"])
        tstate = (spec.thread_seed, ap.thread_length_m, ap.thread_diameter_m, spec.T_world_needle.tobytes())
        if self._mesh_state.get("thread") != tstate:
            path = thread_path(spec.T_world_needle, spec.needle, np.random.default_rng(spec.thread_seed),
                               ap.thread_length_m, ap.thread_diameter_m / 2, THREAD_POINTS)
            tv, tn, _ = sweep_tube(path, np.full(len(path), ap.thread_diameter_m / 2), 8)
            self._write_mesh("thread", tv, tn, tstate)
            meshes.append(self.mesh["thread"])
        if self._write_texture("tissue", cached_texture("tissue", ap.texture_seed, spec.texture_size),
                               ("tissue", ap.texture_seed % TEXTURE_VARIANTS)):
            textures.append(self.tex["tissue"])
        if self._write_texture("table", cached_texture("table", ap.texture_seed + 7, 256),
                               ("table", (ap.texture_seed + 7) % TEXTURE_VARIANTS)):
            textures.append(self.tex["table"])
        mat = self.mat
        m.mat_rgba[mat["tissue"]] = [*ap.tissue_rgb, 1]
        m.mat_specular[mat["tissue"]] = ap.tissue_specular
        m.mat_shininess[mat["tissue"]] = ap.tissue_shininess
        m.mat_rgba[mat["tissue_side"]] = [*(np.asarray(ap.tissue_rgb) * 0.7), 1]
        m.mat_specular[mat["tissue_side"]] = 0.2
        m.mat_rgba[mat["table"]] = [*ap.table_rgb, 1]
        m.mat_rgba[mat["needle"]] = [*ap.needle_rgb, 1]
        m.mat_specular[mat["needle"]] = ap.needle_specular
        m.mat_shininess[mat["needle"]] = ap.needle_shininess
        m.mat_reflectance[mat["needle"]] = ap.needle_reflectance
        m.mat_rgba[mat["thread"]] = [*ap.thread_rgb, 1.0 if ap.thread_visible else 0.0]
        m.mat_specular[mat["thread"]] = 0.15
        m.mat_shininess[mat["thread"]] = 0.2
        rgb = np.asarray(ap.light_rgb) * ap.light_diffuse
        lo = np.asarray(ap.light_offset, dtype=float)
        key, fill = self.light["scope_light"], self.light["scope_fill"]
        m.light_pos[key], m.light_pos0[key] = lo, lo
        m.light_diffuse[key], m.light_specular[key] = rgb, rgb * 0.9
        m.light_castshadow[key] = bool(ap.shadows)
        m.light_pos[fill], m.light_pos0[fill] = -lo, -lo
        m.light_diffuse[fill] = rgb * 0.35
        m.vis.headlight.ambient[:] = ap.ambient
        for i, (j0, j1) in enumerate(self.jaws):
            ja = spec.instruments[i].jaw_open / 2 if i < len(spec.instruments) else 0.3
            m.body_quat[j0] = [np.cos(ja / 2), np.sin(ja / 2), 0, 0]
            m.body_quat[j1] = [np.cos(-ja / 2), np.sin(-ja / 2), 0, 0]
        for g, mk in zip(self.markers, spec.markers):
            m.geom_pos[g] = mk[:3]
            m.geom_size[g][0] = mk[3]
            m.geom_rbound[g] = mk[3]
        return meshes, textures

    def set_poses(self, data, spec: SceneSpec) -> None:
        """Mocap poses of the needle and the instruments (the ECM is set per frame)."""
        self.set_mocap(data, "needle", spec.T_world_needle)
        for i in range(MAX_INSTRUMENTS):
            name = f"instrument{i}"
            if i < len(spec.instruments):
                ins = spec.instruments[i]
                data.mocap_pos[self.mocap[name]] = ins.tip
                data.mocap_quat[self.mocap[name]] = _quat_from_z(np.asarray(ins.shaft_dir, float), ins.roll)
            else:
                data.mocap_pos[self.mocap[name]] = _HIDDEN
                data.mocap_quat[self.mocap[name]] = [1, 0, 0, 0]

    def set_mocap(self, data, body: str, T: np.ndarray) -> None:
        i = self.mocap[body]
        data.mocap_pos[i] = T[:3, 3]
        data.mocap_quat[i] = R_to_quat(T[:3, :3])
