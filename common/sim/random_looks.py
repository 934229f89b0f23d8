"""The ``random`` preset's looks, in which no look is special, and the held-out ``unseen`` family.

``POOLS`` is the one place that splits the textures and instrument kinds between the looks the
detector trains on (``train``: the ``random`` preset) and the looks kept for measuring how it
generalises (``unseen``: the ``unseen`` family, which no training render uses):

| pool | procedural patterns | photographs (scikit-image) | instrument kinds |
| --- | --- | --- | --- |
| train | noise, folds, stripes, cells, vessels | immunohistochemistry, retina, gravel, grass, coffee, chelsea, hubble_deep_field, cell, astronaut, rocket, camera, coins | grasper, needle_driver, scissors, maryland, bipolar |
| unseen | marble, mesh, crackle | brick, moon, motorcycle, clock, page | hook, clip_applier, suction |

Everything else is drawn alike in both: palettes over the whole hue circle (tissue reds and
pinks, greens, blues, greys, white pads, dark drapes), 1-4 lights of 2700-8000 K and any
strength, tissue specularity, needles from bright steel to dark coated, threads of any colour or
none, instruments of any finish (shiny or matt metal, black, gold inserts) and, beyond the two
of the other presets, a third and fourth instrument, sometimes near the camera
(``extra_instruments``). The image-space effects are ``common.sim.image_effects``.
"""
from __future__ import annotations

import colorsys
from dataclasses import replace

import numpy as np

from common.geometry.transforms import transform_points
from common.sim.instrument_kinds import GRASPING
from common.sim.look_textures import TextureLook, photos_available
from common.sim.scene import Appearance, Instrument
from common.sim.scene_looks import LOOK_INSTRUMENTS, LOOK_LIGHTS, InstrumentLook, LightLook, Look

POOLS = {
    "train": {"patterns": ("noise", "folds", "stripes", "cells", "vessels"),
              "photos": ("immunohistochemistry", "retina", "gravel", "grass", "coffee", "chelsea",
                         "hubble_deep_field", "cell", "astronaut", "rocket", "camera", "coins"),
              "instruments": ("grasper", "needle_driver", "scissors", "maryland", "bipolar")},
    "unseen": {"patterns": ("marble", "mesh", "crackle"),
               "photos": ("brick", "moon", "motorcycle", "clock", "page"),
               "instruments": ("hook", "clip_applier", "suction")},
}

P_PHOTO = 0.3          # share of textures that are photographs (when scikit-image is installed)


# ---------------------------------------------------------------- colours

def _hsv(h, s, v) -> np.ndarray:
    return np.array(colorsys.hsv_to_rgb(h % 1.0, float(np.clip(s, 0, 1)), float(np.clip(v, 0, 1))))


def palette(rng: np.random.Generator, role: str) -> tuple:
    """Dark, middle and light colours (RGB 0..1) of a texture: tissue-like reds, pinks and yellows
    in a third of the pads, greys and whites in a fifth, any hue otherwise; backgrounds darker."""
    u = rng.random()
    if u < 0.35:
        h, s, v = rng.uniform(-0.06, 0.14), rng.uniform(0.25, 0.85), rng.uniform(0.45, 0.95)
    elif u < 0.55:
        h, s, v = rng.random(), rng.uniform(0.0, 0.12), rng.uniform(0.3, 1.0)
    else:
        h, s, v = rng.random(), rng.uniform(0.2, 0.9), rng.uniform(0.3, 0.95)
    if role == "table":
        v *= rng.uniform(0.3, 0.9)
    dh = rng.normal(0, 0.04, 2)
    dark = _hsv(h + dh[0], s * rng.uniform(0.8, 1.3), v * rng.uniform(0.2, 0.6))
    mid = _hsv(h, s, v)
    light = _hsv(h + dh[1], s * rng.uniform(0.2, 0.8), min(1.0, v * rng.uniform(1.05, 1.4)))
    return tuple(tuple(float(c) for c in col) for col in (dark, mid, light))


def kelvin_rgb(kelvin: float) -> np.ndarray:
    """RGB (max 1) of a black body at ``kelvin`` (Tanner Helland's fit, 1000-40000 K)."""
    t = kelvin / 100.0
    r = 255.0 if t <= 66 else 329.698727446 * (t - 60) ** -0.1332047592
    g = 99.4708025861 * np.log(t) - 161.1195681661 if t <= 66 else 288.1221695283 * (t - 60) ** -0.0755148492
    b = 255.0 if t >= 66 else (0.0 if t <= 19 else 138.5177312231 * np.log(t - 10) - 305.0447927307)
    rgb = np.clip([r, g, b], 0, 255) / 255.0
    return rgb / rgb.max()


# ---------------------------------------------------------------- the look

def texture_look(rng: np.random.Generator, pool: dict, role: str, photos: bool) -> TextureLook:
    """A texture of the pool for the pad (``tissue``) or the background (``table``)."""
    if photos and rng.random() < P_PHOTO:
        kind = "photo:" + str(rng.choice(pool["photos"]))
    else:
        kind = str(rng.choice(pool["patterns"]))
    tissue = role == "tissue"
    return TextureLook(kind, int(rng.integers(1 << 30)), palette(rng, role), zoom=float(np.exp(rng.uniform(0, 1.2))),
                       angle=float(rng.uniform(-np.pi, np.pi)), relief=float(rng.uniform(0, 0.8)),
                       stains=float(rng.uniform(0.02, 0.25)) if tissue and rng.random() < 0.35 else 0.0,
                       incisions=int(rng.integers(1, 4)) if tissue and rng.random() < 0.3 else 0,
                       photo_hue=bool(rng.random() < 0.5), hue_turn=float(rng.random()))


def _finish(rng: np.random.Generator, kind: str) -> tuple:
    """(r, g, b, specular, shininess, reflectance) of a shiny metal, a matt metal, a black coating
    or a gold-coloured insert."""
    if kind == "metal":
        v = rng.uniform(0.45, 0.85)
        return (*np.clip(v + rng.normal(0, 0.02, 3), 0, 1), rng.uniform(0.5, 1.0), rng.uniform(0.4, 1.0),
                rng.uniform(0.0, 0.3))
    if kind == "matt":
        v = rng.uniform(0.3, 0.6)
        return (*np.clip(v + rng.normal(0, 0.02, 3), 0, 1), rng.uniform(0.1, 0.4), rng.uniform(0.1, 0.4), 0.0)
    if kind == "gold":
        return (*_hsv(rng.uniform(0.09, 0.14), rng.uniform(0.4, 0.7), rng.uniform(0.55, 0.85)),
                rng.uniform(0.5, 0.9), rng.uniform(0.4, 0.8), 0.0)
    v = rng.uniform(0.03, 0.15)                                              # black coating
    return (*np.full(3, v), rng.uniform(0.2, 0.8), rng.uniform(0.3, 0.9), 0.0)


def instrument_look(rng: np.random.Generator, kind: str) -> InstrumentLook:
    finishes = ("metal", "matt", "black")
    return InstrumentLook(kind, float(rng.uniform(0.0025, 0.0045)),
                          tuple(float(x) for x in _finish(rng, "black" if rng.random() < 0.6 else "metal")),
                          tuple(float(x) for x in _finish(rng, str(rng.choice(finishes, p=[0.5, 0.25, 0.25])))),
                          tuple(float(x) for x in _finish(rng, str(rng.choice(finishes + ("gold",))))))


def light_looks(rng: np.random.Generator) -> tuple:
    """1-4 lights on the endoscope: colour temperature 2700-8000 K; the first 0.5-1.3 strong,
    the others 0.1-0.6."""
    n = int(rng.integers(1, LOOK_LIGHTS + 1))
    strength = np.concatenate([[rng.uniform(0.5, 1.3)], rng.uniform(0.1, 0.6, n - 1)])
    out = []
    for k in range(n):
        pos = (rng.uniform(-0.006, 0.006, 3) * [1, 1, 0.3] if k < 2
               else np.append(rng.uniform(-0.03, 0.03, 2), rng.uniform(-0.02, 0.01)))
        d = np.array([rng.normal(0, 0.15), rng.normal(0, 0.15), -1.0])
        rgb = kelvin_rgb(rng.uniform(2700, 8000)) * strength[k]
        out.append(LightLook(tuple(float(x) for x in pos), tuple(float(x) for x in d),
                             tuple(float(x) for x in rgb), float(rng.uniform(0.2, 1.3)),
                             float(rng.uniform(45, 85)), float(rng.uniform(0.5, 6))))
    return tuple(out)


def sample_look(rng: np.random.Generator, a: Appearance, pool_name: str) -> Appearance:
    """The ``random`` look of pool ``pool_name`` on top of an appearance (see the module docstring)."""
    pool = POOLS[pool_name]
    photos = photos_available()
    tissue, table = texture_look(rng, pool, "tissue", photos), texture_look(rng, pool, "table", photos)
    kinds = [str(rng.choice([k for k in pool["instruments"] if k in GRASPING]))]   # slot 0 may hold the needle
    kinds += [str(rng.choice(pool["instruments"])) for _ in range(LOOK_INSTRUMENTS - 1)]
    look = Look(tissue, table, light_looks(rng), tuple(instrument_look(rng, k) for k in kinds))
    steel = rng.random()                                   # 0 dark coated .. 1 bright steel
    v = 0.08 + 0.82 * steel
    needle = np.clip(v + rng.normal(0, 0.03, 3), 0, 1)
    u = rng.random()
    if u < 0.15:
        thread_rgb, visible = a.thread_rgb, False
    elif u < 0.3:
        thread_rgb, visible = tuple(np.full(3, rng.choice([0.06, 0.85, 0.95]))), True  # black, undyed, white
    else:
        thread_rgb, visible = tuple(_hsv(rng.random(), rng.uniform(0.3, 1.0), rng.uniform(0.25, 0.95))), True
    return replace(
        a, look=look, tissue_rgb=(1.0, 1.0, 1.0), table_rgb=(1.0, 1.0, 1.0),
        tissue_specular=float(rng.uniform(0.0, 1.0)), tissue_shininess=float(rng.uniform(0.02, 1.0)),
        needle_rgb=tuple(float(x) for x in needle), needle_specular=float(rng.uniform(0.15, 0.5) + 0.5 * steel),
        needle_shininess=float(rng.uniform(0.2, 1.0)), needle_reflectance=float(rng.uniform(0, 0.3) * steel),
        thread_rgb=tuple(float(x) for x in thread_rgb), thread_visible=visible and a.thread_visible,
        thread_length_m=float(rng.uniform(0.004, 0.09)), ambient=float(rng.uniform(0.05, 0.35)))


def with_graspers(rng: np.random.Generator, a: Appearance, pool_name: str, slots: int) -> Appearance:
    """The look with its first ``slots`` instruments of kinds that can hold the needle (a take's
    instruments pass it between them)."""
    kinds = [k for k in POOLS[pool_name]["instruments"] if k in GRASPING]
    looks = tuple(replace(il, kind=str(rng.choice(kinds))) if i < slots and il.kind not in GRASPING else il
                  for i, il in enumerate(a.look.instruments))
    return replace(a, look=replace(a.look, instruments=looks))


# ---------------------------------------------------------------- more instruments, nearer the camera

def extra_instruments(rng: np.random.Generator, inst: list, T_world_needle: np.ndarray, needle, rig,
                      T_world_ecm: np.ndarray, p_near: float, p_more: float = 0.35,
                      over_needle: bool = False) -> list:
    """Up to ``LOOK_INSTRUMENTS`` instruments: a third and a fourth beside the needle with
    probability ``p_more`` each, either one near the camera (1.2-5 cm in front of it, coming in from
    the image's side) with probability ``p_near``. A near one keeps its tip's pixel off the
    needle's image, so that it covers the needle only where its shaft passes, unless
    ``over_needle`` (needle-free frames: its jaws may lie anywhere, the image's centre too)."""
    out = list(inst)
    cam = rig["left"]
    T_world_cam = T_world_ecm @ cam.T_ecm_cam
    centre = transform_points(T_world_needle, needle.keypoints()).mean(axis=0)
    uv_needle = cam.project(transform_points(np.linalg.inv(T_world_cam), needle.sample_arc(12)))
    while len(out) < LOOK_INSTRUMENTS:
        if rng.random() < p_near:
            out.append(_near_camera(rng, cam, T_world_cam, None if over_needle else uv_needle))
        elif rng.random() < p_more:
            side = 1.0 if rng.random() < 0.5 else -1.0
            ang = rng.uniform(0, 2 * np.pi)
            tip = centre + np.array([*(rng.uniform(0.012, 0.045) * np.array([np.cos(ang), np.sin(ang)])),
                                     rng.uniform(0.004, 0.03)])
            trocar = np.array([side * rng.uniform(0.1, 0.18), rng.uniform(-0.12, 0.08), rng.uniform(0.15, 0.22)])
            d = trocar - tip
            out.append(Instrument(tuple(tip), tuple(d / np.linalg.norm(d)), float(rng.uniform(-np.pi, np.pi)),
                                  float(rng.uniform(0.0, 0.9))))
        else:
            break
    return out


def _near_camera(rng: np.random.Generator, cam, T_world_cam: np.ndarray, uv_needle: np.ndarray | None) -> Instrument:
    """An instrument whose jaws are 1.2-5 cm in front of the camera, its shaft leaving the image
    sideways; its tip's pixel off ``uv_needle``'s box (when given)."""
    w, h = cam.width, cam.height
    for _ in range(20):
        side = 1.0 if rng.random() < 0.5 else -1.0
        u = w / 2 + side * rng.uniform(0.0 if uv_needle is None else 0.1, 0.45) * w
        v = rng.uniform(0.1, 0.9) * h
        if uv_needle is None:
            break
        lo, hi = uv_needle.min(axis=0), uv_needle.max(axis=0)
        if not (lo[0] - 0.1 * w < u < hi[0] + 0.1 * w and lo[1] - 0.1 * h < v < hi[1] + 0.1 * h):
            break
    depth = rng.uniform(0.012, 0.05)
    p_cam = depth * np.linalg.solve(cam.K, [u, v, 1.0])
    d_cam = np.array([side, rng.uniform(-0.3, 0.3), -rng.uniform(0.2, 0.8)])   # out sideways, back towards the scope
    tip = transform_points(T_world_cam, p_cam[None])[0]
    d = T_world_cam[:3, :3] @ (d_cam / np.linalg.norm(d_cam))
    return Instrument(tuple(tip), tuple(d), float(rng.uniform(-np.pi, np.pi)), float(rng.uniform(0.0, 0.9)))
