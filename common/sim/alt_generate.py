"""Dataset folders rendered by the second renderer (``common/sim/alt_render.py``), not by MuJoCo.

Random scenes of its own (tissue, needle mesh, thread, instruments, lights), an endoscope arm of
its own (another remote centre of motion, same modified-DH model), the paper's multi-view
protocol (N needle poses, each seen from K endoscope poses; between steps one random revolute
ECM joint moves 0.05 rad while the needle stays at rest; the needle 10-25 cm from the endoscope
with the whole needle in view at step 0), written with the project's ``DatasetWriter``.
Sequence ``s`` depends only on (seed, s, steps, image size, supersampling): a run is
reproducible, resumable (finished sequences are kept) and extensible.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import MULTIVIEW_STEP_RAD, REVOLUTE_JOINTS, EcmArm
from common.geometry.needle import NeedleModel
from common.geometry.transforms import (
    inv_T,
    make_T,
    quat_to_R,
    rotvec_to_R,
    transform_points,
)
from common.sim.alt_meshes import (
    LABELS,
    InstrumentShape,
    Material,
    NeedleShape,
    instrument_meshes,
    needle_mesh,
    tube_mesh,
)
from common.sim.alt_render import AltRenderer, AltScene, Light
from common.sim.alt_tissue import Tissue, make_tissue_textures

FPS = 30.0
GENERATE_FILE = "generate_alt.json"
RCM_WORLD = np.array([0.025, -0.14, 0.28])   # this arm's remote centre of motion (m, world z up)
DISTANCE_RANGE_M = (0.10, 0.25)


@dataclass(frozen=True)
class AltGenerateConfig:
    sequences: int
    steps: int
    seed: int = 0
    width: int = 1920
    height: int = 1080
    image_format: str = "jpg"
    jpeg_quality: int = 95
    supersample: int = 3
    thread: str = "random"      # "none": no suture thread drawn (a threadless twin)

    def stable(self) -> dict:
        """What must match for a folder to be resumed or extended."""
        d = dict(self.__dict__)
        d.pop("sequences")
        if d["thread"] == "random":        # folders made before the option resume as they were
            d.pop("thread")
        return d


# ---------------------------------------------------------------- the arm and its poses

def alt_arm() -> EcmArm:
    """This renderer's ECM: RCM at ``RCM_WORLD``, insertion axis at q = 0 aimed at the world
    origin, ECM x along world x (image right is world +x at q = 0)."""
    view = -RCM_WORLD / np.linalg.norm(RCM_WORLD)
    z = -view
    x = np.array([1.0, 0.0, 0.0]) - z * z[0]
    x /= np.linalg.norm(x)
    return EcmArm(make_T(np.stack([x, np.cross(z, x), z], axis=1), RCM_WORLD), 0.0, 0.0)


def view_direction(arm: EcmArm, q) -> np.ndarray:
    """World direction of the optical axis (-z of the ECM frame)."""
    return -arm.T_world_ecm(q)[:3, 2]


def aim_joints(arm: EcmArm, target: np.ndarray, roll: float, distance: float) -> np.ndarray:
    """Joints whose optical axis passes through ``target`` with the ECM origin ``distance`` (m)
    from it. Closed form: with F = RotY(-yaw) RotX(-pitch) RotZ(-roll) (rotation part), the axis
    in the base frame is [sin(yaw) cos(pitch), -sin(pitch), -cos(yaw) cos(pitch)]."""
    d = arm.T_world_base[:3, :3].T @ (np.asarray(target, float) - arm.T_world_base[:3, 3])
    d /= np.linalg.norm(d)
    q = np.array([np.arctan2(d[0], -d[2]), np.arcsin(np.clip(-d[1], -1, 1)), 0.0, roll])
    q[2] = insertion_for_distance(arm, q, target, distance)
    return q


def insertion_for_distance(arm: EcmArm, q, target: np.ndarray, distance: float) -> float:
    """Insertion putting the ECM origin ``distance`` from ``target`` along the current axis (the
    nearer solution; the point of nearest approach when none exists)."""
    q = np.array(q, float)
    q[2] = 0.0
    o = arm.T_world_ecm(q)[:3, 3]
    v = view_direction(arm, q)
    w = np.asarray(target, float) - o
    b = float(v @ w)
    disc = b * b - float(w @ w) + distance ** 2
    return b if disc < 0 else b - float(np.sqrt(disc))


def needle_in_view(rig: StereoRig, needle: NeedleModel, T_world_needle, T_world_ecm, margin: float) -> bool:
    """The whole arc at least 2 cm in front of both cameras and inside both images shrunk by
    ``margin`` (a fraction of the image size)."""
    return rig.sees(transform_points(inv_T(T_world_ecm) @ T_world_needle, needle.sample_arc(16)), margin, 0.02)


def sample_first_view(rng, arm, rig, needle, T_world_needle, tries: int = 60):
    """Step-0 joints: 10-25 cm from the needle, off-centre and rolled a little, all in view."""
    centre = transform_points(T_world_needle, needle.keypoints()).mean(axis=0)
    for _ in range(tries):
        dist = rng.uniform(*DISTANCE_RANGE_M)
        q = aim_joints(arm, centre, rng.uniform(-0.5, 0.5), dist)
        q[:2] += rng.uniform(-0.06, 0.06, 2)
        q[2] = insertion_for_distance(arm, q, centre, dist)
        if needle_in_view(rig, needle, T_world_needle, arm.T_world_ecm(q), 0.12):
            return q
    return None


def multiview_joints(rng, arm, rig, needle, T_world_needle, q0, steps: int) -> list[np.ndarray]:
    """The paper's protocol: one random revolute joint moves +-0.05 rad per step; the sign that
    keeps the needle in view is preferred."""
    qs = [np.asarray(q0, float)]
    for _ in range(steps - 1):
        j = int(rng.choice(REVOLUTE_JOINTS))
        sign = rng.choice([-1.0, 1.0])
        q = qs[-1].copy()
        q[j] += sign * MULTIVIEW_STEP_RAD
        if not needle_in_view(rig, needle, T_world_needle, arm.T_world_ecm(q), 0.03):
            q2 = qs[-1].copy()
            q2[j] -= sign * MULTIVIEW_STEP_RAD
            if needle_in_view(rig, needle, T_world_needle, arm.T_world_ecm(q2), 0.03):
                q = q2
        qs.append(q)
    return qs


# ---------------------------------------------------------------- random scenes

_TISSUE_RGB = ((0.55, 0.16, 0.14), (0.38, 0.08, 0.07), (0.66, 0.30, 0.24), (0.60, 0.22, 0.26))
_THREAD_RGB = ((0.16, 0.04, 0.30), (0.03, 0.18, 0.07), (0.04, 0.06, 0.26), (0.02, 0.02, 0.02), (0.55, 0.50, 0.40))
_METAL_RGB = ((0.62, 0.62, 0.64), (0.66, 0.58, 0.45), (0.50, 0.53, 0.56), (0.22, 0.22, 0.24))


def sample_tissue(rng: np.random.Generator, centre_xy: np.ndarray) -> Tissue:
    waves = []
    for _ in range(4):
        lam = rng.uniform(0.03, 0.15)
        ang = rng.uniform(0, 2 * np.pi)
        k = 2 * np.pi / lam
        # gentle folds: amplitude 0.3-1.5% of the wavelength (0.1-2.3 mm)
        waves.append([lam * rng.uniform(0.003, 0.015), k * np.cos(ang), k * np.sin(ang), rng.uniform(0, 2 * np.pi)])
    base = np.asarray(_TISSUE_RGB[int(rng.integers(len(_TISSUE_RGB)))]) * rng.uniform(0.85, 1.15, 3)
    albedo, detail = make_tissue_textures(rng, np.clip(base, 0.02, 0.9))
    marks = []
    for _ in range(int(rng.integers(2, 4))):      # entry/exit marks around the needle
        a, r = rng.uniform(0, 2 * np.pi), rng.uniform(0.008, 0.03)
        ring = rng.random() < 0.4
        marks.append([centre_xy[0] + r * np.cos(a), centre_xy[1] + r * np.sin(a), rng.uniform(0.001, 0.0025),
                      rng.uniform(0.0005, 0.0009) if ring else 0.0])
    return Tissue(np.asarray(waves), albedo, 0.5, detail, rng.uniform(0.015, 0.03), np.asarray(marks),
                  ks=rng.uniform(0.1, 0.4), shininess=rng.uniform(15, 70))


def sample_needle_shape(rng: np.random.Generator) -> NeedleShape:
    n_ring = int(rng.choice([6, 7, 8, 10, 12]))
    tip = rng.uniform(0.0008, 0.0013) if rng.random() < 0.4 else rng.uniform(0.0023, 0.0036)
    return NeedleShape(wire_diameter_m=rng.uniform(0.0006, 0.001), flattening=rng.uniform(0.0, 0.25),
                       power=rng.uniform(2.0, 3.5), tip_length_m=tip, tip_exponent=rng.uniform(0.6, 1.0),
                       swage_scale=rng.uniform(1.1, 1.3), swage_length_m=rng.uniform(0.001, 0.0022),
                       tail=str(rng.choice(["dome", "chamfer"])), n_ring=n_ring,
                       n_arc=int(rng.integers(40, 111)), phase=rng.uniform(0, 2 * np.pi / n_ring))


def _align_z(n: np.ndarray) -> np.ndarray:
    """A rotation taking +z to the unit vector ``n``."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, n)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.eye(3) if n[2] > 0 else rotvec_to_R([np.pi, 0, 0])
    return rotvec_to_R(axis / s * np.arctan2(s, n @ z))


def sample_needle_pose(rng, tissue: Tissue, V_needle: np.ndarray, held: bool) -> np.ndarray:
    """T_world_needle: lying on the tissue (its mesh touching the surface) or, ``held``, at any
    orientation with its lowest point 3-25 mm above the surface."""
    xy = rng.uniform([-0.035, -0.03], [0.035, 0.03])
    if held:
        q = rng.standard_normal(4)
        R = quat_to_R(q / np.linalg.norm(q))             # uniform over rotations
    else:
        n = np.array(tissue.normal(np.float32(xy[0]), np.float32(xy[1])), float)
        flip = rotvec_to_R([np.pi, 0, 0]) if rng.random() < 0.5 else np.eye(3)
        R = _align_z(n) @ rotvec_to_R(np.append(rng.normal(0, 0.05, 2), rng.uniform(-np.pi, np.pi))) @ flip
    T = make_T(R, [xy[0], xy[1], 0.0])
    V = transform_points(T, V_needle)
    lift = float(np.max(tissue.height(V[:, 0].astype(np.float32), V[:, 1].astype(np.float32)) - V[:, 2]))
    T[2, 3] += lift + (rng.uniform(0.003, 0.025) if held else 0.0)
    return T


def sample_thread(rng, tissue: Tissue, needle: NeedleModel, T_world_needle, radius: float) -> np.ndarray:
    """A suture leaving the tail E along the arc's tangent, falling onto the tissue and
    meandering on it (world polyline, m)."""
    aE = needle.arc_span_rad[1]
    E = transform_points(T_world_needle, needle.arc_points([aE]))[0]
    d = T_world_needle[:3, :3] @ np.array([-np.sin(aE), np.cos(aE), 0.0])
    pts, p = [E], E.copy()
    step = 0.0008
    turn = rng.normal(0, 0.4, 2)
    for i in range(int(rng.uniform(0.03, 0.08) / step)):
        if i > 3:
            d = d + np.array([*(turn * 0.08 + rng.normal(0, 0.08, 2)), -0.12])
            d /= np.linalg.norm(d)
        p = p + step * d
        floor = float(tissue.height(np.float32(p[0]), np.float32(p[1]))) + radius
        if p[2] < floor:
            p[2] = floor
            d[2] = max(d[2], 0.0)
            d /= np.linalg.norm(d)
        pts.append(p.copy())
    P = np.asarray(pts)
    for _ in range(3):   # smooth, keeping the end at E
        P[1:-1] = 0.25 * P[:-2] + 0.5 * P[1:-1] + 0.25 * P[2:]
    return P


def _instrument_materials(rng):
    g = rng.uniform(0.02, 0.07)
    shaft = Material((g, g, g * rng.uniform(1.0, 1.4)), 1.0, rng.uniform(0.15, 0.4), rng.uniform(15, 40))
    m = rng.uniform(0.4, 0.6)
    metal = Material((m, m, m * 1.03), 0.5, 0.6, rng.uniform(25, 60), env=0.4)
    return shaft, metal


def sample_instruments(rng, tissue: Tissue, needle: NeedleModel, T_world_needle, V_needle_world,
                       held: bool, shape: NeedleShape) -> list:
    """0-2 instruments: one grasping the needle (when held), one beside it or across it."""
    meshes = []
    side = rng.choice([-1.0, 1.0])
    centre = transform_points(T_world_needle, needle.keypoints()).mean(axis=0)

    def trocar(sd):
        return np.array([sd * rng.uniform(0.10, 0.16), rng.uniform(-0.08, 0.05), rng.uniform(0.16, 0.22)])

    if held:
        a = np.deg2rad(rng.uniform(105, 140))
        g = transform_points(T_world_needle, needle.arc_points([a]))[0]
        tangent = T_world_needle[:3, :3] @ np.array([-np.sin(a), np.cos(a), 0.0])
        u = trocar(side) - g
        u /= np.linalg.norm(u)
        ish = InstrumentShape(shaft_radius_m=rng.uniform(0.0025, 0.004), jaw_length_m=rng.uniform(0.006, 0.01),
                              opening_rad=0.0, gap_m=shape.wire_diameter_m * shape.swage_scale)
        meshes += instrument_meshes(g - u * rng.uniform(0.001, 0.002), u, np.cross(u, tangent), ish,
                                    *_instrument_materials(rng))
    if rng.random() < 0.7:
        sd = -side
        top = float(V_needle_world[:, 2].max())
        if rng.random() < 0.3:     # jaws above part of the needle: a partial occlusion
            ang = rng.uniform(0, 2 * np.pi)
            off = rng.uniform(0.002, 0.007) * np.array([np.cos(ang), np.sin(ang)])
            tip = np.array([centre[0] + off[0], centre[1] + off[1], top + rng.uniform(0.003, 0.01)])
        else:                      # beside the needle, towards its trocar
            ang = np.arctan2(0.0, sd) + rng.uniform(-1.0, 1.0)
            off = rng.uniform(0.018, 0.04) * np.array([np.cos(ang), np.sin(ang)])
            xy = centre[:2] + off
            tip = np.array([xy[0], xy[1], float(tissue.height(np.float32(xy[0]), np.float32(xy[1])))
                            + rng.uniform(0.003, 0.02)])
        u = trocar(sd) - tip
        ish = InstrumentShape(shaft_radius_m=rng.uniform(0.0025, 0.004), jaw_length_m=rng.uniform(0.006, 0.01),
                              opening_rad=rng.uniform(0.0, 0.7))
        meshes += instrument_meshes(tip, u, rng.standard_normal(3), ish, *_instrument_materials(rng))
    return meshes


def sample_scene(rng: np.random.Generator, needle: NeedleModel, thread: bool = True) -> AltScene:
    """A random scene: tissue, needle (its own mesh and finish) at rest, thread, instruments,
    two lights on the scope tip, optics blur and sensor noise."""
    shape = sample_needle_shape(rng)
    mrgb = np.asarray(_METAL_RGB[int(rng.integers(len(_METAL_RGB)))])
    metal = Material(tuple(mrgb), rng.uniform(0.25, 0.5), rng.uniform(0.6, 1.0), rng.uniform(25, 120),
                     tuple(0.5 + 0.5 * mrgb / mrgb.max()), env=rng.uniform(0.3, 0.7))
    mesh0 = needle_mesh(needle, shape, metal)
    held = rng.random() < 0.3
    xy_guess = np.zeros(2)
    tissue = sample_tissue(rng, xy_guess)
    T = sample_needle_pose(rng, tissue, mesh0.V, held)
    centre = transform_points(T, needle.keypoints()).mean(axis=0)
    tissue.marks[:, :2] += centre[:2]                 # marks around where the needle lies
    needle_world = mesh0.transformed(T)
    meshes = [needle_world]
    if rng.random() < 0.85:
        r = rng.uniform(0.00012, 0.00022)
        th = _THREAD_RGB[int(rng.integers(len(_THREAD_RGB)))]
        tube = tube_mesh(sample_thread(rng, tissue, needle, T, r), r, 6, LABELS["thread"],
                         Material(th, 1.0, 0.12, 12.0))
        if thread:          # drawn or not, the same draws: a threadless twin of the scene
            meshes.append(tube)
    meshes += sample_instruments(rng, tissue, needle, T, needle_world.V, held, shape)
    a, b = rng.uniform(0.0015, 0.0035), rng.uniform(0.001, 0.003)
    tint = rng.normal(0, 0.03, 3)
    lights = [Light((a, b, 0.0), tuple(np.clip(1 + tint, 0.85, 1.0)), rng.uniform(0.4, 0.6)),
              Light((-a, -b, 0.0), tuple(np.clip(1 - tint, 0.85, 1.0)), rng.uniform(0.4, 0.6))]
    return AltScene(needle=needle, needle_shape=shape, T_world_needle=T, tissue=tissue, meshes=meshes,
                    lights=lights, spot_exponent=rng.uniform(1.0, 4.0), ambient=rng.uniform(0.02, 0.06),
                    exposure=rng.uniform(0.85, 1.3), env_low=tuple(np.asarray(tissue.albedo.mean(axis=(0, 1))) * 0.6),
                    blur_sigma_px=rng.uniform(0.3, 0.8), noise_sigma=rng.uniform(0.8, 2.5),
                    noise_seed=int(rng.integers(1 << 31)))


@dataclass
class AltSequencePlan:
    scene: AltScene
    joints: list


def plan_alt_sequence(seed: int, sequence: int, steps: int, rig: StereoRig, needle: NeedleModel,
                      arm: EcmArm, thread: bool = True) -> AltSequencePlan:
    """Deterministic plan of sequence ``sequence`` of a run seeded ``seed``."""
    rng = np.random.default_rng([seed, sequence, steps, 0xA17])
    for _ in range(50):
        scene = sample_scene(rng, needle, thread)
        q0 = sample_first_view(rng, arm, rig, needle, scene.T_world_needle)
        if q0 is not None:
            return AltSequencePlan(scene, multiview_joints(rng, arm, rig, needle, scene.T_world_needle, q0, steps))
    raise RuntimeError(f"alt render: could not place the needle in view for sequence {sequence}")


# ---------------------------------------------------------------- the folder

def alt_meta(width: int, height: int, source: str):
    """dataset.yaml contents: the spec's default stereo rig, needle model and this arm."""
    from common.data.dataset import DatasetMeta
    return DatasetMeta((width, height), StereoRig.default(width, height), NeedleModel(), alt_arm(), source)


def render_alt_sequence(renderer: AltRenderer, cfg: AltGenerateConfig, sequence: int):
    """Yield (images {camera: BGR}, frame fields) per step of sequence ``sequence``."""
    meta = alt_meta(cfg.width, cfg.height, "")
    plan = plan_alt_sequence(cfg.seed, sequence, cfg.steps, meta.rig, meta.needle, meta.arm, cfg.thread != "none")
    for step, q in enumerate(plan.joints):
        T_world_ecm = meta.arm.T_world_ecm(q)
        renders = renderer.render(plan.scene, T_world_ecm)
        gt = renderer.ground_truth(plan.scene, T_world_ecm, renders)
        yield ({c: r.bgr for c, r in renders.items()},
               {"sequence": sequence, "step": step, "ecm_joints": np.asarray(q, float), "T_world_ecm": T_world_ecm,
                "T_world_needle": plan.scene.T_world_needle, "keypoints": gt["keypoints"],
                "visible": gt["visible"], "bbox": gt["bbox"]})


def generate_alt(folder: str, cfg: AltGenerateConfig, progress: bool = True, overwrite: bool = False) -> int:
    """Generate (or resume, or extend) a folder; returns the number of frames in it."""
    from common.progress import progress_bar

    from common.data.dataset import Frame
    from common.data.writer import DatasetWriter, resume_generation
    if cfg.width < 16 or cfg.height < 16:
        raise ValueError(f"generate-alt: image size {cfg.width}x{cfg.height} is too small")
    resume, done = resume_generation(folder, GENERATE_FILE, cfg.stable(), cfg.sequences, cfg.steps,
                                     "dataset generate-alt", overwrite)
    source = (f"needletrack dataset generate-alt (common/sim/alt_render.py: numpy/OpenCV z-buffer rasteriser, "
              f"not MuJoCo; its own needle meshes, tissue, lights and ECM): seed={cfg.seed} steps={cfg.steps}")
    meta = alt_meta(cfg.width, cfg.height, source)
    writer = DatasetWriter(folder, meta, cfg.image_format, cfg.jpeg_quality, resume=resume)
    renderer = AltRenderer(meta.rig, cfg.supersample)
    bar = progress_bar(total=cfg.sequences * cfg.steps, initial=done * cfg.steps, unit="frame", desc="generate-alt",
               show=progress, smoothing=0.1)
    try:
        for s in range(done, cfg.sequences):
            for images, fields in render_alt_sequence(renderer, cfg, s):
                index = s * cfg.steps + fields["step"]
                paths = writer.write_images(index, images)
                writer.append(Frame(index=index, stamp_ns=int(round(index * 1e9 / FPS)), left=paths["left"],
                                    right=paths["right"], **fields))
                bar.update(1)
    finally:
        bar.close()
        writer.close()
    return writer.n_frames
