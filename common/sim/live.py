"""The live simulator behind the ``sim`` node: scene, endoscope motion scripts and frames.

Motion scripts (``MOTIONS``):
- ``static``: the endoscope stays where it was placed;
- ``multiview``: the paper's protocol: ``steps`` endoscope poses per needle pose, one random
  revolute ECM joint moving 0.05 rad between poses, each held ``hold_frames`` frames; then a new
  needle pose (a new ``sequence``);
- ``sweep``: smooth yaw/pitch oscillation of ``sweep_amplitude_rad`` over ``sweep_period_s``;
- ``pickup``, ``handover``, ``throw``, ``suture``: the instruments move the needle
  (``common.sim.motion``), one take after another, each a new ``sequence`` with
  ``needle_at_rest`` false (``common.sim.takes``).

Every frame carries the instruments (``SimFrame.instruments``: name -> ``InstrumentPose``), as
their arms report them (``arm_error``: ``common.sim.arm_error``, exact by default; the jaws are
rendered where they truly are, the truth in ``T_world_jaw_truth`` / ``jaw_rad_truth``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import transform_points
from common.sim.arm_error import arm_error_config, draw_arm_errors
from common.sim.motion import INSTRUMENTS
from common.sim.motion import MOTIONS as INSTRUMENT_MOTIONS
from common.sim.randomise import (
    aim_joints,
    default_arm,
    degrade_stereo,
    get_preset,
    noise_bank,
    keypoints_in_view,
    multiview_joints,
    plan_sequence,
)
from common.sim.render import SceneRenderer

MOTIONS = ("static", "multiview", "sweep") + INSTRUMENT_MOTIONS


@dataclass
class SimFrame:
    """One stereo frame: BGR images by camera, ECM joints, T_world_ecm and ground truth."""

    images: dict
    q: np.ndarray
    T_world_ecm: np.ndarray
    T_world_needle: np.ndarray
    truth: dict            # keypoints / visible / bbox by camera
    sequence: int
    step: int
    instruments: dict | None = None    # name -> common.data.instruments.InstrumentPose
    needle_at_rest: bool | None = None

    @property
    def ecm_joints(self) -> np.ndarray:
        return self.q

    @property
    def keypoints(self) -> dict:
        return self.truth["keypoints"]

    @property
    def visible(self) -> dict:
        return self.truth["visible"]

    @property
    def bbox(self) -> dict:
        return self.truth["bbox"]


class LiveSim:
    """Renders an endless stream of frames of the built-in scene under a motion script."""

    def __init__(self, width: int = 1920, height: int = 1080, randomise: str = "test", seed: int = 0,
                 motion: str = "sweep", steps: int = 5, hold_frames: int = 15, sweep_period_s: float = 8.0,
                 sweep_amplitude_rad: float = 0.06, rate_hz: float = 30.0, texture_size: int = 1024,
                 msaa: int = 4, arm_error: str = "exact"):
        if motion not in MOTIONS:
            raise ValueError(f"sim: motion must be one of {MOTIONS}, got {motion!r}")
        self.arm_error = arm_error_config(arm_error)
        self.rig = StereoRig.default(width, height)
        self.needle = NeedleModel()
        self.arm = default_arm()
        self.preset = get_preset(randomise)
        self.seed, self.motion, self.steps = int(seed), motion, max(1, int(steps))
        self.hold_frames = max(1, int(hold_frames))
        self.sweep_period_s, self.sweep_amplitude = float(sweep_period_s), float(sweep_amplitude_rad)
        self.dt = 1.0 / rate_hz if rate_hz > 0 else 1.0 / 30.0
        self.texture_size, self.msaa = texture_size, int(msaa)
        self.renderer = SceneRenderer()
        self.sequence = -1
        self.frame_in_sequence = 0
        self._rng = np.random.default_rng([self.seed, 7])
        self.take = None
        self.pinned = False                 # a needle placed by pose: at rest until the next place_needle
        self.place_needle()
        if self.preset.noise_sigma[1] > 0:          # the first frame would make it: here, at set-up
            noise_bank((height, width, 3))

    def place_needle(self, seed: int | None = None, T_world_needle=None) -> None:
        """A new needle pose (and scene look): the next planned one, the one planned for ``seed``,
        or exactly ``T_world_needle`` (4x4, world) with the endoscope aimed at it."""
        self.sequence += 1
        key = self.sequence if seed is None else int(seed)
        self.pinned = T_world_needle is not None
        if self.motion in INSTRUMENT_MOTIONS and T_world_needle is None:
            self._start_take(key)
            return
        self.take = None
        plan = plan_sequence(self.seed, key, self.steps, self.preset, self.rig, self.needle, self.arm,
                             self.texture_size, self.msaa)
        if T_world_needle is not None:
            T = np.asarray(T_world_needle, dtype=float)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise ValueError("place_needle: T_world_needle must be a finite 4x4 matrix")
            plan.spec.T_world_needle = T
            plan.spec.instruments = []
            centre = transform_points(T, self.needle.keypoints()).mean(axis=0)
            q0 = aim_joints(self.arm, centre, 0.0, 0.15)
            plan.joints = multiview_joints(np.random.default_rng(key), self.arm, self.rig, self.needle, T,
                                           q0, self.steps)
        self.renderer.load(plan.spec)
        self.plan = plan
        self.arm_errors = draw_arm_errors(self.arm_error, (self.seed, key),
                                          {n: ins.T_world_jaw for n, ins in zip(INSTRUMENTS, plan.spec.instruments)})
        self.frame_in_sequence = 0
        self._img_rng = np.random.default_rng(plan.image_seed)

    def _start_take(self, key: int) -> None:
        from common.sim.takes import plan_take
        self.take = plan_take(self.seed, key, self.motion, self.preset, self.rig, self.needle, self.arm,
                              self.texture_size, self.msaa, arm_error=self.arm_error)
        self.plan = self.take
        self.renderer.load(self.take.spec)
        self.frame_in_sequence = 0
        self._img_rng = np.random.default_rng(self.take.image_seed)

    def joints(self) -> tuple[np.ndarray, int]:
        """Joints of the current frame under the motion script, and the multiview step."""
        if self.take is not None:
            k = min(self.frame_in_sequence, len(self.take) - 1)
            return self.take.joints[k].copy(), k
        q0 = self.plan.joints[0]
        if self.motion == "static":
            return q0.copy(), 0
        if self.motion == "multiview":
            step = min(self.frame_in_sequence // self.hold_frames, len(self.plan.joints) - 1)
            return self.plan.joints[step].copy(), step
        t = self.frame_in_sequence * self.dt
        w = 2 * np.pi / self.sweep_period_s
        q = q0.copy()
        q[0] += self.sweep_amplitude * np.sin(w * t)
        q[1] += 0.6 * self.sweep_amplitude * np.sin(2 * w * t)
        return q, 0

    def next_frame(self) -> SimFrame:
        """Render the next frame and advance the script."""
        if self.motion == "multiview" and self.frame_in_sequence >= self.hold_frames * self.steps:
            self.place_needle()
        if (self.motion in INSTRUMENT_MOTIONS and not self.pinned) != (self.take is not None) or (
                self.take is not None and (self.frame_in_sequence >= len(self.take) or self.take.motion != self.motion)):
            self.place_needle()                     # the next take (or back to a needle at rest)
        q, step = self.joints()
        T_world_ecm = self.arm.T_world_ecm(q)
        if self.take is not None:
            from common.sim.takes import frame_instruments, take_spec
            sf = self.take.script.frames[step]
            self.renderer.load(take_spec(self.take, sf))
            T_world_needle, at_rest = sf.T_world_needle.copy(), False
            instruments = frame_instruments(sf, self.take.arm_errors, step)
        else:
            from common.sim.takes import scene_instruments
            T_world_needle, at_rest = self.plan.spec.T_world_needle.copy(), None
            instruments = scene_instruments(self.plan.spec.instruments, self.arm_errors, self.frame_in_sequence)
        renders = self.renderer.render(T_world_ecm)
        truth = self.renderer.ground_truth(T_world_ecm, renders)
        images = degrade_stereo({c: r.bgr for c, r in renders.items()}, self._img_rng, self.preset,
                                avoid=truth["keypoints"])
        self.frame_in_sequence += 1
        return SimFrame(images, q, T_world_ecm, T_world_needle, truth, self.sequence, step, instruments, at_rest)

    def warm_up(self) -> None:
        """Render the current pose once and discard it (the GL pipeline's first use costs 3-4
        frames on a CPU renderer); the script does not advance, so the frames are unchanged."""
        q, _ = self.joints()
        self.renderer.render(self.arm.T_world_ecm(q))

    def needle_in_view(self) -> bool:
        q, step = self.joints()
        T = (self.take.script.frames[step].T_world_needle if self.take is not None else self.plan.spec.T_world_needle)
        return keypoints_in_view(self.rig, self.needle, T, self.arm.T_world_ecm(q))

    def close(self) -> None:
        self.renderer.close()
