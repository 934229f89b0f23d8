"""The built-in scene's geometry: the tissue phantom's surface, tubes swept along a polyline, the
needle's body and the suture thread's path. World frame as in ``common.sim.scene``: the table top
at z = 0, z up, the phantom pad centred on the origin. All lengths in metres.
"""
from __future__ import annotations

import numpy as np

from common.geometry.needle import NeedleModel
from common.geometry.transforms import transform_points

# Phantom pad: size (x, y) and nominal top height above the table (m).
PHANTOM_SIZE = (0.12, 0.10)
PHANTOM_TOP = 0.012
PHANTOM_BUMP = 0.0006  # amplitude of the surface undulation (m)


def phantom_height(x, y) -> np.ndarray:
    """Height (m, world z) of the phantom's top surface at world (x, y): a gentle undulation."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    return (PHANTOM_TOP
            + PHANTOM_BUMP * 0.6 * np.sin(x * 55.0 + 0.4) * np.cos(y * 47.0 - 0.4)
            + PHANTOM_BUMP * 0.4 * np.sin(x * 23.0 - y * 31.0 + 0.8))


def perpendicular(v: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to ``v`` (3,)."""
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
    N[0] = perpendicular(T[0])
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
    a0, a1 = needle.arc_span_rad
    arc_len = needle.radius_m * abs(a1 - a0)
    s = np.linspace(0.0, 1.0, n_arc) ** 1.0
    # denser sampling near the tip so the taper is smooth
    s = np.unique(np.concatenate([s, np.linspace(0, min(1.0, 2 * tip_length_m / arc_len), 30)]))
    ang = a0 + s * (a1 - a0)
    pts = needle.arc_points(ang)
    radii = needle_radii(needle, s * arc_len, wire_diameter_m, tip_length_m, tip_exponent, swage_scale)
    return sweep_tube(pts, radii, n_ring, cap_start=False, cap_end=True)


SWAGE_LENGTH_M = 0.0015
"""Length of the built-in needle's swage, the thicker end of the wire at E (m)."""


def needle_radii(needle: NeedleModel, dist_m, wire_diameter_m: float | None = None, tip_length_m: float = 0.0018,
                 tip_exponent: float = 0.75, swage_scale: float = 1.08) -> np.ndarray:
    """Radius (m) of the built-in needle's wire (``needle_mesh``) at ``dist_m`` (m) along the arc
    from the tip A: 0 at A, ``(dist / tip_length) ** tip_exponent`` of the wire's radius along the
    taper, ``swage_scale`` x the wire's radius over the last ``SWAGE_LENGTH_M`` before E."""
    rw = 0.5 * (wire_diameter_m or needle.wire_diameter_m)
    a0, a1 = needle.arc_span_rad
    arc_len = needle.radius_m * abs(a1 - a0)
    dist = np.asarray(dist_m, dtype=float)
    radii = np.full(dist.shape, rw)
    tip = dist < tip_length_m
    radii[tip] = rw * (np.maximum(dist[tip], 0.0) / tip_length_m) ** tip_exponent
    radii[dist > arc_len - SWAGE_LENGTH_M] = rw * swage_scale
    return radii


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


def phantom_surface(x, y) -> np.ndarray:
    """Height (m, world z) of the phantom's top surface as its mesh draws it: ``phantom_height``
    with the rim rounded down to the pad's sides over its outer 3 mm; -inf outside the pad."""
    sx, sy = PHANTOM_SIZE
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    edge = np.minimum.reduce([x + sx / 2, sx / 2 - x, y + sy / 2, sy / 2 - y])
    z = phantom_height(x, y)
    z = np.where(edge < 0.003, z - (0.003 - edge) * 1.5, z)
    return np.where(edge >= 0.0, z, -np.inf)


def under_phantom(points_world: np.ndarray, depth_m=0.0) -> np.ndarray:
    """(N,) bool: which world points (N, 3) lie inside the phantom pad more than ``depth_m`` (m,
    scalar or (N,)) under its top surface (the pad is solid down to the table)."""
    p = np.asarray(points_world, dtype=float).reshape(-1, 3)
    return (p[:, 2] < phantom_surface(p[:, 0], p[:, 1]) - depth_m) & (p[:, 2] > 0.0)


def phantom_mesh(nx: int = 97, ny: int = 81):
    """The phantom's top surface (world frame) with texture coordinates: (verts, texcoords, faces)."""
    sx, sy = PHANTOM_SIZE
    xs = np.linspace(-sx / 2, sx / 2, nx)
    ys = np.linspace(-sy / 2, sy / 2, ny)
    X, Y = np.meshgrid(xs, ys)
    Z = phantom_surface(X, Y)
    verts = np.stack([X, Y, Z], -1).reshape(-1, 3)
    uv = np.stack([(X + sx / 2) / sx, 1.0 - (Y + sy / 2) / sy], -1).reshape(-1, 2)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return verts, uv, faces
