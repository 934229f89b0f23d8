"""Moving takes of the built-in scene: an instrument motion script (``common.sim.motion``) under
an endoscope that stays still or drifts, rendered frame by frame with its ground truth.

Take ``s`` of a run seeded ``seed`` depends only on (seed, s, motion, preset, image size), like a
multi-view sequence (``common.sim.randomise.plan_sequence``). Each frame's fields follow
``docs/dataset.md``: ``needle_at_rest: false``, ``instruments`` with ``holds_needle``, and
``visible``/``bbox`` from the render, so the jaws and the tissue hide what they cover. The jaws
are rendered where the script puts them; ``instruments`` reports them as the take's arms do
(``TakePlan.arm_errors``, ``common.sim.arm_error``: exact unless an arm error is asked for), with
the truth in ``T_world_jaw_truth`` / ``jaw_rad_truth`` where the report differs from it.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import EcmArm
from common.geometry.needle import NeedleModel
from common.geometry.transforms import transform_points
from common.sim.arm_error import ArmErrorConfig, draw_arm_errors, reported
from common.sim.motion import FPS, INSTRUMENTS, MOTIONS, ScriptedTake, script_take
from common.sim.random_looks import with_graspers
from common.sim.randomise import Preset, aim_joints, sample_appearance
from common.sim.scene import Instrument, SceneSpec

TAKE_MOTIONS = MOTIONS + ("mixed",)
"""``mixed``: take s plays ``MOTIONS[s % 4]``."""


def take_motion(motion: str, take: int) -> str:
    if motion not in TAKE_MOTIONS:
        raise ValueError(f"motion must be one of {TAKE_MOTIONS}, got {motion!r}")
    return MOTIONS[take % len(MOTIONS)] if motion == "mixed" else motion


@dataclass
class TakePlan:
    """A take: the scene (its first frame), the script and the endoscope joints per frame."""

    spec: SceneSpec
    script: ScriptedTake
    joints: list
    image_seed: int
    motion: str = ""                   # what it was planned for (``mixed`` plays the others)
    arm_errors: dict = field(default_factory=dict)   # name -> ArmError; empty: reported exactly

    def __len__(self) -> int:
        return len(self.script.frames)


def plan_take(seed: int, take: int, motion: str, preset: Preset, rig: StereoRig, needle: NeedleModel,
              arm: EcmArm, texture_size: int = 1024, msaa: int = 4, thread: bool = True,
              arm_error: ArmErrorConfig | None = None) -> TakePlan:
    """Deterministic plan of take ``take``; ``thread=False`` the same take with no thread drawn;
    ``arm_error``: how the arms report the jaws (None: exactly), drawn from its own seed, so the
    rendered take is the same whatever it is."""
    rng = np.random.default_rng([seed, take, 34])
    ap = sample_appearance(rng, preset)
    if preset.pool:                      # the random looks: both instruments can hold the needle
        ap = with_graspers(rng, ap, preset.pool, len(INSTRUMENTS))
    if not thread:
        ap = replace(ap, thread_visible=False)
    script = script_take(take_motion(motion, take), rng, needle, ap.wire_diameter_m / 2)
    # the endoscope looks at the middle of where the needle goes, 10-16 cm away
    path = np.array([transform_points(f.T_world_needle, needle.keypoints()).mean(axis=0) for f in script.frames])
    target = 0.5 * (path.min(axis=0) + path.max(axis=0))
    q0 = aim_joints(arm, target, rng.uniform(-preset.roll_range, preset.roll_range), rng.uniform(0.10, 0.16))
    n = len(script.frames)
    if rng.random() < 0.5:
        joints = [q0.copy() for _ in range(n)]                       # a still endoscope
    else:                                                            # a slow drift of yaw and pitch
        amp, period, phase = rng.uniform(0.01, 0.03, 2), rng.uniform(4.0, 8.0), rng.uniform(0, 2 * np.pi, 2)
        t = np.arange(n) / FPS
        joints = [q0 + np.array([amp[0] * np.sin(2 * np.pi * ti / period + phase[0]),
                                 amp[1] * np.sin(2 * np.pi * ti / period + phase[1]), 0.0, 0.0]) for ti in t]
    spec = SceneSpec(rig=rig, needle=needle, T_world_needle=script.frames[0].T_world_needle, appearance=ap,
                     instruments=_instruments(script.frames[0]), thread_seed=int(rng.integers(1 << 30)),
                     texture_size=texture_size, msaa=msaa)
    first = {name: T for name, (T, _, _) in script.frames[0].instruments.items()}
    return TakePlan(spec, script, joints, int(rng.integers(1 << 30)), motion,
                    draw_arm_errors(arm_error, (seed, take), first))


def _instruments(frame) -> list:
    """The scene's instruments of a script frame, in the order of ``common.sim.motion.INSTRUMENTS``."""
    return [Instrument.from_jaw(T, jaw) for T, jaw, _ in frame.instruments.values()]


def frame_instruments(frame, arm_errors: dict | None = None, step: int = 0) -> dict:
    """The ``instruments`` field of script frame ``step``: name -> ``InstrumentPose``, as the arms
    of ``arm_errors`` (name -> ``ArmError``) report them (the others: exactly)."""
    return {name: reported(arm_errors or {}, name, T, jaw, bool(holds), step)
            for name, (T, jaw, holds) in frame.instruments.items()}


def scene_instruments(instruments: list, arm_errors: dict | None = None, step: int = 0) -> dict:
    """The instruments of a scene at rest (``SceneSpec.instruments``), named in order, as the arms
    of ``arm_errors`` report them in frame ``step``; whether one holds the needle is not stated."""
    return {name: reported(arm_errors or {}, name, ins.T_world_jaw, float(ins.jaw_open), None, step)
            for name, ins in zip(INSTRUMENTS, instruments)}


def take_spec(plan: TakePlan, frame) -> SceneSpec:
    """The scene of one frame of a take."""
    return replace(plan.spec, T_world_needle=frame.T_world_needle, instruments=_instruments(frame))


def render_take(renderer, plan: TakePlan, arm: EcmArm, degrade=None, every: int = 1):
    """Render a take: yields (BGR images by camera, frame fields) per frame, or per ``every``-th
    frame (``step`` stays the frame's index in the 30 Hz take); ``degrade`` (images, keypoints by
    camera -> images) applies the sensor model."""
    for step, (fr, q) in enumerate(zip(plan.script.frames, plan.joints)):
        if step % every:
            continue
        renderer.load(take_spec(plan, fr))
        T_world_ecm = arm.T_world_ecm(q)
        renders = renderer.render(T_world_ecm)
        gt = renderer.ground_truth(T_world_ecm, renders)
        images = {c: r.bgr for c, r in renders.items()}
        if degrade is not None:
            images = degrade(images, gt["keypoints"])
        yield images, {"step": step, "ecm_joints": np.asarray(q, float), "T_world_ecm": T_world_ecm,
                       "T_world_needle": fr.T_world_needle, "keypoints": gt["keypoints"], "visible": gt["visible"],
                       "bbox": gt["bbox"], "arc_visible": gt["arc_visible"], "arc_seen": gt["arc_seen"], "needle_at_rest": False,
                       "instruments": frame_instruments(fr, plan.arm_errors, step)}
