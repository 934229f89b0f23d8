"""Textures of the ``random`` looks: procedural patterns and photographs that scikit-image ships,
recoloured through a palette, zoomed, turned, with blood-like stains and cut lines painted on.

A ``TextureLook`` describes one texture completely (``look_texture`` makes it, RGB uint8, the
same for the same description in every process). Patterns are made at ``BASE`` px and warped to
the texture's size, so a new texture costs tens of milliseconds. Which patterns and photographs
the training looks use and which are held out is decided in one place,
``common.sim.random_looks.POOLS``; this module only makes them.

Photographs need scikit-image (the ``train`` extra, imported on first use); without it
``photos_available()`` is False and the looks use patterns only (said once on stderr).
"""
from __future__ import annotations

import sys
from dataclasses import dataclass

import cv2
import numpy as np

from common.sim.scene_textures import value_noise

BASE = 512  # px: the size patterns and photographs are made at before the warp


@dataclass(frozen=True)
class TextureLook:
    """One texture: ``kind`` a pattern of ``PATTERNS`` or ``photo:NAME`` (``PHOTOS``), drawn from
    ``seed``; ``palette`` the dark, middle and light colours (RGB 0..1) a pattern's (or a photo's
    grey) levels are mapped to; ``zoom`` (> 1 magnifies) and ``angle`` (rad) of the warp;
    ``relief`` 0..1 the emboss shading; ``stains`` 0..1 roughly the share under blood-like stains;
    ``incisions`` cut lines (dark, with a bright lip); ``photo_hue``: a colour photo keeps its own
    colours, its hue turned by ``hue_turn`` (0..1 of the circle), instead of the palette's."""

    kind: str
    seed: int
    palette: tuple
    zoom: float = 1.0
    angle: float = 0.0
    relief: float = 0.5
    stains: float = 0.0
    incisions: int = 0
    photo_hue: bool = False
    hue_turn: float = 0.0


# ---------------------------------------------------------------- patterns (float32 [0, 1], n x n)

def _octaves(rng, n, scales, weights):
    return sum(w * value_noise(rng, (n, n), n / s) for s, w in zip(scales, weights)) / sum(weights)


def _noise(rng, n):
    """Mottled tissue: value noise over three octaves."""
    return _octaves(rng, n, (rng.uniform(2, 5), rng.uniform(8, 16), rng.uniform(30, 70)), (0.5, 0.3, 0.2))


def _folds(rng, n):
    """Folds and creases: ridged noise (sharp bright ridges where the noise crosses its middle)."""
    r = np.clip(1.0 - np.abs(2.0 * _octaves(rng, n, (rng.uniform(2, 6), rng.uniform(6, 12)), (0.7, 0.3)) - 1.0), 0, 1)
    return 0.7 * r ** rng.uniform(2.0, 6.0) + 0.3 * value_noise(rng, (n, n), n / rng.uniform(10, 30))


def _stripes(rng, n):
    """Muscle fibres or a drape's weave: stripes warped by noise."""
    y, x = np.mgrid[0:n, 0:n].astype(np.float32)
    a = rng.uniform(0, np.pi)
    period = rng.uniform(5, 30)
    warp = value_noise(rng, (n, n), n / rng.uniform(2, 6)) * rng.uniform(2, 12)
    s = np.clip(0.5 + 0.5 * np.sin(2 * np.pi * (x * np.cos(a) + y * np.sin(a)) / period + warp), 0, 1)
    return (0.7 * s ** rng.uniform(0.5, 3.0) + 0.3 * value_noise(rng, (n, n), n / 8)).astype(np.float32)


def _cells(rng, n):
    """Cells (fat lobules: distance to the nearest of random seeds) or spots (random discs)."""
    if rng.random() < 0.5:
        mask = np.ones((n, n), np.uint8)
        pts = rng.integers(0, n, (int(rng.integers(30, 400)), 2))
        mask[pts[:, 1], pts[:, 0]] = 0
        d = cv2.distanceTransform(mask, cv2.DIST_L2, 3)
        d = d / (d.max() + 1e-6)
        return (d ** rng.uniform(0.4, 1.5)).astype(np.float32)
    img = (0.5 * value_noise(rng, (n, n), n / 6)).astype(np.float32)
    for _ in range(int(rng.integers(20, 300))):
        c = tuple(int(v) for v in rng.integers(0, n, 2))
        cv2.circle(img, c, int(rng.integers(2, 18)), float(rng.uniform(0.5, 1.0)), -1, cv2.LINE_AA)
    return cv2.GaussianBlur(img, (0, 0), rng.uniform(0.5, 2.5))


def _vessels(rng, n):
    """Mottled tissue with darker branching vessels."""
    base = _noise(rng, n)
    vess = np.zeros((n, n), np.float32)
    for _ in range(int(rng.integers(4, 16))):
        p = rng.uniform(0, n, 2)
        ang = rng.uniform(0, 2 * np.pi)
        pts = []
        for _ in range(int(rng.integers(15, 40))):
            pts.append(p.copy())
            ang += rng.normal(0, 0.3)
            p = p + rng.uniform(4, 10) * np.array([np.cos(ang), np.sin(ang)])
        cv2.polylines(vess, [np.int32(pts)], False, float(rng.uniform(0.4, 1.0)), int(rng.integers(1, 4)),
                      cv2.LINE_AA)
    vess = cv2.GaussianBlur(vess, (0, 0), 0.8)
    return base * (1.0 - 0.7 * vess)


def _marble(rng, n):
    """Marbled veins: a sine through turbulent noise."""
    y, x = np.mgrid[0:n, 0:n].astype(np.float32)
    turb = sum(np.abs(value_noise(rng, (n, n), n / s) - 0.5) / k
               for k, s in ((1, rng.uniform(2, 4)), (2, rng.uniform(6, 10)), (4, rng.uniform(14, 24))))
    a = rng.uniform(0, np.pi)
    s = np.abs(np.sin((x * np.cos(a) + y * np.sin(a)) / rng.uniform(15, 40) + turb * rng.uniform(6, 14)))
    return (s ** rng.uniform(0.3, 1.0)).astype(np.float32)


def _mesh(rng, n):
    """A woven surgical mesh: bright fibres on a grid over a darker ground."""
    y, x = np.mgrid[0:n, 0:n].astype(np.float32)
    p = rng.uniform(8, 28)
    w = p * rng.uniform(0.08, 0.2)
    wob = value_noise(rng, (n, n), n / 4) * rng.uniform(0, 6)
    line = lambda t: np.exp(-(((t + wob) % p) - p / 2) ** 2 / (2 * w * w))  # noqa: E731
    return (np.maximum(line(x), 0.85 * line(y)) * (0.7 + 0.3 * value_noise(rng, (n, n), n / 10))).astype(np.float32)


def _crackle(rng, n):
    """Crazed glaze: cells of random tone split by dark cracks."""
    mask = np.ones((n, n), np.uint8)
    pts = rng.integers(0, n, (int(rng.integers(40, 300)), 2))
    mask[pts[:, 1], pts[:, 0]] = 0
    _, labels = cv2.distanceTransformWithLabels(mask, cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_CCOMP)
    tone = rng.uniform(0.4, 1.0, labels.max() + 1).astype(np.float32)
    img = tone[labels]
    edge = ((labels != np.roll(labels, 1, 0)) | (labels != np.roll(labels, 1, 1))).astype(np.float32)
    return img * (1.0 - 0.85 * cv2.GaussianBlur(edge, (0, 0), 0.7))


PATTERNS = {"noise": _noise, "folds": _folds, "stripes": _stripes, "cells": _cells, "vessels": _vessels,
            "marble": _marble, "mesh": _mesh, "crackle": _crackle}
"""Every procedural pattern (``POOLS`` in ``common.sim.random_looks`` splits them)."""


# ---------------------------------------------------------------- photographs (scikit-image)

PHOTOS = {
    # name: the scikit-image loader (skimage.data.NAME, or a function of the module)
    "immunohistochemistry": "immunohistochemistry", "retina": "retina", "gravel": "gravel", "grass": "grass",
    "coffee": "coffee", "chelsea": "chelsea", "hubble_deep_field": "hubble_deep_field", "cell": "cell",
    "astronaut": "astronaut", "rocket": "rocket", "camera": "camera", "coins": "coins",
    "brick": "brick", "moon": "moon", "motorcycle": "stereo_motorcycle", "clock": "clock", "page": "page",
}
"""Every photograph a texture may use: sample images inside the scikit-image wheel (no download)."""

_PHOTO_CACHE: dict = {}
_SAID = set()


def photos_available() -> bool:
    """Whether scikit-image is installed (the ``train`` extra); says once on stderr when it is not."""
    try:
        import skimage.data  # noqa: F401
    except ImportError:
        if "photos" not in _SAID:
            _SAID.add("photos")
            print("needletrack: scikit-image is not installed (pip install 'needletrack[train]'): the random "
                  "looks use procedural textures only, no photographs", file=sys.stderr)
        return False
    return True


def photo(name: str) -> np.ndarray:
    """The photograph ``name`` of ``PHOTOS``, square-cropped to BASE x BASE, RGB float32 0..1."""
    if name not in _PHOTO_CACHE:
        import skimage.data
        img = getattr(skimage.data, PHOTOS[name])()
        img = img[0] if isinstance(img, tuple) else img
        img = np.asarray(img)
        if img.dtype == bool:
            img = img.astype(np.uint8) * 255
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        img = img[..., :3].astype(np.float32) / (255.0 if img.dtype == np.uint8 else float(img.max() or 1))
        h, w = img.shape[:2]
        s = min(h, w)
        img = img[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
        _PHOTO_CACHE[name] = cv2.resize(img, (BASE, BASE), interpolation=cv2.INTER_AREA)
    return _PHOTO_CACHE[name]


# ---------------------------------------------------------------- the texture

def _palette_lut(palette) -> np.ndarray:
    """256 x 3 float32: grey level -> colour, through the palette's dark, middle and light stops."""
    stops = np.asarray(palette, np.float32).reshape(-1, 3)
    t = np.linspace(0, 1, 256, dtype=np.float32)
    xs = np.linspace(0, 1, len(stops))
    return np.stack([np.interp(t, xs, stops[:, k]) for k in range(3)], axis=1).astype(np.float32)


def _levels(g: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(g[::4, ::4], (1, 99))
    return np.clip((g - lo) / max(hi - lo, 1e-6), 0, 1)


def look_texture(t: TextureLook, size: int) -> np.ndarray:
    """The texture ``t`` describes, (size, size, 3) RGB uint8."""
    rng = np.random.default_rng(t.seed)
    if t.kind.startswith("photo:"):
        rgb = photo(t.kind[6:])
        grey = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
        if t.photo_hue and float(np.std(rgb - grey[..., None])) > 0.02:
            hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)           # H in degrees
            hsv[..., 0] = (hsv[..., 0] + 360.0 * t.hue_turn) % 360.0
            col = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
        else:
            col = _palette_lut(t.palette)[(_levels(grey) * 255).astype(np.uint8)]
    else:
        grey = _levels(PATTERNS[t.kind](rng, BASE)).astype(np.float32)
        col = _palette_lut(t.palette)[(grey * 255).astype(np.uint8)]
    if t.relief > 0:
        g = cv2.GaussianBlur(grey, (0, 0), 1.5)
        slope = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3) + cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
        shade = 1.0 + t.relief * 2.5 * slope   # lit from the top left: an emboss
        col = col * np.clip(shade, 0.4, 1.6)[..., None]
    img = (np.clip(col, 0, 1) * 255).astype(np.uint8)
    if t.stains > 0:
        img = _stains(img, rng, t.stains)
    for _ in range(t.incisions):
        _incision(img, rng)
    c = (BASE - 1) / 2.0
    M = cv2.getRotationMatrix2D((c, c), np.rad2deg(t.angle), t.zoom * size / BASE)
    M[:, 2] += (size - 1) / 2.0 - c
    return cv2.warpAffine(img, M, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT101)


def _stains(img: np.ndarray, rng, share: float) -> np.ndarray:
    """Blood-like stains: dark red blobs, glossy-dark at their cores, over about ``share`` of the area."""
    n = img.shape[0]
    blob = value_noise(rng, (n, n), n / rng.uniform(4, 12)) * 0.7 + 0.3 * value_noise(rng, (n, n), n / 40)
    thr = np.quantile(blob[::8, ::8], 1.0 - share)
    a = np.clip((blob - thr) / 0.04, 0, 1)[..., None] * rng.uniform(0.6, 0.95)
    red = np.array([rng.uniform(90, 160), rng.uniform(0, 20), rng.uniform(5, 25)], np.float32)
    core = np.clip((blob - thr) / 0.15, 0, 1)[..., None]
    colour = red * (1.0 - 0.5 * core)
    return (img * (1.0 - a) + colour * a).astype(np.uint8)


def _incision(img: np.ndarray, rng) -> None:
    """A cut or a pad's edge: a dark wandering line with a bright lip beside it (in place)."""
    n = img.shape[0]
    p = rng.uniform(0.1 * n, 0.9 * n, 2)
    ang = rng.uniform(0, 2 * np.pi)
    pts = []
    for _ in range(int(rng.integers(8, 30))):
        pts.append(p.copy())
        ang += rng.normal(0, 0.15)
        p = p + n / 60 * np.array([np.cos(ang), np.sin(ang)])
    pts = np.float32(pts)
    w = int(rng.integers(1, 4))
    dark = tuple(float(v) for v in np.clip(img[int(np.clip(pts[0, 1], 0, n - 1)), int(np.clip(pts[0, 0], 0, n - 1))]
                                           * rng.uniform(0.2, 0.5), 0, 255))
    cv2.polylines(img, [np.int32(pts)], False, dark, w, cv2.LINE_AA)
    cv2.polylines(img, [np.int32(pts + w)], False, (235, 230, 225), max(1, w // 2), cv2.LINE_AA)
