"""The second renderer's triangle meshes (world or object frame, metres): the needle swept along
its arc with a taper, a thread, boxes, instruments; their materials and labels."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry.needle import NeedleModel
from common.geometry.transforms import transform_points

LABELS = {"tissue": 0, "needle": 1, "thread": 2, "instrument": 3, "none": -1}
"""Per-pixel labels of the rendered objects."""


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

    def thickness(self, s, arc_length_m: float) -> np.ndarray:
        """The cross-section's scale (1: the wire's) at ``s`` (m) along the arc from the tip A, on an
        arc ``arc_length_m`` long: 0 at A, the taper, the swage, the dome or chamfer ending at E."""
        s = np.asarray(s, dtype=float)
        lt, ls, L = self.tip_length_m, self.swage_length_m, arc_length_m
        rd = 0.5 * self.wire_diameter_m * (1 + self.flattening / 2) * self.swage_scale   # dome / chamfer extent
        g = np.ones_like(s)
        tip = s < lt
        g[tip] = (np.maximum(s[tip], 0.0) / lt) ** self.tip_exponent
        u = L - s                                                      # distance from E
        ramp = np.clip((ls - u) / 0.0003, 0.0, 1.0)
        g *= 1.0 + (self.swage_scale - 1.0) * ramp * ramp * (3 - 2 * ramp)
        end = u < rd
        if self.tail == "dome":
            g[end] *= np.sqrt(np.clip(1.0 - ((rd - u[end]) / rd) ** 2, 0.0, 1.0))
        else:
            g[end] *= 0.55 + 0.45 * u[end] / rd
        return g

    def radius_at(self, needle: NeedleModel, s) -> np.ndarray:
        """Largest distance (m) of the surface from the arc at ``s`` (m) along it from the tip A
        (``max_radius_m`` where the swage is thickest)."""
        a0, a1 = needle.arc_span_rad
        g = self.thickness(s, needle.radius_m * abs(a1 - a0))
        return self.max_radius_m / self.swage_scale * g


def needle_mesh(needle: NeedleModel, shape: NeedleShape, material: Material) -> Mesh:
    """The needle in the needle frame: its centreline is the model's arc, the sharp tip exactly
    at A, the tail's end exactly at E."""
    if shape.tail not in ("dome", "chamfer"):
        raise ValueError(f"needle shape: tail must be 'dome' or 'chamfer', got {shape.tail!r}")
    r = 0.5 * shape.wire_diameter_m
    a0, a1 = needle.arc_span_rad
    L = needle.radius_m * abs(a1 - a0)
    lt = shape.tip_length_m
    rd = r * (1 + shape.flattening / 2) * shape.swage_scale      # dome / chamfer extent
    s = np.unique(np.concatenate([np.linspace(0, L, shape.n_arc), np.linspace(0, lt, 12),
                                  L - rd * (1 - np.cos(np.linspace(0, np.pi / 2, 8)))]))
    s = np.clip(s, 0.0, L)
    g = shape.thickness(s, L)
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
