"""A second, independent renderer of stereo needle scenes: numpy/OpenCV, no MuJoCo, no GL.

Why: everything the project learns and tunes is seen through the built-in MuJoCo scene
(``common/sim_*.py``). This renderer shares none of its code paths, meshes, textures or shading,
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
visible when it is inside the image, in front of the camera and not occluded (the z-buffer at
its pixel is not nearer than the keypoint minus 1.5 wire radii, or the pixel shows the needle);
``bbox`` is the box of the needle's pixels (pixel centres covered by the needle), edges included.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import cv2
import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T, transform_points

CAMERAS = ("left", "right")
LABELS = {"tissue": 0, "needle": 1, "thread": 2, "instrument": 3, "none": -1}
SUPERSAMPLE = 3            # samples per pixel side in the needle's region
NEAR_M = 0.004             # triangles with a vertex nearer than this are not drawn
_CHUNK = 1 << 20           # candidate samples per rasterisation batch


# ---------------------------------------------------------------- meshes

@dataclass
class Material:
    """Linear-RGB reflectance: diffuse ``rgb`` x ``kd``, Blinn-Phong ``ks`` / ``shininess``
    (highlight coloured by ``spec_rgb``), ``env``: mirror-like reflection of the surroundings."""

    rgb: tuple
    kd: float = 1.0
    ks: float = 0.0
    shininess: float = 20.0
    spec_rgb: tuple = (1.0, 1.0, 1.0)
    env: float = 0.0


@dataclass
class Mesh:
    """Triangles: vertices ``V`` (N, 3) m, faces ``F`` (M, 3), vertex normals ``N`` (N, 3),
    a label (``LABELS``) and a material."""

    V: np.ndarray
    F: np.ndarray
    N: np.ndarray
    label: int
    material: Material

    def transformed(self, T: np.ndarray) -> "Mesh":
        return Mesh(transform_points(T, self.V), self.F, self.N @ T[:3, :3].T, self.label, self.material)


def vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Area-weighted average of the adjacent faces' normals (unit; zero for unused vertices)."""
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N = np.zeros_like(V)
    for k in range(3):
        np.add.at(N, F[:, k], fn)
    n = np.linalg.norm(N, axis=1, keepdims=True)
    return N / np.maximum(n, 1e-30)


def transport_frames(P: np.ndarray, n0=None) -> tuple[np.ndarray, np.ndarray]:
    """Rotation-minimising (parallel-transport) normals and binormals along a polyline (n, 3)."""
    T = np.gradient(P, axis=0)
    T /= np.maximum(np.linalg.norm(T, axis=1, keepdims=True), 1e-30)
    ref = np.asarray(n0, float) if n0 is not None else (
        np.array([0.0, 0.0, 1.0]) if abs(T[0, 2]) < 0.9 else np.array([1.0, 0.0, 0.0]))
    N = np.empty_like(P)
    N[0] = ref - T[0] * (ref @ T[0])
    N[0] /= np.linalg.norm(N[0])
    for i in range(1, len(P)):
        n = N[i - 1] - T[i] * (N[i - 1] @ T[i])
        N[i] = n / max(np.linalg.norm(n), 1e-30)
    return N, np.cross(T, N)


def sweep(P, N, B, ra, rb, n_ring: int, power: float = 2.0, phase: float = 0.0,
          cap_end: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A tube along the polyline ``P`` (n, 3) with a superellipse cross-section: semi-axes
    ``ra`` along ``N`` and ``rb`` along ``B`` (per point), exponent ``power`` (2 = ellipse,
    larger = flatter sides). ``cap_end`` closes the last ring with a flat fan.
    Returns (V, F, vertex normals), normals pointing outwards."""
    n = len(P)
    phi = phase + 2 * np.pi * np.arange(n_ring) / n_ring
    c, s = np.cos(phi), np.sin(phi)
    X = np.sign(c) * np.abs(c) ** (2.0 / power)
    Y = np.sign(s) * np.abs(s) ** (2.0 / power)
    ra, rb = np.broadcast_to(ra, (n,)), np.broadcast_to(rb, (n,))
    V = (P[:, None] + (ra[:, None] * X)[..., None] * N[:, None] + (rb[:, None] * Y)[..., None] * B[:, None]
         ).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n - 1), np.arange(n_ring), indexing="ij")
    a = i * n_ring + j
    b = i * n_ring + (j + 1) % n_ring
    F = np.concatenate([np.stack([a, a + n_ring, b], -1).reshape(-1, 3),
                        np.stack([b, a + n_ring, b + n_ring], -1).reshape(-1, 3)])
    Nv = vertex_normals(V, F)
    out = (X[None, :, None] * N[:, None] + Y[None, :, None] * B[:, None]).reshape(-1, 3)
    Nv *= np.where(np.sum(Nv * out, axis=1) < 0, -1.0, 1.0)[:, None]
    if cap_end:  # its own vertices, so that the rim stays a sharp edge
        t = P[-1] - P[-2]
        t /= np.linalg.norm(t)
        base = len(V)
        ring = V[-n_ring:]
        V = np.concatenate([V, ring, P[-1:]])
        Nv = np.concatenate([Nv, np.repeat(t[None], n_ring + 1, axis=0)])
        k = np.arange(n_ring)
        F = np.concatenate([F, np.stack([base + k, base + (k + 1) % n_ring, np.full(n_ring, base + n_ring)], -1)])
    return V, F, Nv


@dataclass(frozen=True)
class NeedleShape:
    """The mesh of this renderer's needles (not the built-in one): a superellipse cross-section,
    flattened across the arc's plane; a tip tapering over ``tip_length_m`` to a point at A; a
    swage ``swage_scale`` x thicker over the last ``swage_length_m`` ending at E in a dome or a
    chamfer; ``n_ring`` sides, ``n_arc`` samples along the arc."""

    wire_diameter_m: float = 0.0008
    flattening: float = 0.12          # width/thickness = (1 + f/2) / (1 - f/2)
    power: float = 2.6                # superellipse exponent of the cross-section
    tip_length_m: float = 0.0028
    tip_exponent: float = 0.85
    swage_scale: float = 1.2
    swage_length_m: float = 0.0016
    tail: str = "dome"                # "dome" | "chamfer"
    n_ring: int = 10
    n_arc: int = 72
    phase: float = 0.0

    @property
    def max_radius_m(self) -> float:
        """Largest distance of the surface from the arc (the superellipse's corners included)."""
        corner = np.sqrt(2.0 ** max(1.0 - 2.0 / self.power, 0.0))
        return 0.5 * self.wire_diameter_m * (1 + self.flattening / 2) * self.swage_scale * corner


def needle_mesh(needle: NeedleModel, shape: NeedleShape, material: Material) -> Mesh:
    """The needle in the needle frame: its centreline is the model's arc, the sharp tip exactly
    at A, the tail's end exactly at E."""
    if shape.tail not in ("dome", "chamfer"):
        raise ValueError(f"needle shape: tail must be 'dome' or 'chamfer', got {shape.tail!r}")
    r = 0.5 * shape.wire_diameter_m
    a0, a1 = needle.arc_span_rad
    L = needle.radius_m * abs(a1 - a0)
    lt, ls = shape.tip_length_m, shape.swage_length_m
    rd = r * (1 + shape.flattening / 2) * shape.swage_scale      # dome / chamfer extent
    s = np.unique(np.concatenate([np.linspace(0, L, shape.n_arc), np.linspace(0, lt, 12),
                                  L - rd * (1 - np.cos(np.linspace(0, np.pi / 2, 8)))]))
    s = np.clip(s, 0.0, L)
    g = np.ones_like(s)
    tip = s < lt
    g[tip] = (s[tip] / lt) ** shape.tip_exponent
    u = L - s                                                      # distance from E
    ramp = np.clip((ls - u) / 0.0003, 0.0, 1.0)
    g *= 1.0 + (shape.swage_scale - 1.0) * ramp * ramp * (3 - 2 * ramp)
    end = u < rd
    if shape.tail == "dome":
        g[end] *= np.sqrt(np.clip(1.0 - ((rd - u[end]) / rd) ** 2, 0.0, 1.0))
    else:
        g[end] *= 0.55 + 0.45 * u[end] / rd
    ang = a0 + np.sign(a1 - a0) * s / needle.radius_m
    P = needle.arc_points(ang)
    Nr = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], -1)   # radial, in the arc's plane
    Bz = np.tile([0.0, 0.0, 1.0], (len(s), 1))
    f = shape.flattening
    V, F, Nv = sweep(P, Nr, Bz, r * g * (1 + f / 2), r * g * (1 - f / 2), shape.n_ring, shape.power,
                     shape.phase, cap_end=shape.tail == "chamfer")
    return Mesh(V, F, Nv, LABELS["needle"], material)


def tube_mesh(P: np.ndarray, radius: float, n_ring: int, label: int, material: Material) -> Mesh:
    """A round tube of constant radius along a polyline (e.g. the suture thread)."""
    N, B = transport_frames(P)
    V, F, Nv = sweep(P, N, B, np.full(len(P), radius), np.full(len(P), radius), n_ring)
    return Mesh(V, F, Nv, label, material)


def box_mesh(corners: np.ndarray, label: int, material: Material) -> Mesh:
    """A hexahedron from 8 corners (bottom 0-3, top 4-7, same order), flat-shaded."""
    quads = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    centre = corners.mean(axis=0)
    V, F, N = [], [], []
    for q in quads:
        p = corners[list(q)]
        n = np.cross(p[1] - p[0], p[2] - p[0]) + np.cross(p[2] - p[0], p[3] - p[0])
        n /= max(np.linalg.norm(n), 1e-30)
        if n @ (p.mean(axis=0) - centre) < 0:
            n = -n
        b = len(V)
        V.extend(p)
        N.extend([n] * 4)
        F.extend([(b, b + 1, b + 2), (b, b + 2, b + 3)])
    return Mesh(np.asarray(V), np.asarray(F), np.asarray(N), label, material)


@dataclass(frozen=True)
class InstrumentShape:
    """A laparoscopic instrument: a dark shaft, a metal wrist and two jaws."""

    shaft_radius_m: float = 0.003
    wrist_length_m: float = 0.005
    jaw_length_m: float = 0.008
    jaw_width_m: float = 0.002
    jaw_thickness_m: float = 0.001
    opening_rad: float = 0.3
    gap_m: float = 0.0          # distance between closed jaws (a grasped wire)
    length_m: float = 0.25


def instrument_meshes(tip: np.ndarray, towards: np.ndarray, spread: np.ndarray, shape: InstrumentShape,
                      shaft: Material, metal: Material) -> list[Mesh]:
    """Meshes of an instrument whose jaws' tips meet at ``tip`` (world, m) and whose shaft runs
    along ``towards`` (from the tip to the trocar); the jaws open along ``spread`` (made
    perpendicular to the shaft)."""
    u = np.asarray(towards, float) / np.linalg.norm(towards)
    tip = np.asarray(tip, float)
    w = np.asarray(spread, float) - u * (u @ spread)
    if np.linalg.norm(w) < 1e-9:
        w = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    w /= np.linalg.norm(w)
    v = np.cross(w, u)
    hinge = tip + u * shape.jaw_length_m * np.cos(shape.opening_rad / 2)
    meshes = []
    for side in (-1.0, 1.0):
        # jaw: from the hinge to its tip, opened by half the opening angle in the u-w plane
        jt = tip + side * w * (0.5 * shape.gap_m + 0.5 * shape.jaw_thickness_m
                               + shape.jaw_length_m * np.sin(shape.opening_rad / 2))
        hb = hinge + side * w * (0.5 * shape.gap_m + 0.5 * shape.jaw_thickness_m)
        axis = jt - hb
        axis /= np.linalg.norm(axis)
        nrm = np.cross(axis, v)           # the jaw's thickness direction (about +-w)
        corners = []
        th = shape.jaw_thickness_m
        for z in (-0.5, 0.5):   # bottom face then top face, the jaw narrowing towards its tip
            corners += [hb - v * shape.jaw_width_m / 2 + nrm * th * z, jt - v * 0.45 * shape.jaw_width_m / 2
                        + nrm * th * 0.6 * z, jt + v * 0.45 * shape.jaw_width_m / 2 + nrm * th * 0.6 * z,
                        hb + v * shape.jaw_width_m / 2 + nrm * th * z]
        meshes.append(box_mesh(np.asarray(corners), LABELS["instrument"], metal))
    r = shape.shaft_radius_m
    wrist = hinge + u * np.linspace(-0.0005, shape.wrist_length_m, 6)[:, None]
    Nw = np.tile(v, (len(wrist), 1))
    Bw = np.tile(np.cross(u, v), (len(wrist), 1))
    V, F, Nv = sweep(wrist, Nw, Bw, np.full(len(wrist), 0.8 * r), np.full(len(wrist), 0.8 * r), 16)
    meshes.append(Mesh(V, F, Nv, LABELS["instrument"], metal))
    axis_pts = hinge + u * (shape.wrist_length_m + np.linspace(0.0, shape.length_m, 40))[:, None]
    V, F, Nv = sweep(axis_pts, np.tile(v, (40, 1)), np.tile(np.cross(u, v), (40, 1)),
                     np.full(40, r), np.full(40, r), 20)
    meshes.append(Mesh(V, F, Nv, LABELS["instrument"], shaft))
    return meshes


# ---------------------------------------------------------------- tissue

@dataclass
class Tissue:
    """The tissue surface ``z = sum_k a_k sin(kx_k x + ky_k y + phase_k)`` (world, m) with an
    albedo texture (linear RGB, ``albedo`` covering the square of side ``extent_m`` centred on
    the world origin), a tiled luminance detail texture (``detail``: a pyramid, level 0 of side
    ``detail_extent_m``) and red marks (``marks`` rows: x, y, radius (m), ring width (m); width
    0 = a filled disc), drawn into an RGBA overlay of side ``overlay_extent_m`` about their mean."""

    waves: np.ndarray
    albedo: np.ndarray
    extent_m: float
    detail: list
    detail_extent_m: float
    marks: np.ndarray
    mark_rgb: tuple = (0.42, 0.012, 0.018)
    ks: float = 0.25
    shininess: float = 40.0
    overlay_extent_m: float = 0.08

    def __post_init__(self):
        self._overlay = None

    def height(self, x, y):
        h = np.zeros(np.shape(x), np.float32)
        for a, kx, ky, ph in self.waves.astype(np.float32):
            h += a * np.sin(kx * x + ky * y + ph)
        return h

    def gradient(self, x, y):
        gx = np.zeros(np.shape(x), np.float32)
        gy = np.zeros(np.shape(x), np.float32)
        for a, kx, ky, ph in self.waves.astype(np.float32):
            c = a * np.cos(kx * x + ky * y + ph)
            gx += kx * c
            gy += ky * c
        return gx, gy

    def normal(self, x, y) -> tuple:
        """Unit normal as three component arrays (nx, ny, nz) at the points (x, y)."""
        gx, gy = self.gradient(x, y)
        inv = 1.0 / np.sqrt(gx * gx + gy * gy + 1.0)
        return -gx * inv, -gy * inv, inv

    def raycast(self, o: np.ndarray, dx, dy, dz, t0=None, iterations: int = 6) -> np.ndarray:
        """Ray parameter t of the hit of ``o + t d`` (d given by component arrays) by fixed-point
        iteration on the height (it contracts for the slopes this surface has); inf where the ray
        does not go down. ``t0``: a start (e.g. a coarser solution)."""
        ok = dz < -1e-4
        dzs = np.where(ok, dz, np.float32(-1.0)).astype(np.float32)
        t = ((0.0 - o[2]) / dzs).astype(np.float32) if t0 is None else np.where(np.isfinite(t0), t0, 0.0)
        for _ in range(iterations):
            t = (self.height(o[0] + t * dx, o[1] + t * dy) - o[2]) / dzs
        return np.where(ok & (t > 0), t, np.inf).astype(np.float32)

    def overlay(self) -> np.ndarray:
        """The marks as a premultiplied RGBA texture (built once)."""
        if self._overlay is None:
            size = 1024
            ov = np.zeros((size, size), np.float32)
            c = 0.5 * (self.marks[:, :2].min(axis=0) + self.marks[:, :2].max(axis=0))
            self._overlay_centre = c
            scale = size / self.overlay_extent_m * 16        # 4 fractional bits
            for x, y, rad, width in self.marks:
                p = (int(round(((x - c[0]) / self.overlay_extent_m + 0.5) * size * 16 - 8)),
                     int(round(((y - c[1]) / self.overlay_extent_m + 0.5) * size * 16 - 8)))
                if width > 0:
                    cv2.circle(ov, p, int(round(rad * scale)), 1.0, max(1, int(round(width * size / self.overlay_extent_m))),
                               cv2.LINE_AA, shift=4)
                else:
                    cv2.circle(ov, p, int(round(rad * scale)), 1.0, -1, cv2.LINE_AA, shift=4)
            self._overlay = ov
        return self._overlay

    def albedo_at(self, x: np.ndarray, y: np.ndarray, footprint_m: float) -> np.ndarray:
        """(H, W, 3) linear albedo at the (H, W) points; ``footprint_m`` picks the detail level."""
        S = self.albedo.shape[0]
        k = np.float32(S / self.extent_m)
        alb = cv2.remap(self.albedo, x * k + np.float32(S / 2 - 0.5), y * k + np.float32(S / 2 - 0.5),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        D = self.detail[0].shape[0]
        texel = self.detail_extent_m / D
        level = int(np.clip(np.floor(np.log2(max(footprint_m / texel, 1.0))), 0, len(self.detail) - 1))
        det = self.detail[level]
        Dl = det.shape[0]
        kd = np.float32(Dl / self.detail_extent_m)
        dx = np.mod(x * kd - np.float32(0.5), np.float32(Dl))
        dy = np.mod(y * kd - np.float32(0.5), np.float32(Dl))
        alb *= cv2.remap(det, dx, dy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)[..., None]
        if len(self.marks):
            ov = self.overlay()
            c = self._overlay_centre
            ko = np.float32(ov.shape[0] / self.overlay_extent_m)
            cover = cv2.remap(ov, (x - np.float32(c[0])) * ko + np.float32(ov.shape[0] / 2 - 0.5),
                              (y - np.float32(c[1])) * ko + np.float32(ov.shape[0] / 2 - 0.5), cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
            alb += cover[..., None] * (np.asarray(self.mark_rgb, np.float32) - alb)
        return alb


def _fbm(rng: np.random.Generator, size: int, octaves: int, base: int) -> np.ndarray:
    """Fractal value noise in [-1, 1]-ish: random grids upsampled bicubically and summed."""
    out = np.zeros((size, size), np.float32)
    amp, n = 1.0, base
    for _ in range(octaves):
        g = rng.standard_normal((n, n)).astype(np.float32)
        out += amp * cv2.resize(g, (size, size), interpolation=cv2.INTER_CUBIC)
        amp *= 0.55
        n *= 2
    return out / np.max(np.abs(out))


def make_tissue_textures(rng: np.random.Generator, base_rgb, size: int = 1024,
                         detail_size: int = 512) -> tuple[np.ndarray, list]:
    """This renderer's tissue look: mottled base colour, pale fatty lobules, dark capillary
    streaks (albedo, linear RGB) and a fibrous detail pyramid (luminance multipliers ~1)."""
    base = np.asarray(base_rgb, np.float32)
    m = _fbm(rng, size, 5, 6)
    alb = base[None, None] * (1.0 + 0.18 * m[..., None])
    # lobules: soft pale-yellow blobs
    blobs = np.zeros((size, size), np.float32)
    for _ in range(int(rng.integers(25, 60))):
        c = rng.integers(0, size, 2)
        ax = rng.uniform(0.004, 0.015) * size
        cv2.ellipse(blobs, (int(c[0]), int(c[1])), (max(1, int(ax)), max(1, int(ax * rng.uniform(0.5, 1.0)))),
                    float(rng.uniform(0, 180)), 0, 360, 1.0, -1)
    blobs = cv2.GaussianBlur(blobs, (0, 0), size / 500)
    fat = np.array([0.75, 0.55, 0.25], np.float32)
    alb += (rng.uniform(0.1, 0.35) * blobs)[..., None] * (fat - alb)
    # capillaries: thin dark-red random walks
    cap = np.zeros((size, size), np.float32)
    for _ in range(int(rng.integers(8, 20))):
        p = rng.uniform(0, size, 2)
        ang = rng.uniform(0, 2 * np.pi)
        pts = []
        for _ in range(40):
            ang += rng.normal(0, 0.25)
            p = p + 6 * np.array([np.cos(ang), np.sin(ang)])
            pts.append(p.copy())
        cv2.polylines(cap, [np.round(np.array(pts) * 4).astype(np.int32)], False, 1.0,
                      int(rng.integers(1, 3)), cv2.LINE_AA, shift=2)
    cap = cv2.GaussianBlur(cap, (0, 0), 0.8)
    vessel = np.array([0.25, 0.02, 0.04], np.float32)
    alb += (0.45 * np.clip(cap, 0, 1))[..., None] * (vessel - alb)
    alb = np.clip(alb, 0.005, 1.0)
    # detail: anisotropic fibres (stretched noise) and pores
    fib = cv2.resize(rng.standard_normal((detail_size, detail_size // 16)).astype(np.float32),
                     (detail_size, detail_size), interpolation=cv2.INTER_CUBIC)
    fib = cv2.GaussianBlur(fib, (0, 0), 1.0)
    pores = (rng.random((detail_size, detail_size)) < 0.004).astype(np.float32)
    pores = cv2.GaussianBlur(pores, (0, 0), 1.5) * 20
    det = 1.0 + 0.10 * fib / max(np.max(np.abs(fib)), 1e-6) - 0.25 * np.clip(pores, 0, 1)
    det = np.clip(det, 0.5, 1.5).astype(np.float32)
    pyr = [det]
    while pyr[-1].shape[0] > 8:
        pyr.append(cv2.pyrDown(pyr[-1]))
    return alb.astype(np.float32), pyr


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


# ---------------------------------------------------------------- rasteriser

def rasterise(V_cam: np.ndarray, F: np.ndarray, K: np.ndarray, width: int, height: int,
              depth: np.ndarray | None = None):
    """Z-buffer rasterisation of triangles (camera-frame vertices, m) on the sample grid of
    ``K`` (sample (i, j) is the ray through pixel coordinates (i, j), i.e. K^-1 [i, j, 1]).

    ``depth`` (height, width), if given, is the depth already there (e.g. the tissue): only
    nearer samples win. Returns (face (h, w) int32, -1 where no triangle wins; depth (h, w)
    float32; barycentrics (h, w, 3) float32, perspective-correct, of the winning face).
    A sample exactly on a shared edge belongs to both triangles: harmless with a z-buffer.
    """
    zbuf = np.full(width * height, np.inf, np.float64) if depth is None else \
        depth.astype(np.float64).reshape(-1).copy()
    face = np.full(width * height, -1, np.int32)
    bary = np.zeros((width * height, 3), np.float32)
    z = V_cam[:, 2]
    fid = np.flatnonzero(np.all(z[F] > NEAR_M, axis=1))
    if len(fid):
        uv = (V_cam[:, :2] / z[:, None]) @ K[:2, :2].T + K[:2, 2]
        P = uv[F[fid]]                                           # (T, 3, 2)
        Z = z[F[fid]]                                            # (T, 3)
        area = ((P[:, 1, 0] - P[:, 0, 0]) * (P[:, 2, 1] - P[:, 0, 1])
                - (P[:, 1, 1] - P[:, 0, 1]) * (P[:, 2, 0] - P[:, 0, 0]))
        x0 = np.maximum(np.ceil(P[..., 0].min(axis=1)), 0)
        x1 = np.minimum(np.floor(P[..., 0].max(axis=1)), width - 1)
        y0 = np.maximum(np.ceil(P[..., 1].min(axis=1)), 0)
        y1 = np.minimum(np.floor(P[..., 1].max(axis=1)), height - 1)
        keep = (np.abs(area) > 1e-12) & (x1 >= x0) & (y1 >= y0)
        fid, P, Z, area = fid[keep], P[keep], Z[keep], area[keep]
        x0, x1, y0, y1 = (a[keep].astype(np.int64) for a in (x0, x1, y0, y1))
        nx = x1 - x0 + 1
        cnt = nx * (y1 - y0 + 1)
        ends = np.cumsum(cnt)
        start = 0
        while start < len(fid):
            # a batch of triangles with at most _CHUNK candidate samples (at least one triangle)
            base = ends[start - 1] if start else 0
            stop = max(int(np.searchsorted(ends, base + _CHUNK, side="right")), start + 1)
            sl = slice(start, stop)
            c = cnt[sl]
            t = np.repeat(np.arange(stop - start), c)
            off = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
            px = x0[sl][t] + off % nx[sl][t]
            py = y0[sl][t] + off // nx[sl][t]
            Pt = P[sl][t]
            w0 = ((Pt[:, 2, 0] - Pt[:, 1, 0]) * (py - Pt[:, 1, 1])
                  - (Pt[:, 2, 1] - Pt[:, 1, 1]) * (px - Pt[:, 1, 0])) / area[sl][t]
            w1 = ((Pt[:, 0, 0] - Pt[:, 2, 0]) * (py - Pt[:, 2, 1])
                  - (Pt[:, 0, 1] - Pt[:, 2, 1]) * (px - Pt[:, 2, 0])) / area[sl][t]
            w2 = 1.0 - w0 - w1
            inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
            t, px, py, w = t[inside], px[inside], py[inside], np.stack([w0, w1, w2], -1)[inside]
            Zt = Z[sl][t]
            wz = w / Zt
            inv = wz.sum(axis=1)
            zz = 1.0 / inv
            pix = py * width + px
            front = zz < zbuf[pix]
            t, pix, zz, wz, inv = t[front], pix[front], zz[front], wz[front], inv[front]
            np.minimum.at(zbuf, pix, zz)
            win = zz <= zbuf[pix]
            face[pix[win]] = fid[sl][t[win]]
            bary[pix[win]] = wz[win] / inv[win, None]
            start = stop
    return face.reshape(height, width), zbuf.reshape(height, width).astype(np.float32), \
        bary.reshape(height, width, 3)


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
        T_ecm_needle = inv_T(T_world_ecm) @ scene.T_world_needle
        p_ecm = transform_points(T_ecm_needle, scene.needle.keypoints())
        tol = 1.5 * scene.needle_shape.max_radius_m
        kps, vis, boxes = {}, {}, {}
        for c in CAMERAS:
            cam = self.rig[c]
            p = transform_points(cam.T_cam_ecm, p_ecm)
            uv = cam.project(p)
            inside = cam.in_image(uv) & (p[:, 2] > 0)
            r = renders[c]
            v = np.zeros(5, bool)
            for k in np.flatnonzero(inside):
                u0 = min(max(int(round(uv[k, 0])), 0), cam.width - 1)
                v0 = min(max(int(round(uv[k, 1])), 0), cam.height - 1)
                v[k] = bool(r.label[v0, u0] == LABELS["needle"] or r.depth[v0, u0] >= p[k, 2] - tol)
            ys, xs = np.nonzero(r.label == LABELS["needle"])
            boxes[c] = None if len(xs) == 0 else [float(xs.min()) - 0.5, float(ys.min()) - 0.5,
                                                  float(xs.max()) + 0.5, float(ys.max()) + 0.5]
            kps[c], vis[c] = uv, v
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
