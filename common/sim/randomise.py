"""Random but physical scenes for the simulator: needle poses, endoscope poses, appearance,
instruments and image degradations, under named presets.

Presets (``PRESETS``):
- ``none``: nominal appearance, no instruments, clean images; poses still random.
- ``test``: the standard evaluation look: moderate appearance variation, two instruments
  (sometimes holding the needle), mild sensor noise; no image-space augmentation.
- ``train``: wide variation of light, tissue, needle finish and wire diameter, instruments that
  may occlude the needle, sensor noise, blur, JPEG artefacts, brightness/contrast +-30%.
- ``wide``: ``train`` across looks: tissue from pale pink through red, magenta and purple to
  yellowish; flat-lit scenes in a third of the frames; tip tapers from short to long and blunter
  or thicker tails; the thread cut short or tissue-coloured in a third of the frames.

Two look families no training stage renders (``FAMILIES``), for measuring how the detector and
its stated end identity generalise:
- ``silicone``: ``test`` on a silicone suture pad: mint green, teal or blue; the
  held-out family of the first renderer (kept out of training and of every fit).
- ``liver``: ``train`` on dark, glossy brown tissue under a warm light; the end identity's
  calibration family (fitted on, never trained on, never reported as held out).

- ``random``: ``train``'s poses and occlusions in looks where none is special
  (``common.sim.random_looks``): procedural and photographic textures recoloured over the whole
  hue circle, 1-4 lights of any colour temperature, needles from bright steel to dark coated,
  threads of any colour or none, instruments of five kinds and any finish, a third and fourth
  instrument (some near the camera), blood-like stains and cuts on the pad, and the image
  effects of ``common.sim.image_effects`` (haze, glare, streaks, defocus and motion blur,
  vignetting, white balance) before a harsher sensor model. Its draws come after ``train``'s,
  inside its own code paths, so the other presets draw what they always drew.
- ``unseen`` (a family of ``FAMILIES``): ``random`` with the held-out pool of textures,
  photographs and instrument kinds (``common.sim.random_looks.POOLS``) that ``random`` never
  uses: for measuring honestly how the detector generalises.

Image rotation (the paper's other augmentation) changes the camera model, so it is not baked
into data that claims a pinhole ``K``; trainers apply ``rotate_with_keypoints`` on the fly.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import MULTIVIEW_STEP_RAD, REVOLUTE_JOINTS, EcmArm
from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T, make_T, rotvec_to_R, transform_points
from common.sim.image_effects import look_effects
from common.sim.random_looks import extra_instruments, sample_look
from common.sim.scene import Appearance, Instrument, SceneSpec
from common.sim.scene_meshes import PHANTOM_SIZE, phantom_height

RCM_WORLD = np.array([0.0, -0.12, 0.27])  # the ECM's remote centre of motion above the table
DISTANCE_RANGE_M = (0.10, 0.25)


# suture colours (violet, black, green, undyed, blue); the undyed one is as pale as the needle
THREAD_RGBS = ((0.35, 0.15, 0.55), (0.1, 0.1, 0.12), (0.2, 0.45, 0.3), (0.85, 0.85, 0.8), (0.15, 0.2, 0.5))
PALE_THREAD_RGB = THREAD_RGBS[3]

def default_arm() -> EcmArm:
    """The built-in ECM: RCM above and behind the phantom, insertion axis (at q = 0) aimed at the
    pad's centre, ECM x along world x (so image right is world +x)."""
    target = np.array([0.0, 0.0, 0.012])
    view = target - RCM_WORLD
    view /= np.linalg.norm(view)
    z = -view  # insertion runs along -z of the base/ECM frame
    x = np.array([1.0, 0.0, 0.0])
    x -= z * (x @ z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return EcmArm(make_T(np.stack([x, y, z], axis=1), RCM_WORLD), 0.0, 0.0)


@dataclass(frozen=True)
class Preset:
    name: str
    appearance_jitter: float      # 0 = nominal look, 1 = full variation
    instruments: bool
    p_held: float                 # probability the needle is held above the tissue by an instrument
    p_occlude: float              # probability a free instrument is placed across the needle
    roll_range: float             # +- ECM roll (rad)
    offcentre_rad: float          # +- aim offset of yaw/pitch (rad)
    noise_sigma: tuple            # sensor noise sigma range (grey levels)
    blur_sigma: tuple             # Gaussian blur sigma range (px)
    jpeg_quality: tuple           # re-compression quality range; (100, 100) = none
    brightness: float             # +- relative gain
    contrast: float               # +- relative contrast
    p_shadows: float = 0.0        # probability of cast shadows (they make a frame ~3x slower to render)
    looks: bool = False           # the ``wide`` looks (drawn after the others: other presets keep their draws)
    family: str = ""              # a look family of FAMILIES (drawn last)
    pool: str = ""                # the random looks of this pool of common.sim.random_looks.POOLS (drawn last)
    p_near: float = 0.0           # random looks: probability of each extra instrument near the camera
    p_streaks: float = 0.0        # random looks: probability of specular streaks in a frame
    near_over_needle: bool = False  # random looks: near jaws may lie where the needle is (needle-free frames)


PRESETS = {
    "none": Preset("none", 0.0, False, 0.0, 0.0, 0.3, 0.05, (0, 0), (0, 0), (100, 100), 0.0, 0.0),
    "test": Preset("test", 0.5, True, 0.3, 0.1, 0.4, 0.07, (0.5, 2.0), (0, 0.4), (100, 100), 0.1, 0.1),
    "train": Preset("train", 1.0, True, 0.35, 0.25, 0.8, 0.09, (0, 5.0), (0, 1.2), (55, 100), 0.3, 0.3, 0.25),
}
PRESETS["wide"] = replace(PRESETS["train"], name="wide", looks=True)
PRESETS["silicone"] = replace(PRESETS["test"], name="silicone", family="silicone")
PRESETS["liver"] = replace(PRESETS["train"], name="liver", family="liver")
PRESETS["random"] = replace(PRESETS["train"], name="random", noise_sigma=(0, 8.0), jpeg_quality=(35, 100),
                            brightness=0.35, contrast=0.35, p_shadows=0.15, pool="train", p_near=0.15,
                            p_streaks=0.3)
PRESETS["unseen"] = replace(PRESETS["random"], name="unseen", family="unseen", pool="unseen")

FAMILIES = {
    # tissue colours (RGB 0..1) and the light's colour of each family outside training
    "silicone": {"tissue": ((0.55, 0.80, 0.62), (0.30, 0.60, 0.58), (0.30, 0.42, 0.68)),
                 "light": (1.0, 0.97, 0.92), "specular": (0.2, 0.5)},
    "liver": {"tissue": ((0.30, 0.14, 0.08), (0.40, 0.20, 0.10), (0.25, 0.15, 0.12)),
              "light": (1.0, 0.84, 0.62), "specular": (0.6, 0.9)},
    # the random looks' held-out pool of textures, photographs and instrument kinds
    "unseen": {"pool": "unseen"},
}

# tissue colours of the ``wide`` preset (RGB 0..1): pale pink, salmon, red, dark red, magenta,
# purple, yellowish (fat), tan
TISSUE_RGBS = ((0.93, 0.72, 0.72), (0.90, 0.55, 0.48), (0.80, 0.25, 0.22), (0.55, 0.12, 0.12),
               (0.85, 0.35, 0.62), (0.52, 0.28, 0.55), (0.90, 0.80, 0.45), (0.80, 0.62, 0.45))


def get_preset(name: str) -> Preset:
    if name not in PRESETS:
        raise ValueError(f"randomise: unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    return PRESETS[name]


# ---------------------------------------------------------------- appearance

def sample_appearance(rng: np.random.Generator, preset: Preset) -> Appearance:
    j = preset.appearance_jitter
    a = Appearance(texture_seed=int(rng.integers(1 << 30)))
    if j == 0:
        return a
    shadows = bool(rng.random() < preset.p_shadows) if preset.p_shadows > 0 else False

    def jit(v, s, lo=0.0, hi=1.0):
        return float(np.clip(v + rng.uniform(-s, s) * j, lo, hi))

    hue = rng.uniform(-1, 1) * j
    tissue = np.array([0.86, 0.52 + 0.12 * hue, 0.50 + 0.08 * hue]) * rng.uniform(1 - 0.25 * j, 1 + 0.1 * j)
    a = replace(
        a,
        tissue_rgb=tuple(np.clip(tissue + rng.normal(0, 0.04 * j, 3), 0.1, 1.0)),
        tissue_specular=jit(0.35, 0.25), tissue_shininess=jit(0.25, 0.2),
        table_rgb=tuple(np.clip(np.array([0.12, 0.16, 0.14]) + rng.normal(0, 0.06 * j, 3), 0.02, 0.5)),
        needle_rgb=tuple(np.full(3, jit(0.76, 0.15)) + rng.normal(0, 0.02 * j, 3)),
        needle_specular=jit(0.85, 0.35), needle_shininess=jit(0.8, 0.3),
        needle_reflectance=jit(0.0, 0.3, 0.0, 0.5) if j >= 1 else 0.0,
        wire_diameter_m=float(np.clip(0.0008 + rng.uniform(-0.00025, 0.00025) * j, 0.0004, 0.0012)),
        thread_rgb=tuple(rng.choice(THREAD_RGBS)),
        thread_diameter_m=float(rng.uniform(0.00025, 0.00045)),
        thread_length_m=float(rng.uniform(0.03, 0.08)),
        light_diffuse=jit(0.75, 0.3, 0.3, 1.2),
        light_rgb=tuple(np.clip(1.0 + rng.normal(0, 0.05 * j, 3), 0.8, 1.0)),
        light_offset=tuple(rng.uniform(-0.006, 0.006, 3) * j + np.array([0, 0.004, 0])),
        ambient=jit(0.12, 0.08, 0.02, 0.3),
        shadows=shadows,
    )
    if preset.pool:
        return sample_look(rng, a, preset.pool)
    a = sample_looks(rng, a) if preset.looks else a
    return sample_family(rng, a, preset.family) if preset.family else a


def sample_family(rng: np.random.Generator, a: Appearance, family: str) -> Appearance:
    """A look family's tissue and light on top of an appearance (``FAMILIES``)."""
    f = FAMILIES[family]
    i, k = rng.integers(len(f["tissue"]), size=2)
    tissue = np.asarray(f["tissue"][i]) + rng.uniform(0, 0.5) * (np.asarray(f["tissue"][k]) - f["tissue"][i])
    light = np.asarray(f["light"]) * rng.uniform(0.95, 1.0, 3)
    return replace(a, tissue_rgb=tuple(np.clip(tissue * rng.uniform(0.9, 1.08) + rng.normal(0, 0.02, 3), 0.05, 1.0)),
                   light_rgb=tuple(np.clip(light, 0.0, 1.0)),
                   tissue_specular=float(rng.uniform(*f["specular"])))


def sample_looks(rng: np.random.Generator, a: Appearance) -> Appearance:
    """The ``wide`` preset's looks on top of an appearance (see the module docstring)."""
    i, k = rng.integers(len(TISSUE_RGBS), size=2)
    tissue = np.asarray(TISSUE_RGBS[i]) + rng.uniform(0, 1) * (np.asarray(TISSUE_RGBS[k]) - TISSUE_RGBS[i])
    a = replace(a, tissue_rgb=tuple(np.clip(tissue * rng.uniform(0.85, 1.1) + rng.normal(0, 0.03, 3), 0.05, 1.0)),
                tip_length_m=float(rng.uniform(0.0006, 0.0045)), tip_exponent=float(rng.uniform(0.5, 1.2)),
                swage_scale=float(rng.uniform(1.0, 1.35)))
    if rng.random() < 1 / 3:   # flat-lit: strong ambient, weak key light
        a = replace(a, ambient=float(rng.uniform(0.35, 0.6)), light_diffuse=float(rng.uniform(0.2, 0.45)))
    u = rng.random()
    if u < 1 / 6:              # cut short at the swage
        a = replace(a, thread_length_m=float(rng.uniform(0.002, 0.008)))
    elif u < 1 / 3:            # the tissue's colour
        a = replace(a, thread_rgb=tuple(np.clip(np.asarray(a.tissue_rgb) * rng.uniform(0.8, 1.05), 0, 1)))
    return a


# ---------------------------------------------------------------- needle and instruments

def rest_height(T: np.ndarray, needle: NeedleModel, wire_r: float) -> float:
    """z translation that puts the lowest part of the wire on the phantom's surface."""
    p = transform_points(T, needle.sample_arc(48))
    gap = phantom_height(p[:, 0], p[:, 1]) - p[:, 2]
    return float(np.max(gap)) + wire_r


def sample_needle_pose(rng: np.random.Generator, needle: NeedleModel, wire_r: float, held: bool) -> np.ndarray:
    """T_world_needle resting flat on the phantom (held=False) or held 3-25 mm above it."""
    hx, hy = PHANTOM_SIZE[0] / 2 - 0.025, PHANTOM_SIZE[1] / 2 - 0.022
    xy = rng.uniform([-hx, -hy], [hx, hy])
    if held:
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        R = rotvec_to_R(axis * rng.uniform(0, np.pi))
    else:
        flip = rotvec_to_R([np.pi, 0, 0]) if rng.random() < 0.5 else np.eye(3)
        R = rotvec_to_R([0, 0, rng.uniform(-np.pi, np.pi)]) @ rotvec_to_R(
            np.append(rng.normal(0, 0.08, 2), 0.0)) @ flip
    T = make_T(R, [xy[0], xy[1], 0.0])
    T[2, 3] = rest_height(T, needle, wire_r)
    if held:
        T[2, 3] += rng.uniform(0.003, 0.025)
    return T


def _shaft_towards(tip: np.ndarray, side: float, rng: np.random.Generator) -> np.ndarray:
    """Unit vector from an instrument tip towards its trocar, on the left (-1) or right (+1)."""
    trocar = np.array([side * rng.uniform(0.12, 0.18), rng.uniform(-0.1, 0.06), rng.uniform(0.15, 0.22)])
    d = trocar - tip
    return d / np.linalg.norm(d)


def sample_instruments(rng: np.random.Generator, T_world_needle: np.ndarray, needle: NeedleModel,
                       held: bool, preset: Preset) -> list[Instrument]:
    """Two instruments around the needle: one holds it (when held), one may lie across it."""
    if not preset.instruments:
        return []
    out = []
    centre = transform_points(T_world_needle, needle.keypoints()).mean(axis=0)
    sides = [-1.0, 1.0] if rng.random() < 0.5 else [1.0, -1.0]
    for i, side in enumerate(sides):
        if held and i == 0:
            a = np.deg2rad(rng.uniform(110, 145))  # grasp between C and E
            tip = transform_points(T_world_needle, needle.arc_points([a]))[0]
            out.append(Instrument(tuple(tip), tuple(_shaft_towards(tip, side, rng)),
                                  float(rng.uniform(-np.pi, np.pi)), 0.06))
            continue
        if rng.random() < preset.p_occlude:
            # jaws over part of the needle, the shaft leading away from it: a partial occlusion
            ang = np.arctan2(0.0, side) + rng.uniform(-0.6, 0.6)
            off = rng.uniform(0.005, 0.009) * np.array([np.cos(ang), np.sin(ang)])
            lift = rng.uniform(0.004, 0.012)
        else:
            # beside the needle on the trocar's side, so the shaft does not cross the needle
            ang = np.arctan2(0.0, side) + rng.uniform(-1.2, 1.2)
            off = rng.uniform(0.018, 0.04) * np.array([np.cos(ang), np.sin(ang)])
            lift = rng.uniform(0.004, 0.025)
        xy = centre[:2] + off
        tip = np.array([xy[0], xy[1], float(phantom_height(xy[0], xy[1])) + lift])
        tip[2] = max(tip[2], centre[2] + 0.003) if np.linalg.norm(off) < 0.012 else tip[2]
        out.append(Instrument(tuple(tip), tuple(_shaft_towards(tip, side, rng)),
                              float(rng.uniform(-np.pi, np.pi)), float(rng.uniform(0.0, 0.7))))
    return out


# ---------------------------------------------------------------- endoscope poses

def view_direction(arm: EcmArm, q) -> np.ndarray:
    """World direction of the endoscope's optical axis (-z of the ECM frame) at joints q."""
    return -arm.T_world_ecm(q)[:3, 2]


def aim_joints(arm: EcmArm, target: np.ndarray, roll: float = 0.0, distance: float = 0.15) -> np.ndarray:
    """Joints q whose optical axis passes through ``target`` (world) with the ECM origin
    ``distance`` (m) from it (Gauss-Newton on yaw/pitch; insertion closed form)."""
    rcm = arm.T_world_base[:3, 3]
    w = target - rcm
    d_goal = w / np.linalg.norm(w)
    q = np.array([0.0, 0.0, 0.05, roll])
    for _ in range(20):
        r = view_direction(arm, q) - d_goal
        J = np.empty((3, 2))
        for k, j in enumerate((0, 1)):
            dq = np.zeros(4)
            dq[j] = 1e-6
            J[:, k] = (view_direction(arm, q + dq) - view_direction(arm, q)) / 1e-6
        step = np.linalg.lstsq(J, -r, rcond=None)[0]
        q[:2] += step
        if np.linalg.norm(step) < 1e-12:
            break
    q[2] = insertion_for_distance(arm, q, target, distance)
    return q


def insertion_for_distance(arm: EcmArm, q, target: np.ndarray, distance: float) -> float:
    """Insertion that puts the ECM origin ``distance`` from ``target`` along the current axis."""
    q = np.array(q, dtype=float)
    q[2] = 0.0
    origin0 = arm.T_world_ecm(q)[:3, 3]
    v = view_direction(arm, q)
    w = target - origin0
    b = v @ w
    disc = b * b - w @ w + distance ** 2
    if disc < 0:
        return float(b)  # nearest approach; target not reachable at this distance
    return float(b - np.sqrt(disc)) + 0.0


def keypoints_in_view(rig: StereoRig, needle: NeedleModel, T_world_needle, T_world_ecm,
                      margin: float = 0.0) -> bool:
    """The whole arc in front of both cameras and inside the image shrunk by ``margin`` (fraction)."""
    return rig.sees(transform_points(inv_T(T_world_ecm) @ T_world_needle, needle.sample_arc(12)), margin)


def sample_ecm(rng: np.random.Generator, arm: EcmArm, rig: StereoRig, needle: NeedleModel,
               T_world_needle: np.ndarray, preset: Preset, tries: int = 50) -> np.ndarray | None:
    """Joints looking at the needle from 10-25 cm with the whole needle well inside both images."""
    centre = transform_points(T_world_needle, needle.keypoints()).mean(axis=0)
    for _ in range(tries):
        d = rng.uniform(*DISTANCE_RANGE_M)
        q = aim_joints(arm, centre, rng.uniform(-preset.roll_range, preset.roll_range), d)
        q[:2] += rng.uniform(-preset.offcentre_rad, preset.offcentre_rad, 2)
        q[2] = insertion_for_distance(arm, q, centre, d)
        if keypoints_in_view(rig, needle, T_world_needle, arm.T_world_ecm(q), margin=0.12):
            return q
    return None


def multiview_joints(rng: np.random.Generator, arm: EcmArm, rig: StereoRig, needle: NeedleModel,
                     T_world_needle: np.ndarray, q0, steps: int,
                     step_rad: float = MULTIVIEW_STEP_RAD) -> list[np.ndarray]:
    """The paper's protocol: between steps one random revolute joint (yaw, pitch or roll) moves
    by +-``step_rad`` (0.05 rad); the sign that keeps the needle inside the images is preferred.
    A small ``step_rad`` (e.g. 0.003) makes a sequence a video of a slowly moving endoscope."""
    qs = [np.asarray(q0, dtype=float)]
    for _ in range(steps - 1):
        j = int(rng.choice(REVOLUTE_JOINTS))
        sign = 1.0 if rng.random() < 0.5 else -1.0
        q = qs[-1].copy()
        q[j] += sign * step_rad
        if not keypoints_in_view(rig, needle, T_world_needle, arm.T_world_ecm(q), margin=0.05):
            q2 = qs[-1].copy()
            q2[j] -= sign * step_rad
            if keypoints_in_view(rig, needle, T_world_needle, arm.T_world_ecm(q2), margin=0.05):
                q = q2
        qs.append(q)
    return qs


# ---------------------------------------------------------------- a whole sequence

@dataclass
class SequencePlan:
    """One needle pose seen from several endoscope poses."""

    spec: SceneSpec
    joints: list
    image_seed: int


def plan_sequence(seed: int, sequence: int, steps: int, preset: Preset, rig: StereoRig,
                  needle: NeedleModel, arm: EcmArm, texture_size: int = 1024, msaa: int = 4,
                  step_rad: float = MULTIVIEW_STEP_RAD, thread: bool = True) -> SequencePlan:
    """Deterministic plan of sequence ``sequence`` for a run seeded ``seed``; ``thread=False``
    plans the same scene with no thread drawn (the same random draws: a threadless twin)."""
    rng = np.random.default_rng([seed, sequence])
    for _ in range(100):
        ap = sample_appearance(rng, preset)
        held = preset.instruments and rng.random() < preset.p_held
        T = sample_needle_pose(rng, needle, ap.wire_diameter_m / 2, held)
        q0 = sample_ecm(rng, arm, rig, needle, T, preset)
        if q0 is None:
            continue
        inst = sample_instruments(rng, T, needle, held, preset)
        if preset.pool:
            inst = extra_instruments(rng, inst, T, needle, rig, arm.T_world_ecm(q0), preset.p_near,
                                     over_needle=preset.near_over_needle)
        if not thread:
            ap = replace(ap, thread_visible=False)
        spec = SceneSpec(rig=rig, needle=needle, T_world_needle=T, appearance=ap, instruments=inst,
                         thread_seed=int(rng.integers(1 << 30)), texture_size=texture_size, msaa=msaa)
        qs = multiview_joints(rng, arm, rig, needle, T, q0, steps, step_rad)
        return SequencePlan(spec, qs, int(rng.integers(1 << 30)))
    raise RuntimeError(f"sim: could not place the needle in view for sequence {sequence}")


# ---------------------------------------------------------------- image degradations

def degrade(img: np.ndarray, rng: np.random.Generator, preset: Preset, gain: float = 1.0,
            contrast: float = 1.0, jpeg: bool = True) -> np.ndarray:
    """Sensor-like degradations of a BGR uint8 image: gain/contrast (about the image mean), blur,
    Gaussian noise and, if ``jpeg``, a JPEG round trip at a random quality."""
    out = img
    if gain != 1.0 or contrast != 1.0:
        mean = float(np.mean(cv2.mean(img)[:3]))
        lut = np.clip((np.arange(256) - mean) * contrast + mean * gain + 0.5, 0, 255).astype(np.uint8)
        out = cv2.LUT(out, lut)
    if preset.blur_sigma[1] > 0:
        s = rng.uniform(*preset.blur_sigma)
        if s > 0.05:
            out = cv2.GaussianBlur(out, (0, 0), s)
    if preset.noise_sigma[1] > 0:
        sigma = rng.uniform(*preset.noise_sigma)
        noise = _noise_field(out.shape, rng)
        out = cv2.addWeighted(out, 1.0, noise, sigma / _NOISE_SCALE, 0.0, dtype=cv2.CV_8U)
    if jpeg:
        q = jpeg_quality(rng, preset)
        if q < 100:
            out = cv2.imdecode(cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, q])[1], cv2.IMREAD_COLOR)
    return out


_NOISE_SCALE = 64.0
_NOISE_PAD = 64
_NOISE_BANK: dict = {}


def _noise_field(shape, rng: np.random.Generator) -> np.ndarray:
    """Unit Gaussian noise (times _NOISE_SCALE, int16) of ``shape`` in every channel: a random
    window of a fixed bank, because drawing 6 M normals per image costs 30 ms."""
    h, w, _ = shape
    bank = noise_bank(shape)
    y, x = rng.integers(0, _NOISE_PAD + 1, size=2)
    return bank[y:y + h, x:x + w]


def noise_bank(shape) -> np.ndarray:
    """The fixed bank ``_noise_field`` draws windows of images of ``shape`` (h, w, channels)
    from, made on first use (0.2-0.5 s for 1080p: a live source makes it in its set-up)."""
    h, w, ch = shape
    key = (h, w, ch)
    bank = _NOISE_BANK.get(key)
    if bank is None:
        # the same bank in every process, so that generated data does not depend on the job split
        bank = np.random.default_rng(1234).standard_normal((h + _NOISE_PAD, w + _NOISE_PAD, ch), np.float32)
        bank = np.clip(bank * _NOISE_SCALE, -32767, 32767).astype(np.int16)
        _NOISE_BANK[key] = bank
    return bank


def jpeg_quality(rng: np.random.Generator, preset: Preset) -> int:
    """A JPEG quality from the preset's range (100 = no artefacts)."""
    lo, hi = preset.jpeg_quality
    return 100 if lo >= 100 else int(rng.integers(lo, hi + 1))


def degrade_stereo(images: dict, rng: np.random.Generator, preset: Preset, jpeg: bool = True,
                   avoid: dict | None = None) -> dict:
    """Degrade both images of a frame alike (one gain/contrast), with independent noise; the
    random looks' presets first apply their image effects, whose glare keeps off the pixels of
    ``avoid`` (camera -> (N, 2), e.g. the keypoints)."""
    if preset.pool:
        images = look_effects(images, rng, avoid, preset.p_streaks)
    gain = 1.0 + rng.uniform(-preset.brightness, preset.brightness)
    contrast = 1.0 + rng.uniform(-preset.contrast, preset.contrast)
    return {c: degrade(img, rng, preset, gain, contrast, jpeg) for c, img in images.items()}


def rotate_with_keypoints(img: np.ndarray, uv: np.ndarray, angle_rad: float):
    """Rotate an image about its centre by ``angle_rad`` (counter-clockwise as displayed) and map
    (N, 2) pixel coordinates along; returns (image, uv). For training-time augmentation."""
    h, w = img.shape[:2]
    c = ((w - 1) / 2.0, (h - 1) / 2.0)
    M = cv2.getRotationMatrix2D(c, np.rad2deg(angle_rad), 1.0)
    out = cv2.warpAffine(img, M, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    return out, uv @ M[:, :2].T + M[:, 2]
