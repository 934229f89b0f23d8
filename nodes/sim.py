"""``sim``: the built-in MuJoCo suturing scene as a live stereo camera source.

Outputs: ``left``/``right`` (``CameraImage``, sharing ``seq``), ``joints`` (``EcmJoints``),
``truth`` (``GroundTruth``: poses, keypoints, visibility, boxes; ``sequence``/``step`` of the
multi-view protocol; ``needle_at_rest`` false in a take whose needle moves), ``instruments``
(``InstrumentState``, one per instrument and frame: ``psm1``, ``psm2``, their jaw frames,
openings and, in a take of an instrument motion, ``holds_needle``), ``calib`` (``Calibration``:
before the first frame, then once a second).
``stamp_ns`` is the wall-clock time of the frame.

params: ``width``/``height`` (1920x1080), ``rate_hz`` (30; a maximum: rendering 1080p on the CPU
is slower; 0 = as fast as possible), ``randomise`` (none|test|train, default test), ``seed`` (0),
``motion`` (static|multiview|sweep: the endoscope moves, the needle rests; pickup|handover|throw|suture:
the instruments move the needle, one take after another, docs/datasets.md; default sweep),
``steps`` (5) and ``hold_frames`` (15) of the
multi-view protocol, ``sweep_period_s`` (8), ``sweep_amplitude_rad`` (0.06), ``msaa`` (anti-aliasing
samples, 4; 0 renders ~2.5x faster), ``arm_error`` (how the arms report the jaws: ``exact``, default,
or ``dvrk``, a few mm and degrees of error, with optional overrides: ``common.sim.arm_error``,
docs/datasets.md; the truth travels in ``T_world_jaw_truth`` / ``jaw_rad_truth``), ``encoding``
(jpeg|png|bgr8, default jpeg), ``jpeg_quality`` (95), ``count`` (stop after this many frames;
0 = never).

Commands: ``place_needle`` (args: optional ``seed`` int, or ``T_world_needle`` 4x4: that needle
stays at rest, whatever the motion, until the next ``place_needle`` without one), ``set_motion``
(args: ``motion``).
"""
import time
from dataclasses import dataclass
from typing import Literal

import numpy as np

from common.frames import CAMERAS
from common.runtime.camera_source import CameraSourceNode
from common.runtime.messages import (
    Calibration,
    CameraImage,
    Command,
    EcmJoints,
    GroundTruth,
    InstrumentState,
    rigid_error,
)
from common.runtime.node import NodeError, run
from common.runtime.pacing import Pacer


class SimNode(CameraSourceNode):
    """Live simulator source."""

    OUTPUTS = ("left", "right", "joints", "truth", "instruments", "calib")

    @dataclass
    class Params:
        width: int = 1920
        height: int = 1080
        rate_hz: float = 30.0                 # a maximum; 0: as fast as it renders
        encoding: Literal["jpeg", "png", "bgr8"] = "jpeg"
        jpeg_quality: int = 95
        count: int = 0                        # 0: forever
        randomise: str = "test"
        seed: int = 0
        motion: str = "sweep"
        steps: int = 5
        hold_frames: int = 15
        sweep_period_s: float = 8.0
        sweep_amplitude_rad: float = 0.06
        msaa: int = 4
        arm_error: str = "exact"

    def setup(self):
        import common.sim.render  # noqa: F401  (headless GL before mujoco)
        from common.sim.live import LiveSim
        p = self.p
        rate = p.rate_hz
        self.encoding = p.encoding
        self.jpeg_quality = p.jpeg_quality
        self.count_max = p.count
        try:
            self.sim = LiveSim(width=p.width, height=p.height, randomise=p.randomise, seed=p.seed,
                               motion=p.motion, steps=p.steps, hold_frames=p.hold_frames,
                               sweep_period_s=p.sweep_period_s, sweep_amplitude_rad=p.sweep_amplitude_rad,
                               rate_hz=rate, msaa=p.msaa, arm_error=p.arm_error)
        except (KeyError, ValueError) as exc:
            raise NodeError(f"bad simulator params: {exc}") from None
        self.sim.warm_up()        # a (re)started camera's first frame then comes at its usual pace
        self.seq = 0
        self.pacer = Pacer(rate)
        self.last_calib = None
        self.calib = Calibration(stamp_ns=0, image_size=np.array([self.sim.rig.left.width, self.sim.rig.left.height]),
                                 cameras=self.sim.rig.to_dict(), needle=self.sim.needle.to_dict(),
                                 ecm=self.sim.arm.to_dict(), source="needletrack sim (MuJoCo built-in scene)")

    def step(self):
        if self.count_max and self.seq >= self.count_max:
            return False
        if self.seq == 0:
            self._publish_calib(force=True)
        self.pacer.wait()
        fr = self.sim.next_frame()
        stamp = time.time_ns()
        for cam in CAMERAS:
            self.publish(cam, CameraImage.from_bgr(cam, self.seq, stamp, fr.images[cam], self.encoding,
                                                   self.jpeg_quality))
        self.publish("joints", EcmJoints(self.seq, stamp, np.asarray(fr.q, float)))
        self.publish("truth", GroundTruth.from_frame(fr, self.seq, stamp))
        for name, pose in (fr.instruments or {}).items():
            self.publish("instruments", InstrumentState.from_pose(name, pose, self.seq, stamp))
        self.seq += 1
        self._publish_calib()
        return True

    def on_command(self, msg: Command):
        args = msg.args or {}
        if msg.name == "place_needle":
            T, seed = args.get("T_world_needle"), args.get("seed")
            err = None if T is None else rigid_error(_as_float(T), "place_needle.T_world_needle")
            if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2 ** 32):
                err = f"place_needle.seed: expected an int in 0..2^32-1, got {seed!r}"[:200]
            if err:
                self.count("bad_commands")
                self.log.warning("sim: command refused: %s", err)
                return
            self.sim.place_needle(seed=seed, T_world_needle=None if T is None else np.asarray(T, float))
            self.count("needle_placed")
        elif msg.name == "set_motion":
            from common.sim.live import MOTIONS
            motion = args.get("motion")
            if not isinstance(motion, str) or motion not in MOTIONS:
                self.count("bad_commands")
                self.log.warning("sim: command refused: set_motion: motion must be one of %s, got %r",
                                 MOTIONS, motion)
                return
            self.sim.motion = motion
        else:
            self.count("commands_ignored")
            self.log.warning("sim: unknown command %r", msg.name)

    def teardown(self):
        if hasattr(self, "sim"):
            self.sim.close()


def _as_float(v):
    try:
        return np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        return np.full(1, np.nan)


NODE = SimNode
if __name__ == "__main__":
    run(NODE)
