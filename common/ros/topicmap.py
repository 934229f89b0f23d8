"""Topic maps: which topics of a bag (or a live ROS 2 system) carry what, and their conventions.

A topic map is a mapping (YAML file, ``--topics MAP.yaml``) over a preset (``ambf``, ``dvrk`` or
none); every key is optional and overrides the preset's. docs/ros.md is the reference:

```yaml
preset: dvrk                       # base: ambf | dvrk (the command's --preset when left out)
images: {left: /jhu_daVinci/left/image_raw, right: /jhu_daVinci/right/image_raw}
camera_info: {left: /jhu_daVinci/left/camera_info, right: /jhu_daVinci/right/camera_info}
fovy_rad: 1.2                      # intrinsics when there is no camera_info (square pixels,
                                   # principal point at the image centre ((w-1)/2, (h-1)/2))
registration: reg.yaml             # T_ecm_cam of both cameras: a file or {left: 4x4, right: 4x4}
camera_axes: opencv                # opencv | ambf: the axes of camera poses given by topics
ecm_joints: /ECM/measured_js       # sensor_msgs/JointState: yaw, pitch, insertion, roll
ecm_pose: /ECM/measured_cp         # PoseStamped (or ambf RigidBodyState): T_world_ecm
needle_pose: /needle/measured_cp   # ground truth T_world_needle (PoseStamped, Pose, RigidBodyState)
needle_frame: dataset              # dataset | ambf: the needle body frame of needle_pose
T_given_needle: 4x4                # or any fixed transform from the dataset needle frame to it
needle: {radius_m: 0.01018, keypoint_angles_deg: [30, 60, 90, 120, 150]}
unit: m                            # m | dm | cm | mm | auto (AMBF: from the baseline)
stereo_tolerance_ms: 5             # left/right header stamps further apart are not a pair
ecm: {T_world_base: 4x4, L_rcc: 0.0, L_scopelen: 0.0}   # optional arm model for ecm_joints
instruments: {psm1: {pose: /PSM1/measured_cp, jaw: /PSM1/jaw/measured_js}, psm2: {...}}
instrument_registration: psm_reg.yaml   # {psm1: 4x4 T_world_base, ...}  (common/ros/instruments.py)
```

AMBF only: ``camera_frame`` (the CameraFrame body's RigidBodyState: T_world_ecm, the ECM frame
being the AMBF CameraFrame) and ``camera_states`` ({left, right} CameraState poses in their
parent, the CameraFrame). A topic may be a list of alternatives: the first the bag has is used.
"""
from __future__ import annotations

import copy
import os

import numpy as np
import yaml

from common.errors import NeedletrackError
from common.frames import CAMERAS
from common.ros.conventions import AMBF_FOVY_RAD, AMBF_NEEDLE_RADIUS_M, UNITS
from common.ros.instruments import PRESET_INSTRUMENTS, merge_instruments, validate_instruments

PRESETS = {
    "ambf": {
        "images": {"left": ["/ambf/env/cameras/cameraL/ImageData", "/ambf/env/cameras/cameraL/ImageData/compressed"],
                   "right": ["/ambf/env/cameras/cameraR/ImageData", "/ambf/env/cameras/cameraR/ImageData/compressed"]},
        "camera_frame": ["/ambf/env/CameraFrame/State", "/ambf/env/CameraFrame"],
        "camera_states": {"left": "/ambf/env/cameras/cameraL/State", "right": "/ambf/env/cameras/cameraR/State"},
        "needle_pose": ["/ambf/env/Needle/State", "/ambf/env/phantom/Needle/State"],
        "needle_frame": "ambf",
        "camera_axes": "ambf",
        "fovy_rad": AMBF_FOVY_RAD,
        "unit": "auto",
        "needle": {"radius_m": AMBF_NEEDLE_RADIUS_M},   # metres, whatever unit the scene is in
        "stereo_tolerance_ms": 5.0,
        "instruments": PRESET_INSTRUMENTS["ambf"],
    },
    "dvrk": {
        # {rig} is found in the bag: the one name with both cameras' topics
        "images": {"left": ["/{rig}/left/image_raw", "/{rig}/left/camera/image_raw", "/{rig}/left/image_rect_color",
                            "/{rig}/left/image_raw/compressed", "/{rig}/left/camera/image_raw/compressed"],
                   "right": ["/{rig}/right/image_raw", "/{rig}/right/camera/image_raw", "/{rig}/right/image_rect_color",
                             "/{rig}/right/image_raw/compressed", "/{rig}/right/camera/image_raw/compressed"]},
        "camera_info": {"left": ["/{rig}/left/camera_info", "/{rig}/left/camera/camera_info"],
                        "right": ["/{rig}/right/camera_info", "/{rig}/right/camera/camera_info"]},
        "ecm_joints": "/ECM/measured_js",
        "ecm_pose": "/ECM/measured_cp",
        "needle_frame": "dataset",
        "camera_axes": "opencv",
        "unit": "m",
        "stereo_tolerance_ms": 5.0,
        "instruments": PRESET_INSTRUMENTS["dvrk"],
    },
}
KEYS = {"preset", "images", "camera_info", "fovy_rad", "registration", "camera_axes", "ecm_joints", "ecm_pose",
        "needle_pose", "needle_frame", "T_given_needle", "needle", "unit", "stereo_tolerance_ms", "ecm",
        "camera_frame", "camera_states", "instruments", "instrument_registration"}


class TopicMapError(NeedletrackError, ValueError):
    """A topic map that cannot be used; the text names the key (and the file)."""


def load_topic_map(preset: str | None, path_or_dict=None) -> dict:
    """The preset's map updated with the user's (a YAML file path or a dict); validated."""
    user, where = {}, "topic map"
    if isinstance(path_or_dict, (str, os.PathLike)):
        where = os.fspath(path_or_dict)
        try:
            with open(where, encoding="utf-8") as f:
                user = yaml.safe_load(f) or {}
        except OSError as exc:
            raise TopicMapError(f"{where}: cannot read the topic map: {exc.strerror}") from None
        except yaml.YAMLError as exc:
            raise TopicMapError(f"{where}: not valid YAML: {exc}") from None
    elif path_or_dict:
        user = dict(path_or_dict)
    if not isinstance(user, dict):
        raise TopicMapError(f"{where}: expected a mapping of keys, got {type(user).__name__}")
    unknown = set(user) - KEYS
    if unknown:
        raise TopicMapError(f"{where}: unknown key {sorted(unknown)[0]!r} (known: {', '.join(sorted(KEYS))})")
    name = user.get("preset", preset)
    if name is not None and name not in PRESETS:
        raise TopicMapError(f"{where}: preset must be one of {', '.join(PRESETS)}, got {name!r}")
    m = copy.deepcopy(PRESETS[name]) if name else {"camera_axes": "opencv", "needle_frame": "dataset",
                                                   "unit": "m", "stereo_tolerance_ms": 5.0}
    inst = merge_instruments(m.get("instruments"), user.get("instruments")) if "instruments" in user else None
    m.update(copy.deepcopy(user))
    if inst is not None:
        m["instruments"] = inst
    m["preset"] = name
    base = os.path.dirname(where) if where != "topic map" else ""
    _validate(m, where, base)
    return m


def _T(v, where: str, key: str) -> np.ndarray:
    T = np.asarray(v, dtype=float)
    if T.shape != (4, 4) or not np.allclose(T[3], [0, 0, 0, 1]) or \
            not np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-6) or np.linalg.det(T[:3, :3]) < 0:
        raise TopicMapError(f"{where}: {key}: expected a 4x4 rigid transform, got {np.asarray(v).tolist()}")
    return T


def referenced(value, where: str, base: str, key: str) -> tuple:
    """(the value, where it came from) of a key that may name a YAML file (relative to ``base``,
    the topic map's folder) instead of holding its value."""
    if not isinstance(value, (str, os.PathLike)):
        return value, f"{where}: {key}"
    path = value if os.path.isabs(value) or not base else os.path.join(base, value)
    try:
        with open(path, encoding="utf-8") as f:
            return yaml.safe_load(f), os.fspath(path)
    except (OSError, yaml.YAMLError) as exc:
        raise TopicMapError(f"{where}: {key}: cannot read {path}: {exc}") from None


def _validate(m: dict, where: str, base: str) -> None:
    if "images" not in m or not isinstance(m["images"], dict) or set(m["images"]) != {"left", "right"}:
        raise TopicMapError(f"{where}: images: expected {{left: TOPIC, right: TOPIC}}")
    if m.get("camera_axes") not in ("opencv", "ambf"):
        raise TopicMapError(f"{where}: camera_axes: must be opencv or ambf, got {m.get('camera_axes')!r}")
    if m.get("needle_frame") not in ("dataset", "ambf"):
        raise TopicMapError(f"{where}: needle_frame: must be dataset or ambf, got {m.get('needle_frame')!r}")
    if m.get("unit") != "auto" and m.get("unit") not in UNITS:
        raise TopicMapError(f"{where}: unit: must be one of {', '.join(UNITS)} or auto, got {m.get('unit')!r}")
    try:
        m["stereo_tolerance_ms"] = float(m.get("stereo_tolerance_ms", 5.0))
    except (TypeError, ValueError):
        raise TopicMapError(f"{where}: stereo_tolerance_ms: expected a number") from None
    if m.get("T_given_needle") is not None:
        m["T_given_needle"] = _T(m["T_given_needle"], where, "T_given_needle")
    reg, where_reg = referenced(m.get("registration"), where, base, "registration")
    if reg is not None:
        if isinstance(reg, dict) and "T_ecm_cam" in reg:
            reg = reg["T_ecm_cam"]
        if not isinstance(reg, dict) or not {"left", "right"} <= set(reg):
            raise TopicMapError(f"{where_reg}: expected {{left: 4x4 T_ecm_cam, right: 4x4 T_ecm_cam}} "
                                f"(OpenCV camera frames in the ECM tip frame)")
        m["registration"] = {c: _T(reg[c], where_reg, c) for c in CAMERAS}
    if m.get("ecm") is not None and not isinstance(m["ecm"], dict):
        raise TopicMapError(f"{where}: ecm: expected {{T_world_base, L_rcc, L_scopelen}}")
    nd = m.get("needle")
    if nd is not None and (not isinstance(nd, dict) or "radius_m" not in nd):
        raise TopicMapError(f"{where}: needle: expected {{radius_m: R, keypoint_angles_deg: [5 angles]}}")
    validate_instruments(m, where, base, _T, TopicMapError, referenced)


def candidates(value) -> list:
    """A topic setting as a list of alternatives (None -> [])."""
    if value is None:
        return []
    return list(value) if isinstance(value, (list, tuple)) else [value]


def resolve_rig(m: dict, topics) -> dict:
    """Fill ``{rig}`` in the dVRK preset's topics with the one rig name whose left and right
    image topics are both in ``topics``; TopicMapError listing what was found otherwise."""
    pats = candidates(m["images"]["left"])
    if not any("{rig}" in p for p in pats):
        return m
    rigs = set()
    for p in pats:
        head, tail = p.split("{rig}")
        for t in topics:
            if t.startswith(head) and t.endswith(tail) and len(t) > len(head) + len(tail):
                rig = t[len(head):len(t) - len(tail)]
                right = [q.replace("{rig}", rig) for q in candidates(m["images"]["right"])]
                if any(r in topics for r in right):
                    rigs.add(rig)
    if len(rigs) != 1:
        what = "no" if not rigs else f"{len(rigs)} ({', '.join(sorted(rigs))})"
        raise TopicMapError(f"preset {m.get('preset')}: {what} stereo rig found: expected topics like "
                            f"{pats[0]} and its right twin among {sorted(topics)[:20]}; give images: "
                            f"{{left: TOPIC, right: TOPIC}} in a topic map (--topics)")
    return resolve_rig_name(m, rigs.pop())


def resolve_rig_name(m: dict, rig: str) -> dict:
    """The map with ``{rig}`` in its image and camera_info topics replaced by ``rig``."""
    def sub(v):
        if isinstance(v, str):
            return v.replace("{rig}", rig)
        if isinstance(v, list):
            return [sub(x) for x in v]
        if isinstance(v, dict):
            return {k: sub(x) for k, x in v.items()}
        return v
    out = dict(m)
    for k in ("images", "camera_info"):
        if k in out:
            out[k] = sub(out[k])
    out["rig"] = rig
    return out
