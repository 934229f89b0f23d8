"""Image-space effects of the ``random`` looks, applied before the sensor model
(``common.sim.randomise.degrade``): smoke or haze, glare (specular blobs) and specular streaks,
defocus and motion blur, vignetting and white balance. Both images of a stereo frame get the
same effects at the same pixels.

Effects that could hide the needle stay off it: glare blobs and streaks keep clear of the points
given in ``avoid`` (the keypoints and the arc between them), and haze is never opaque (at most
55%), so the ground truth's ``visible`` still says what an image shows.
"""
from __future__ import annotations

from dataclasses import dataclass

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


LOW = 8  # the smooth maps (haze, vignetting, blobs) are made at 1/LOW of the image's size


def _haze(rng, h, w) -> np.ndarray:
    """(h, w, 1) float32 opacity of smoke: coarse noise, up to HAZE_MAX."""
    gw, gh = int(rng.integers(3, 10)), int(rng.integers(2, 8))
    small = rng.random((gh, gw)).astype(np.float32)
    a = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    a = np.clip((a - rng.uniform(0.0, 0.5)) / 0.5, 0, 1) * rng.uniform(0.15, HAZE_MAX)
    return a[..., None]


def _blobs(rng, h, w, pts) -> np.ndarray | None:
    """(h, w) float32 glare at 1/LOW scale (image size h*LOW x w*LOW): soft specular blobs."""
    if rng.random() >= 0.4:
        return None
    s = w * LOW / 1920.0
    layer = np.zeros((h, w), np.float32)
    for _ in range(int(rng.integers(1, 7))):
        ax = rng.uniform(3, 30, 2) * s
        c = rng.uniform([0, 0], [w * LOW, h * LOW])
        if not _clear(c, pts, (int(ax.max() / LOW) + 4) * LOW):    # its radius and blur, at 1/LOW
            continue
        cv2.ellipse(layer, (int(c[0] / LOW), int(c[1] / LOW)), (int(ax[0] / LOW) + 1, int(ax[1] / LOW) + 1),
                    float(rng.uniform(0, 180)), 0, 360, float(rng.uniform(0.5, 1.0)), -1, cv2.LINE_AA)
    return cv2.GaussianBlur(layer, (0, 0), 0.8)


def _streaks(rng, h, w, pts, p_streaks) -> np.ndarray | None:
    """(h, w) uint8 thin bright curved streaks (specular lines on wet tissue), or None."""
    if rng.random() >= p_streaks:
        return None
    s = w / 1920.0
    layer = np.zeros((h, w), np.uint8)
    for _ in range(int(rng.integers(1, 5))):
        width = int(rng.integers(1, 5))
        p = rng.uniform([0, 0], [w, h])
        ang = rng.uniform(0, 2 * np.pi)
        bend = rng.normal(0, 0.08)
        line = []
        for _ in range(int(rng.integers(6, 30))):
            line.append(p.copy())
            ang += bend
            p = p + 12 * s * np.array([np.cos(ang), np.sin(ang)])
        line = np.float32(line)
        if _clear(line, pts, width + 14 * s):
            cv2.polylines(layer, [np.int32(line)], False, int(rng.uniform(120, 255)), width, cv2.LINE_AA)
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


GAIN_ONE = 128.0  # the uint8 gain map's unit


@dataclass
class Effects:
    """A frame's effects at image size (h, w): ``gain`` (h, w, 3) uint8 in units of ``GAIN_ONE``
    and ``offset`` (h, w, 3) uint8 (haze, vignetting, white balance: ``img * gain + offset``),
    ``blobs`` (h/LOW, w/LOW) float32 glare 0..1 or None, ``streaks`` (h, w) uint8 or None, and the
    blur ``kernel`` or None."""

    gain: np.ndarray
    offset: np.ndarray
    blobs: np.ndarray | None
    streaks: np.ndarray | None
    kernel: np.ndarray | None


def draw_effects(rng: np.random.Generator, h: int, w: int, avoid: dict | None = None,
                 p_streaks: float = 0.3) -> Effects:
    """A frame's effects for images of h x w, drawn from ``rng``; glare and streaks keep clear of
    the pixels in ``avoid`` (camera -> (N, 2))."""
    hs, ws = h // LOW + 1, w // LOW + 1
    pts = _avoid_points(avoid)
    haze = _haze(rng, hs, ws) if rng.random() < 0.3 else np.zeros((hs, ws, 1), np.float32)
    haze_bgr = np.array([rng.uniform(0.65, 0.95)] * 3, np.float32) * rng.uniform(0.92, 1.08, 3).astype(np.float32) * 255
    blobs = _blobs(rng, hs, ws, pts)
    streaks = _streaks(rng, h, w, pts, p_streaks)
    kernel = _blur_kernel(rng, w)
    gain = np.exp(rng.normal(0, 0.07, 3)).astype(np.float32) if rng.random() < 0.8 else np.ones(3, np.float32)
    if rng.random() < 0.6:
        y, x = np.ogrid[0:hs, 0:ws]
        c = np.array([ws, hs]) / 2 + rng.normal(0, 0.05, 2) * np.array([ws, hs])
        r2 = ((x - c[0]) ** 2 + (y - c[1]) ** 2) / (0.25 * (ws * ws + hs * hs))
        vig = (1.0 - rng.uniform(0.1, 0.7) * r2).astype(np.float32)[..., None]
    else:
        vig = np.ones((hs, ws, 1), np.float32)
    g = vig * gain                                                     # (hs, ws, 3)
    gain8 = cv2.resize(np.clip((1.0 - haze) * g * GAIN_ONE, 0, 255).astype(np.uint8), (w, h))
    offset8 = cv2.resize(np.clip(haze * haze_bgr * g, 0, 255).astype(np.uint8), (w, h))
    return Effects(gain8, offset8, blobs, streaks, kernel)


def apply_effects(img: np.ndarray, fx: Effects) -> np.ndarray:
    """``img * gain + offset``, glare blobs (scaled by the local brightness) and streaks, then the blur."""
    h, w = img.shape[:2]
    f = cv2.add(cv2.multiply(img, fx.gain, scale=1.0 / GAIN_ONE, dtype=cv2.CV_8U), fx.offset)
    if fx.blobs is not None:   # highlights where the scene is lit
        hs, ws = fx.blobs.shape
        small = cv2.resize(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), (ws, hs), interpolation=cv2.INTER_AREA)
        lit = np.clip(small.astype(np.float32) / 90.0, 0.1, 1.0)
        f = cv2.add(f, cv2.cvtColor(cv2.resize((fx.blobs * lit * 255).astype(np.uint8), (w, h)), cv2.COLOR_GRAY2BGR))
    if fx.streaks is not None:
        f = cv2.add(f, cv2.cvtColor(fx.streaks, cv2.COLOR_GRAY2BGR))
    if fx.kernel is not None:
        f = cv2.filter2D(f, -1, fx.kernel, borderType=cv2.BORDER_REFLECT)
    return f


def look_effects(images: dict, rng: np.random.Generator, avoid: dict | None = None,
                 p_streaks: float = 0.3) -> dict:
    """The effects (module docstring) drawn once from ``rng`` (``draw_effects``) and applied to
    every BGR uint8 image of ``images`` (camera -> image, all the same size)."""
    h, w = next(iter(images.values())).shape[:2]
    fx = draw_effects(rng, h, w, avoid, p_streaks)
    return {cam: apply_effects(img, fx) for cam, img in images.items()}
