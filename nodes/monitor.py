"""Monitor: prints the live graph's needle poses, one line per frame or per interval.

Each line: the frame ``seq`` and, per wired pose method, the position of the needle's origin in
the ECM frame (mm) and its rotation vector (deg); when the truth is wired and known, each
method's error against it (position mm / orientation deg), e.g.::

    seq   412 | pnp_joint t=[3.1 -7.9 -152.0]mm r=[171.2 12.0 -3.3]deg err 0.84mm 1.9deg | ...

Params: ``every_s`` (default 1.0; 0 prints every frame), ``methods`` (list: which wired inputs to
print, in order; default all wired).
"""
from __future__ import annotations

import sys
import time
from collections import OrderedDict

import numpy as np

from common.evaluation import EXTRA_METHODS, METHODS, true_T_ecm_needle
from common.messages import Calibration, GroundTruth, PoseEstimate
from common.node import Node, run
from common.pose_node import PoseMethodInputs
from common.transforms import R_to_rotvec, pose_error

POSE_INPUTS = METHODS + EXTRA_METHODS
KEEP_FRAMES = 64


def format_pose(T: np.ndarray) -> str:
    """``t=[x y z]mm r=[rx ry rz]deg``: origin (mm) and rotation vector (deg) of a pose."""
    t = T[:3, 3] * 1e3
    r = np.degrees(R_to_rotvec(T[:3, :3]))
    return f"t=[{t[0]:.1f} {t[1]:.1f} {t[2]:.1f}]mm r=[{r[0]:.1f} {r[1]:.1f} {r[2]:.1f}]deg"


def format_line(seq: int, poses: dict, T_true, methods) -> str:
    """One monitor line for frame ``seq``: ``poses`` method -> PoseEstimate (missing: no pose)."""
    parts = [f"seq {seq:5d}"]
    for m in methods:
        p = poses.get(m)
        if p is None:
            parts.append(f"{m} no pose")
            continue
        s = f"{m} {format_pose(p.T_ecm_needle)}"
        if p.n_views > 1:
            s += f" views {p.n_views}"
        if T_true is not None:
            dp, dr = pose_error(p.T_ecm_needle, T_true)
            s += f" err {dp * 1e3:.2f}mm {np.degrees(dr):.1f}deg"
        parts.append(s)
    return " | ".join(parts)


class MonitorNode(PoseMethodInputs, Node):
    """Prints each method's pose (and its error when the truth is known) for the newest frame."""

    INPUTS = {"truth": GroundTruth, "calib": Calibration,
              "pnp_average": PoseEstimate, "pnp_joint": PoseEstimate,
              "triangulation": PoseEstimate, "multiview": PoseEstimate,
              "refined": PoseEstimate, "multiview_refined": PoseEstimate}
    OUTPUTS = ()
    KEEP_ALL = tuple(INPUTS)

    def setup(self):
        self.every_s = float(self.params.get("every_s", 1.0))
        wanted = self.params.get("methods") or POSE_INPUTS
        self.methods = [m for m in wanted if m in POSE_INPUTS and self.wired(m)]
        self.frames: OrderedDict = OrderedDict()     # seq -> {method: PoseEstimate}
        self.truths: OrderedDict = OrderedDict()     # seq -> GroundTruth
        self.arm = None
        self._last_print = 0.0
        self._printed = -1
        self.out = sys.stdout

    def on_calib(self, msg):
        self.arm = msg.arm()

    def on_truth(self, msg):
        self.truths[msg.seq] = msg
        while len(self.truths) > KEEP_FRAMES:
            self.truths.popitem(last=False)

    def on_pose(self, method, msg):
        self.frames.setdefault(msg.seq, {})[method] = msg
        while len(self.frames) > KEEP_FRAMES:
            self.frames.popitem(last=False)
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
        print(format_line(seq, self.frames[seq], T_true, self.methods), file=self.out, flush=True)
        self._last_print, self._printed = now, seq
        self.count("lines")


NODE = MonitorNode
if __name__ == "__main__":
    run(NODE)
