"""The second renderer's tissue: an analytic height field ``z = sum a sin(k . xy + phase)``
(metres, world z up), ray-cast per sample, with procedural albedo and detail textures."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


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
