"""Monitor: prints the live graph's needle pose, one line per frame or per interval.

A line shows the final method's pose (the first wired of ``FINAL_ORDER``: the dense refinement
when the graph has it): the position of the needle's origin in the ECM frame (mm), its rotation
vector (deg) and, when the truth is known, its error (position mm / orientation deg); a pose the
images could not decide is marked ``ambiguous``, or ``tip 0.62`` when what they could not tell is
which end is the tip (the probability the pose states for it). A line fits ``WIDTH`` (120) columns::

    seq   412 5/5 refined  t=[3.1 -7.9 -152.0]mm r=[171.2 12.0 -3.3]deg err 0.18mm 0.5deg

``5/5``: how many of the wired methods posed the frame. With ``all_methods`` each other wired method follows on a line of its own, indented.
Params: ``every_s`` (1.0; 0 prints every frame), ``methods`` (which wired inputs to count and
show, in order; default all wired), ``all_methods`` (false).
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import numpy as np

from common.data.truth import true_T_ecm_needle
from common.geometry.end_identity import TIP_SURE
from common.geometry.ecm_kinematics import EcmArm
from common.geometry.transforms import R_to_rotvec, pose_error
from common.methods import POSE_METHODS, final_method
from common.runtime.messages import Calibration, GroundTruth, PoseEstimate
from common.runtime.node import Node, run
from common.runtime.pairing import SeqCache
from nodes._pose import PoseMethodInputs

WIDTH = 120
KEEP_FRAMES = 64


def format_pose(T: np.ndarray) -> str:
    """``t=[x y z]mm r=[rx ry rz]deg``: origin (mm) and rotation vector (deg) of a pose."""
    t = T[:3, 3] * 1e3
    r = np.degrees(R_to_rotvec(T[:3, :3]))
    return f"t=[{t[0]:.1f} {t[1]:.1f} {t[2]:.1f}]mm r=[{r[0]:.1f} {r[1]:.1f} {r[2]:.1f}]deg"


def format_method(method: str, pose, T_true) -> str:
    """``method t=[..]mm r=[..]deg  err Xmm Ydeg`` (``no pose`` when ``pose`` is None)."""
    if pose is None:
        return f"{method:<8} no pose"
    s = f"{method:<8} {format_pose(pose.T_ecm_needle)}"
    if T_true is not None:
        dp, dr = pose_error(pose.T_ecm_needle, T_true)
        s += f" err {dp * 1e3:.2f}mm {np.degrees(dr):.1f}deg"
    if pose.ambiguous:   # "tip 0.62": the tip the images could not tell, with its stated probability
        p = pose.end_identity
        s += f" tip {p:.2f}" if p is not None and p < TIP_SURE else " ambiguous"
    if pose.n_views > 1:
        s += f" views {pose.n_views}"
    return s


def format_lines(seq: int, poses: dict, T_true, methods, all_methods: bool = False) -> list[str]:
    """The monitor's lines for frame ``seq``: ``poses`` method -> PoseEstimate (missing: no pose)."""
    final = final_method(methods)
    posed = sum(1 for m in methods if poses.get(m) is not None)
    lines = [f"seq {seq:5d} {posed}/{len(methods)} {format_method(final, poses.get(final), T_true)}"]
    if all_methods:
        lines += [f"{'':4}{format_method(m, poses.get(m), T_true)}" for m in methods if m != final]
    return [line if len(line) <= WIDTH else line[:WIDTH - 3] + "..." for line in lines]


class MonitorNode(PoseMethodInputs, Node):
    """Prints each method's pose (and its error when the truth is known) for the newest frame."""

    INPUTS = {"truth": GroundTruth, "calib": Calibration, **{m: PoseEstimate for m in POSE_METHODS}}
    OUTPUTS = ()
    KEEP_ALL = tuple(INPUTS)

    @dataclass
    class Params:
        every_s: float = 1.0
        methods: list[str] | None = None     # counted and shown methods (default: all wired)
        all_methods: bool = False            # a line for each method, not only the final one

    def setup(self):
        self.every_s = self.p.every_s
        wanted = self.p.methods or POSE_METHODS
        self.methods = [m for m in wanted if m in POSE_METHODS and self.wired(m)]
        self.frames = SeqCache(KEEP_FRAMES)     # seq -> {method: PoseEstimate}
        self.truths = SeqCache(KEEP_FRAMES)     # seq -> GroundTruth
        self.arm = None
        self._last_print = 0.0
        self._printed = -1
        self.out = sys.stdout

    def on_stream_reset(self):
        self.frames.clear()
        self.truths.clear()
        self._printed = -1

    def on_calib(self, msg):
        self.arm = EcmArm.from_calibration(msg.ecm)

    def on_truth(self, msg):
        self.truths.put(msg.seq, msg)

    def on_pose(self, method, msg):
        self.frames.put(msg.seq, {**self.frames.get(msg.seq, {}), method: msg})
        self._maybe_print()

    def _maybe_print(self):
        now = time.monotonic()
        if now - self._last_print < self.every_s or not self.frames:
            return
        # a frame is ready when every wired method answered, or when frames 3 newer exist
        # (then the missing methods gave no pose for it)
        newest = max(self.frames)
        ready = [s for s, d in self.frames.items()
                 if s > self._printed and (len(d) == len(self.methods) or s <= newest - 3)]
        if not ready:
            return
        seq = max(ready)
        gt = self.truths.get(seq)
        T_true = true_T_ecm_needle(gt, self.arm) if gt is not None else None
        for line in format_lines(seq, self.frames[seq], T_true, self.methods, self.p.all_methods):
            print(line, file=self.out)
        self.out.flush()
        self._last_print, self._printed = now, seq
        self.count("lines")


NODE = MonitorNode
if __name__ == "__main__":
    run(NODE)
