"""The patient-side instruments of a ROS source: which topics carry each arm's tool-tip pose
(``measured_cp``), its jaw angle (``jaw/measured_js``) and, optionally, its base's pose in world,
and how they make the jaw frame of ``docs/dataset.md`` in world (docs/ros.md#instruments).

A topic map's ``instruments`` (every key optional over the preset's):

```yaml
instruments:
  psm1:
    pose: /PSM1/measured_cp        # PoseStamped (or Transform(Stamped), RigidBodyState): T_base_tip
    jaw: /PSM1/jaw/measured_js     # JointState: position[0] = the jaws' opening (rad, 0 closed)
    base: /ambf/env/psm1/baselink/State   # optional: T_world_base from a topic (scene units)
    unit: m                        # the pose topic's unit (default: the map's unit)
    T_tip_jaw: 4x4                 # optional fixed transform from the reported tip frame to the jaws'
instrument_registration: psm_registration.yaml   # T_world_base per arm when no base topic
```

``T_world_jaw = T_world_base @ T_base_tip @ T_tip_jaw``: ``T_world_base`` from the ``base`` topic,
else the registration file's entry for the arm, else the identity (the pose already in world).
A jaw angle below 0 (the dVRK's jaws squeezed shut read slightly negative) counts as 0.
"""
from __future__ import annotations

import numpy as np

INSTRUMENT_ROLES = ("instrument_pose", "instrument_jaw", "instrument_base")
_ROLE_OF_KEY = {"pose": "instrument_pose", "jaw": "instrument_jaw", "base": "instrument_base"}
ENTRY_KEYS = {"pose", "jaw", "base", "unit", "T_tip_jaw"}
MAX_ARMS = 8


def _dvrk_arm(n: int) -> dict:
    return {"pose": f"/PSM{n}/measured_cp", "jaw": f"/PSM{n}/jaw/measured_js"}


def _ambf_arm(n: int) -> dict:
    # the challenge's CRTK wrapper (launch_crtk_interface.py): measured_cp in the arm's base frame
    # (frame_id psmN/baselink), in metres; the base body's state in the scene's units
    return {"pose": f"/CRTK/psm{n}/measured_cp", "jaw": f"/CRTK/psm{n}/jaw/measured_js",
            "base": [f"/ambf/env/psm{n}/baselink/State", f"/ambf/env/psm{n}/baselinksimple/State"], "unit": "m"}


PRESET_INSTRUMENTS = {"dvrk": {f"psm{n}": _dvrk_arm(n) for n in (1, 2)},
                      "ambf": {f"psm{n}": _ambf_arm(n) for n in (1, 2)}}


def merge_instruments(preset: dict | None, user) -> dict:
    """The preset's instruments updated arm by arm, key by key, with the user's."""
    out = {name: dict(v) for name, v in (preset or {}).items()}
    for name, v in (user or {}).items():
        out[name] = {**out.get(name, {}), **(v or {})} if isinstance(v, dict) else v
    return out


def validate_instruments(m: dict, where: str, base_dir: str, rigid, error, referenced) -> None:
    """Check (and normalise in place) a map's ``instruments`` and ``instrument_registration``;
    ``rigid(value, where, key)`` checks a 4x4, ``error(text)`` makes the exception,
    ``referenced(value, where, base_dir, key)`` reads a value given as a file name
    (``common.ros.topicmap``)."""
    from common.ros.conventions import UNITS
    inst = m.get("instruments")
    if inst is not None:
        if not isinstance(inst, dict) or len(inst) > MAX_ARMS:
            raise error(f"{where}: instruments: expected {{NAME: {{pose: TOPIC, jaw: TOPIC}}}} (at most {MAX_ARMS})")
        for name, v in inst.items():
            if not isinstance(v, dict):
                raise error(f"{where}: instruments.{name}: expected {{pose: TOPIC, jaw: TOPIC, base: TOPIC}}")
            unknown = set(v) - ENTRY_KEYS
            if unknown:
                raise error(f"{where}: instruments.{name}: unknown key {sorted(unknown)[0]!r} "
                            f"(known: {', '.join(sorted(ENTRY_KEYS))})")
            if not v.get("pose") or not v.get("jaw"):
                raise error(f"{where}: instruments.{name}: needs a pose and a jaw topic")
            if v.get("unit") is not None and v["unit"] not in UNITS:
                raise error(f"{where}: instruments.{name}.unit: must be one of {', '.join(UNITS)}, got {v['unit']!r}")
            if v.get("T_tip_jaw") is not None:
                v["T_tip_jaw"] = rigid(v["T_tip_jaw"], where, f"instruments.{name}.T_tip_jaw")
    reg, where_reg = referenced(m.get("instrument_registration"), where, base_dir, "instrument_registration")
    if reg is not None:
        if isinstance(reg, dict) and "T_world_base" in reg:
            reg = reg["T_world_base"]
        if not isinstance(reg, dict):
            raise error(f"{where_reg}: expected {{ARM: 4x4 T_world_base}} (each arm's base in world)")
        m["instrument_registration"] = {str(k): rigid(T, where_reg, str(k)) for k, T in reg.items()}


def instrument_topics(m: dict) -> list:
    """``(topic, role, arm)`` for every alternative topic of every instrument of a map."""
    from common.ros.topicmap import candidates
    out = []
    for name, v in (m.get("instruments") or {}).items():
        for key, role in _ROLE_OF_KEY.items():
            for t in candidates(v.get(key)):
                out.append((t, role, name))
    return out


def jaw_angle(position) -> float:
    """The opening of a jaw JointState's first position (rad), clamped into [0, pi]."""
    return float(np.clip(float(np.asarray(position, float).reshape(-1)[0]), 0.0, np.pi))


def instrument_poses(m: dict, state: dict, scale: float) -> dict | None:
    """``{arm: InstrumentPose}`` of the arms whose pose and jaw the ``state`` holds
    (``state["instrument_pose.psm1"]`` etc.: a pose part and the jaw's positions); None if none."""
    from common.data.instruments import InstrumentPose
    from common.ros.roles import pose_of
    from common.ros.conventions import unit_scale
    out = {}
    reg = m.get("instrument_registration") or {}
    for name, v in (m.get("instruments") or {}).items():
        pose, jaw = state.get(f"instrument_pose.{name}"), state.get(f"instrument_jaw.{name}")
        if pose is None or jaw is None or len(jaw) < 1:
            continue
        s_tip = unit_scale(v["unit"]) if v.get("unit") else scale
        base = state.get(f"instrument_base.{name}")
        T_wb = pose_of(base, scale) if base is not None else np.asarray(reg.get(name, np.eye(4)), float)
        T_tj = np.eye(4) if v.get("T_tip_jaw") is None else np.asarray(v["T_tip_jaw"], float)
        out[name] = InstrumentPose(T_wb @ pose_of(pose, s_tip) @ T_tj, jaw_angle(jaw))
    return out or None
