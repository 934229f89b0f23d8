"""Instrument motion scripts of the built-in scene: the needle picked up, handed over and driven
through the tissue by two patient-side instruments, ``psm1`` (from the left) and ``psm2`` (from
the right), at ``FPS`` frames a second.

Scripts (``MOTIONS``):
- ``pickup``: psm1 approaches the needle at rest on the pad with its jaws open, closes them on the
  needle's body, lifts it off the pad and carries it across the view;
- ``handover``: psm1 holds the needle in the air; psm2 approaches, closes on it, psm1 lets go
  and backs off, psm2 carries it;
- ``throw``: the holder brings the needle above the pad, its plane upright, and turns it about the
  arc's axis: the tip enters the tissue, travels hidden and comes out at the exit, while the jaws
  hold the tail third; then the jaws let go and back off;
- ``suture``: pickup (at the middle of the arc), handover to psm2 (at the tail third), throw.

Every move is a minimum-jerk segment in position and rotation (``minimum_jerk``) timed so that
the peak speeds stay under the take's limits (drawn up to ``MAX_SPEED_M_S`` and
``MAX_TURN_RAD_S``). While an instrument holds the needle, ``T_world_needle = T_world_jaw @
T_jaw_needle`` exactly (a rigid grasp, ``grasp_pose``): grasp points vary along the arc (the
middle, the tail third) and so does the needle's angle in the jaws. The jaw frame is that of
``docs/dataset.md`` (``common.sim.scene.T_BODY_JAW``). All lengths in metres.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from common.geometry.needle import NeedleModel
from common.geometry.transforms import R_to_rotvec, inv_T, make_T, rotation_angle, rotvec_to_R, transform_points
from common.sim.randomise import rest_height
from common.sim.scene_meshes import phantom_height

MOTIONS = ("pickup", "handover", "throw", "suture")
FPS = 30.0
INSTRUMENTS = ("psm1", "psm2")
SIDES = {"psm1": -1.0, "psm2": 1.0}              # world x side of each instrument's trocar
MAX_SPEED_M_S = 0.020
MAX_TURN_RAD_S = np.deg2rad(90.0)
JAW_OPEN_RAD = 0.9                               # open to take or let go of the needle
JAW_CLOSED_RAD = 0.06                            # closed on the wire
JAW_SPEED_RAD_S = 2.5
PEAK = 1.875                                     # peak / mean speed of a minimum-jerk move


def minimum_jerk(tau):
    """The minimum-jerk profile s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5 on [0, 1]."""
    tau = np.clip(tau, 0.0, 1.0)
    return tau ** 3 * (10 - 15 * tau + 6 * tau * tau)


def interpolate_pose(T0: np.ndarray, T1: np.ndarray, s: float) -> np.ndarray:
    """The pose a fraction ``s`` of the way from T0 to T1 (straight line, geodesic rotation)."""
    R = T0[:3, :3] @ rotvec_to_R(s * R_to_rotvec(T0[:3, :3].T @ T1[:3, :3]))
    return make_T(R, (1 - s) * T0[:3, 3] + s * T1[:3, 3])


def grasp_pose(needle: NeedleModel, angle_rad: float, depth_m: float, wire_rad: float,
               plane_rad: float) -> np.ndarray:
    """``T_jaw_needle`` of jaws closed on the arc at ``angle_rad`` (needle frame), that point
    ``depth_m`` from the pivot along the jaws' z. The wire crosses the jaw faces (their y-z plane)
    at ``wire_rad`` from y; the needle's plane is turned ``plane_rad`` about the wire from the
    jaws' x-y plane (0, 0: the needle square to the jaws)."""
    c, s = np.cos(wire_rad), np.sin(wire_rad)
    t_j = np.array([0.0, c, s])                      # the wire's tangent in the jaw frame
    w_j = np.cos(plane_rad) * np.array([1.0, 0, 0]) + np.sin(plane_rad) * np.array([0.0, s, -c])
    u = np.array([np.cos(angle_rad), np.sin(angle_rad), 0.0])
    t = np.array([-np.sin(angle_rad), np.cos(angle_rad), 0.0])
    R = np.stack([w_j, t_j, np.cross(w_j, t_j)], 1) @ np.stack([u, t, [0.0, 0, 1]], 1).T
    return make_T(R, np.array([0.0, 0.0, depth_m]) - needle.radius_m * w_j)


@dataclass
class TakeFrame:
    """The truth of one frame of a take: the needle, and per instrument (jaw pose, opening,
    holds the needle)."""

    T_world_needle: np.ndarray
    instruments: dict                                # name -> (T_world_jaw, jaw_rad, holds)


@dataclass
class Take:
    """A take being scripted: the current state and the frames so far (``record`` appends one)."""

    T_world_needle: np.ndarray
    jaws: dict                                       # name -> T_world_jaw
    jaw_rad: dict
    speed_m_s: float = MAX_SPEED_M_S
    turn_rad_s: float = MAX_TURN_RAD_S
    grasps: dict = field(default_factory=dict)       # name -> T_jaw_needle while it holds
    frames: list = field(default_factory=list)

    def record(self) -> None:
        self.frames.append(TakeFrame(self.T_world_needle.copy(), {
            n: (self.jaws[n].copy(), float(self.jaw_rad[n]), n in self.grasps) for n in self.jaws}))

    def _follow(self) -> None:
        if self.grasps:
            name = sorted(self.grasps)[0]
            self.T_world_needle = self.jaws[name] @ self.grasps[name]

    def duration(self, targets: dict) -> float:
        """Seconds a move to ``targets`` (name -> (T_world_jaw or None, jaw_rad or None)) takes."""
        t = 0.0
        for name, (T, jaw) in targets.items():
            if T is not None:
                T0 = self.jaws[name]
                t = max(t, PEAK * np.linalg.norm(T[:3, 3] - T0[:3, 3]) / self.speed_m_s,
                        PEAK * rotation_angle(T0[:3, :3].T @ T[:3, :3]) / self.turn_rad_s)
            if jaw is not None:
                t = max(t, PEAK * abs(jaw - self.jaw_rad[name]) / JAW_SPEED_RAD_S)
        return t

    def move(self, targets: dict, min_s: float = 0.2) -> None:
        """Move instruments to ``targets`` together (the needle follows its holder)."""
        n = max(1, int(np.ceil(max(self.duration(targets), min_s) * FPS)))
        start = {name: (self.jaws[name], self.jaw_rad[name]) for name in targets}
        for k in range(1, n + 1):
            s = float(minimum_jerk(k / n))
            for name, (T, jaw) in targets.items():
                T0, j0 = start[name]
                if T is not None:
                    self.jaws[name] = interpolate_pose(T0, T, s)
                if jaw is not None:
                    self.jaw_rad[name] = j0 + s * (jaw - j0)
            self._follow()
            self.record()

    def hold(self, seconds: float) -> None:
        for _ in range(int(round(seconds * FPS))):
            self.record()

    def grasp(self, name: str) -> None:
        """``name``'s jaws close on the needle: from the next frame on it moves with them."""
        self.move({name: (None, JAW_CLOSED_RAD)})
        self.grasps[name] = inv_T(self.jaws[name]) @ self.T_world_needle

    def release(self, name: str) -> None:
        self.grasps.pop(name, None)
        self.move({name: (None, JAW_OPEN_RAD)})

    def turn_needle(self, name: str, centre: np.ndarray, axis: np.ndarray, angle: float) -> None:
        """Turn the needle held by ``name`` by ``angle`` (rad) about ``axis`` through ``centre``
        (world), the jaws following; timed for the jaws' speed and turn limits."""
        T0n, T_jn = self.T_world_needle.copy(), self.grasps[name]
        reach = np.linalg.norm(np.cross(axis, self.jaws[name][:3, 3] - centre))
        t = PEAK * abs(angle) * max(1.0 / self.turn_rad_s, reach / self.speed_m_s)
        n = max(1, int(np.ceil(t * FPS)))
        for k in range(1, n + 1):
            R = rotvec_to_R(axis * angle * float(minimum_jerk(k / n)))
            M = make_T(R, centre - R @ centre)
            self.T_world_needle = M @ T0n
            self.jaws[name] = self.T_world_needle @ inv_T(T_jn)
            self.record()


# ---------------------------------------------------------------- poses of the script

def _jaw_look(T_world_jaw: np.ndarray, side: float) -> tuple[float, float]:
    """(how far the shaft points up, how far it points towards its trocar's side) for a jaw
    pose: the shaft runs along -z of the jaw frame."""
    shaft = -T_world_jaw[:3, 2]
    return float(shaft[2]), float(side * shaft[0])


def _draw_grasp(rng, needle: NeedleModel, poses: list, side: float, where: str, up_min: float = 0.45,
                towards_min: float = 0.15, tries: int = 400) -> np.ndarray:
    """A grasp (``T_jaw_needle``) of the needle by an instrument on ``side`` that, at each of the
    needle's ``poses``, has the shaft lead up (``up_min``) and towards its trocar
    (``towards_min``) with the pivot above the tissue; the best of ``tries`` draws."""
    lo, hi = {"middle": (75, 105), "tail": (118, 136)}[where]
    best, best_score = None, -np.inf
    for _ in range(tries):
        mirrored = np.pi if rng.random() < 0.5 else 0.0   # the arc curving the other way in the jaws
        T_jn = grasp_pose(needle, np.deg2rad(rng.uniform(lo, hi)), rng.uniform(0.0025, 0.0045),
                          np.deg2rad(rng.uniform(-35, 35)), np.deg2rad(rng.uniform(-40, 40)) + mirrored)
        if rng.random() < 0.5:                       # the jaws turned over (they are symmetric)
            T_jn = make_T(rotvec_to_R([0, 0, np.pi]), np.zeros(3)) @ T_jn
        score = np.inf
        for T_wn in poses:
            T_wj = T_wn @ inv_T(T_jn)
            up, towards = _jaw_look(T_wj, side)
            p = T_wj[:3, 3]
            above = p[2] - float(phantom_height(p[0], p[1]))
            score = min(score, up - up_min, towards - towards_min, (above - 0.0015) * 200)
        if score > best_score:
            best, best_score = T_jn, score
        if score > 0.05:
            break
    return best


def _park(rng, side: float, near: np.ndarray) -> np.ndarray:
    """A jaw pose beside ``near`` on ``side``, the shaft leading up to the trocar."""
    p = near + np.array([side * rng.uniform(0.018, 0.03), rng.uniform(-0.012, 0.012), rng.uniform(0.012, 0.022)])
    shaft = np.array([side * 0.75, rng.uniform(-0.2, 0.3), 0.65])
    z = -shaft / np.linalg.norm(shaft)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z], 1) @ rotvec_to_R([0, 0, rng.uniform(-1.0, 1.0)])
    return make_T(R, p)


def _rest_pose(rng, needle: NeedleModel, wire_r: float, reach: float = 0.014) -> np.ndarray:
    """The needle flat on the pad near its centre (within ``reach`` m), either side up."""
    flip = rotvec_to_R([np.pi, 0, 0]) if rng.random() < 0.5 else np.eye(3)
    R = rotvec_to_R([0, 0, rng.uniform(-np.pi, np.pi)]) @ rotvec_to_R(np.append(rng.normal(0, 0.05, 2), 0)) @ flip
    T = make_T(R, np.append(rng.uniform(-reach, reach, 2), 0.0))
    T[2, 3] = rest_height(T, needle, wire_r)
    return T


def _above(T: np.ndarray, dz: float) -> np.ndarray:
    out = T.copy()
    out[2, 3] += dz
    return out


def _backed_off(T_world_jaw: np.ndarray, dist: float) -> np.ndarray:
    """The jaws drawn back ``dist`` along their shaft (and a little up)."""
    out = T_world_jaw.copy()
    out[:3, 3] += -T_world_jaw[:3, 2] * dist + np.array([0, 0, 0.3 * dist])
    return out


def throw_site(rng, needle: NeedleModel) -> tuple:
    """Where a throw happens: (centre, axis) in world, the arc's axis horizontal and the centre
    0.8 of the radius above the pad, so the 120-degree arc bites 2 mm deep."""
    xy = rng.uniform([-0.012, -0.01], [0.012, 0.01])
    az = rng.uniform(np.deg2rad(20), np.deg2rad(60)) * (1 if rng.random() < 0.5 else -1)
    axis = np.array([np.sin(az), np.cos(az), 0.0])        # facing the endoscope (which looks along +y)
    centre = np.array([xy[0], xy[1], float(phantom_height(*xy)) + 0.8 * needle.radius_m])
    return centre, axis


def throw_start(needle: NeedleModel, centre: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The needle's pose at the start of a throw that turns it by ``-THROW_ANGLE`` about ``axis``
    (horizontal) through ``centre``: its plane upright, the tip 10 degrees above where it enters."""
    z = axis                                             # turning by -angle about z moves the tip down
    up = np.array([0.0, 0.0, 1.0])
    x0 = np.cross(up, z)
    x0 /= np.linalg.norm(x0)
    # the tip (arc angle a_A) at 10 deg above the entry, which lies asin(0.8) below the horizontal
    a_tip = needle.arc_span_rad[0]
    psi = -np.arcsin(0.8) + np.deg2rad(10)
    rot = psi - a_tip
    x = np.cos(rot) * x0 + np.sin(rot) * np.cross(z, x0)
    return make_T(np.stack([x, np.cross(z, x), z], 1), centre)


THROW_ANGLE = np.deg2rad(97.0)      # from 10 deg above the entry to the tip 11 deg out of the exit


def throw_poses(T_start: np.ndarray, centre: np.ndarray, axis: np.ndarray, n: int = 7) -> list:
    """``n`` needle poses over a throw from ``T_start`` about ``axis`` through ``centre``."""
    out = []
    for f in np.linspace(0, 1, n):
        R = rotvec_to_R(axis * -THROW_ANGLE * f)
        out.append(make_T(R, centre - R @ centre) @ T_start)
    return out


# ---------------------------------------------------------------- the scripts

@dataclass
class ScriptedTake:
    """A take's frames and what the script drew (``grasps``: name -> where on the arc)."""

    frames: list
    motion: str
    grasps: dict
    speed_m_s: float
    turn_rad_s: float


def script_take(motion: str, rng: np.random.Generator, needle: NeedleModel, wire_r: float) -> ScriptedTake:
    """The frames of one take of ``motion`` (see the module docstring)."""
    if motion not in MOTIONS:
        raise ValueError(f"motion must be one of {MOTIONS}, got {motion!r}")
    speed = float(rng.uniform(0.75, 1.0) * MAX_SPEED_M_S)
    turn = float(rng.uniform(0.6, 1.0) * MAX_TURN_RAD_S)
    first, second = INSTRUMENTS
    where = {}
    T_rest = _rest_pose(rng, needle, wire_r)
    centre = transform_points(T_rest, needle.keypoints()).mean(axis=0)
    jaws = {n: _park(rng, SIDES[n], centre) for n in INSTRUMENTS}
    take = Take(T_rest, jaws, {n: float(rng.uniform(0.2, 0.5)) for n in INSTRUMENTS}, speed, turn)
    throws = motion in ("throw", "suture")
    if throws:
        site, axis = throw_site(rng, needle)
        axis = axis * (1.0 if rng.random() < 0.5 else -1.0)
        T_start = throw_start(needle, site, axis)
        T_high = _above(T_start, rng.uniform(0.005, 0.008))
        thrower = second if motion == "suture" else first
        T_jn_throw = _draw_grasp(rng, needle, [T_high] + throw_poses(T_start, site, axis), SIDES[thrower], "tail",
                                 up_min=0.2, towards_min=0.05)
    # where the needle changes hands: above the throw site, upright, in a suture; else in the air
    T_air = T_high if motion == "suture" else _above(T_rest, rng.uniform(0.006, 0.01))
    if motion in ("handover", "throw"):                  # the needle starts in psm1's jaws, in the air
        where[first] = "tail" if motion == "throw" else str(rng.choice(["middle", "tail"]))
        T_air = T_high if motion == "throw" else T_air
        T_jn = T_jn_throw if motion == "throw" else _draw_grasp(rng, needle, [T_air], SIDES[first], where[first])
        take.T_world_needle = T_air.copy()
        take.jaws[first] = T_air @ inv_T(T_jn)
        take.jaw_rad[first] = JAW_CLOSED_RAD
        take.grasps[first] = T_jn
    if motion in ("pickup", "suture"):
        where[first] = "middle" if motion == "suture" else str(rng.choice(["middle", "tail"]))
        T_lift = _above(T_rest, rng.uniform(0.006, 0.01))
        if motion == "suture":
            T_carry = T_air
        else:
            a = rng.uniform(0, 2 * np.pi)
            carry = rng.uniform(0.01, 0.018) * np.array([np.cos(a), np.sin(a), 0.0])
            T_carry = make_T(rotvec_to_R(rng.normal(0, 0.25, 3)) @ T_rest[:3, :3], T_lift[:3, 3] + carry)
        T_jn1 = _draw_grasp(rng, needle, [T_rest, T_lift, T_carry], SIDES[first], where[first],
                            up_min=0.3 if motion == "suture" else 0.45)
        T_grip = T_rest @ inv_T(T_jn1)
        take.jaws[first] = _backed_off(T_grip, rng.uniform(0.012, 0.018))   # in view, coming in
        take.jaw_rad[first] = JAW_OPEN_RAD
    if motion in ("handover", "suture"):
        where[second] = "tail" if motion == "suture" or where[first] == "middle" else "middle"
        T_jn2 = T_jn_throw if motion == "suture" else _draw_grasp(rng, needle, [T_air], SIDES[second], where[second])
        T_grip2 = T_air @ inv_T(T_jn2)
        take.jaws[second] = _backed_off(T_grip2, rng.uniform(0.014, 0.02))  # waiting in view, near
        take.jaw_rad[second] = JAW_OPEN_RAD
    take.hold(0.2)
    if motion in ("pickup", "suture"):
        take.move({first: (_backed_off(T_grip, 0.004), None)})              # approach
        take.move({first: (T_grip, None)})
        take.grasp(first)
        take.move({first: (T_lift @ inv_T(T_jn1), None)})                   # off the pad
        take.move({first: (T_carry @ inv_T(T_jn1), None)})                  # across the view
        take.hold(0.2)
    holder = first
    if motion in ("handover", "suture"):
        take.move({second: (_backed_off(T_grip2, 0.004), None)})
        take.move({second: (T_grip2, None)})
        take.grasp(second)
        take.hold(0.15)
        take.release(first)
        take.move({first: (_backed_off(take.jaws[first], 0.01), None)})
        holder = second
        if motion == "handover":
            a = rng.uniform(0, 2 * np.pi)                # psm2 carries it away across the view
            carry = np.array([np.cos(a), np.sin(a), rng.uniform(-0.3, 0.3)]) * rng.uniform(0.008, 0.015)
            take.move({second: (make_T(take.jaws[second][:3, :3], take.jaws[second][:3, 3] + carry), None)})
    if throws:
        T_jn = take.grasps[holder]
        take.move({holder: (T_start @ inv_T(T_jn), None)})                  # down to the tissue
        take.turn_needle(holder, site, axis, -THROW_ANGLE)                 # the tip in, under, out
        take.hold(0.15)
        take.release(holder)
        take.move({holder: (_backed_off(take.jaws[holder], 0.008), None)})
    take.hold(0.1)
    return ScriptedTake(take.frames, motion, where, speed, turn)
