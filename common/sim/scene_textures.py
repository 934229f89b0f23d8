"""The built-in scene's procedural textures: the tissue phantom's and the table's (RGB uint8, near
white: the material's colour tints them), and a per-process cache of a few variants.
"""
from __future__ import annotations

import cv2
import numpy as np

from common.sim.scene_meshes import PHANTOM_SIZE


def value_noise(rng, shape, scale):
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
    n = (0.45 * value_noise(rng, (size, size), 160 * size / 1024) + 0.3 * value_noise(rng, (size, size), 40 * size / 1024)
         + 0.25 * value_noise(rng, (size, size), 8 * size / 1024))
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
    n = 0.7 + 0.3 * value_noise(rng, (size, size), 30) + 0.1 * (rng.random((size, size)) - 0.5)
    return (np.clip(np.repeat(n[..., None], 3, axis=2), 0, 1) * 255).astype(np.uint8)


_TEXTURE_CACHE: dict = {}
TEXTURE_VARIANTS = 16  # distinct tissue patterns a process keeps (generating one takes ~0.3 s)


def cached_texture(kind: str, seed: int, size: int) -> np.ndarray:
    key = (kind, seed % TEXTURE_VARIANTS, size)
    if key not in _TEXTURE_CACHE:
        fn = tissue_texture if kind == "tissue" else table_texture
        _TEXTURE_CACHE[key] = fn(seed % TEXTURE_VARIANTS, size)
    return _TEXTURE_CACHE[key]
