"""Image-space effects of the ``random`` looks, applied before the sensor model
(``common.sim.randomise.degrade``): smoke or haze, glare (specular blobs) and specular streaks,
defocus and motion blur, vignetting and white balance. Both images of a stereo frame get the
same effects at the same pixels.

Effects that could hide the needle stay off it: glare blobs and streaks keep clear of the points
given in ``avoid`` (the keypoints and the arc between them), and haze is never opaque (at most
55%), so the ground truth's ``visible`` still says what an image shows.
"""
from __future__ import annotations

import cv2
import numpy as np

HAZE_MAX = 0.55


def _avoid_points(avoid) -> np.ndarray:
    """(N, 2) pixels to keep clear: the given points and the midpoints between neighbours."""
    pts = [np.asarray(p, float).reshape(-1, 2) for p in (avoid or {}).values()]
    pts = [p[np.all(np.isfinite(p), axis=1)] for p in pts]
    pts = [np.vstack([p, 0.5 * (p[1:] + p[:-1])]) if len(p) > 1 else p for p in pts]
    return np.vstack(pts) if pts else np.zeros((0, 2))


def _clear(xy: np.ndarray, pts: np.ndarray, r: float) -> bool:
    if len(pts) == 0:
        return True
    d = np.linalg.norm(np.asarray(xy, float).reshape(-1, 1, 2) - pts[None], axis=2)
    return bool(d.min() > r)


def _haze(rng, h, w) -> np.ndarray:
    """(h, w, 1) float32 opacity of smoke: coarse noise, up to HAZE_MAX."""
    gw, gh = int(rng.integers(3, 10)), int(rng.integers(2, 8))
    small = rng.random((gh, gw)).astype(np.float32)
    a = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    a = np.clip((a - rng.uniform(0.0, 0.5)) / 0.5, 0, 1) * rng.uniform(0.15, HAZE_MAX)
    return a[..., None]


def _glare(rng, h, w, pts, p_streaks) -> np.ndarray | None:
    """(h, w) float32 additive highlights (0..1): blobs and, with probability ``p_streaks``, streaks."""
    s = w / 1920.0
    layer = None
    if rng.random() < 0.4:
        layer = np.zeros((h, w), np.float32)
        for _ in range(int(rng.integers(1, 7))):
            ax = rng.uniform(3, 30, 2) * s
            c = rng.uniform([0, 0], [w, h])
            if not _clear(c, pts, ax.max() * 1.5 + 8 * s):
                continue
            cv2.ellipse(layer, (int(c[0]), int(c[1])), (int(ax[0]) + 1, int(ax[1]) + 1), float(rng.uniform(0, 180)),
                        0, 360, float(rng.uniform(0.5, 1.0)), -1, cv2.LINE_AA)
        layer = cv2.GaussianBlur(layer, (0, 0), 3 * s + 0.5)
    if rng.random() < p_streaks:
        layer = np.zeros((h, w), np.float32) if layer is None else layer
        for _ in range(int(rng.integers(1, 5))):
            width = int(rng.integers(1, 5))
            p = rng.uniform([0, 0], [w, h])
            ang = rng.uniform(0, 2 * np.pi)
            bend = rng.normal(0, 0.08)
            pts_s = []
            for _ in range(int(rng.integers(6, 30))):
                pts_s.append(p.copy())
                ang += bend
                p = p + 12 * s * np.array([np.cos(ang), np.sin(ang)])
            pts_s = np.float32(pts_s)
            if _clear(pts_s, pts, width + 14 * s):
                cv2.polylines(layer, [np.int32(pts_s)], False, float(rng.uniform(0.5, 1.0)), width, cv2.LINE_AA)
        layer = cv2.GaussianBlur(layer, (0, 0), 0.6)
    return layer


def _blur_kernel(rng, w) -> np.ndarray | None:
    """Defocus (a disc) or motion (a line) kernel, or None."""
    s = w / 1920.0
    u = rng.random()
    if u < 0.15:
        r = rng.uniform(1.0, 4.0) * s + 0.5
        n = 2 * int(np.ceil(r)) + 1
        k = np.zeros((n, n), np.float32)
        cv2.circle(k, (n // 2, n // 2), max(1, int(round(r))), 1.0, -1, cv2.LINE_AA)
    elif u < 0.3:
        length = rng.uniform(3, 16) * s + 1
        n = 2 * int(np.ceil(length / 2)) + 1
        k = np.zeros((n, n), np.float32)
        a = rng.uniform(0, np.pi)
        d = 0.5 * (length - 1) * np.array([np.cos(a), np.sin(a)])
        c = np.array([n // 2, n // 2])
        cv2.line(k, tuple(int(v) for v in np.round(c - d)), tuple(int(v) for v in np.round(c + d)), 1.0, 1, cv2.LINE_AA)
    else:
        return None
    return k / k.sum()


def look_effects(images: dict, rng: np.random.Generator, avoid: dict | None = None,
                 p_streaks: float = 0.3) -> dict:
    """The effects (module docstring) drawn once from ``rng`` and applied to every BGR uint8
    image of ``images`` (camera -> image, all the same size); ``avoid``: camera -> (N, 2) pixels
    that glare and streaks keep clear of."""
    h, w = next(iter(images.values())).shape[:2]
    pts = _avoid_points(avoid)
    haze = _haze(rng, h, w) if rng.random() < 0.3 else None
    haze_bgr = np.array([rng.uniform(0.65, 0.95)] * 3, np.float32) * rng.uniform(0.92, 1.08, 3).astype(np.float32) * 255
    glare = _glare(rng, h, w, pts, p_streaks)
    glare_bgr = np.clip(rng.uniform(0.85, 1.0, 3), 0, 1).astype(np.float32) * 255
    kernel = _blur_kernel(rng, w)
    gain = np.exp(rng.normal(0, 0.07, 3)).astype(np.float32) if rng.random() < 0.8 else np.ones(3, np.float32)
    if rng.random() < 0.6:
        y, x = np.ogrid[0:h, 0:w]
        c = np.array([w, h]) / 2 + rng.normal(0, 0.05, 2) * np.array([w, h])
        r2 = ((x - c[0]) ** 2 + (y - c[1]) ** 2) / (0.25 * (w * w + h * h))
        gmap = (1.0 - rng.uniform(0.1, 0.7) * r2).astype(np.float32)[..., None] * gain
    else:
        gmap = gain
    out = {}
    for cam, img in images.items():
        f = img.astype(np.float32)
        if glare is not None:   # highlights where the scene is lit: scaled by the local brightness
            small = cv2.resize(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), (w // 16 + 1, h // 16 + 1),
                               interpolation=cv2.INTER_AREA)
            lit = cv2.resize(np.clip(small.astype(np.float32) / 90.0, 0.1, 1.0), (w, h))
            f += (glare * lit)[..., None] * glare_bgr
        if haze is not None:
            f = f * (1.0 - haze) + haze * haze_bgr
        if kernel is not None:
            f = cv2.filter2D(f, -1, kernel, borderType=cv2.BORDER_REFLECT)
        f *= gmap
        out[cam] = np.clip(f, 0, 255).astype(np.uint8)
    return out
