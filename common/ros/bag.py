"""Stereo frames out of a ROS bag: ROS 1 ``.bag``, ROS 2 ``.db3`` or ``.mcap`` (a file or a bag
directory), read with ``rosbags`` (no ROS installation).

``BagStereo(path, preset, topics)`` iterates ``StereoSample``s in bag order: the left and right
images paired by header stamp (within ``stereo_tolerance_ms``; an image without a partner is
dropped and counted), with the intrinsics (camera_info, or the vertical field of view), the
cameras' poses ``T_ecm_cam`` (OpenCV axes, metres), and, when the bag has them, the ECM joints,
``T_world_ecm`` and the ground-truth ``T_world_needle`` (dataset needle frame, metres). States
(joints, poses, camera_info) are the last ones the bag holds before the pair completes.
The conventions (frames, fixed transforms, units) are in ``common/ros/conventions.py`` and
docs/ros.md.
"""
from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from common.errors import NeedletrackError
from common.frames import CAMERAS
from common.geometry.camera import intrinsics_from_fovy
from common.geometry.needle import NeedleModel
from common.ros.conventions import (
    T_AMBF_NEEDLE,
    T_AMBFCAM_CV,
    infer_ambf_unit,
    stamp_ns,
    unit_scale,
)
from common.ros.images import ImageError, image_to_bgr
from common.ros.instruments import INSTRUMENT_ROLES, instrument_poses, instrument_topics
from common.ros.roles import IMAGE_TYPES, message_problem, pose_of, pose_part
from common.ros.topicmap import TopicMapError, candidates, load_topic_map, resolve_rig

TIMED_ROLES = ("ecm_joints", "ecm_pose", "needle_pose", "camera_frame") + INSTRUMENT_ROLES
MAX_STATE_BYTES = 1 << 20    # a non-image message's serialised size (a JointState of 4 joints: ~120 B)
HISTORY = 256                # time-varying states kept per role (each a pose or <= MAX_JOINTS floats)
IMAGE_QUEUE = 16             # images waiting for their partner, per camera

log = logging.getLogger("needletrack.ros")


class BagError(NeedletrackError, ValueError):
    """A bag that cannot give stereo frames; the text names the bag, topic and what is wrong."""


class BadMessage(BagError):
    """One message refused at the source (wrong type for its role, non-finite calibration or pose,
    oversized arrays, an image that cannot be decoded): counted per topic; the stream goes on."""


class _NotReady(Exception):
    """A pair that came before a state it needs (camera_info, camera states): skipped, counted."""


@dataclass
class StereoSample:
    """One stereo frame of a bag. Poses 4x4 in metres; ``K`` 3x3 px; ``dist`` OpenCV order."""

    index: int
    stamp_ns: int
    images: dict                               # {camera: (h, w, 3) uint8 BGR}
    cameras: dict                              # {camera: {"K", "dist", "T_ecm_cam"}}
    image_size: tuple                          # (w, h)
    ecm_joints: Optional[np.ndarray] = None    # [yaw, pitch, insertion, roll] rad, rad, m, rad
    T_world_ecm: Optional[np.ndarray] = None
    T_world_needle: Optional[np.ndarray] = None
    info: dict = field(default_factory=dict)
    instruments: Optional[dict] = None         # {arm: common.data.instruments.InstrumentPose}, world, m


def _kept(role: str, msg):
    """What the assembler keeps of a time-varying state: the pose or the first 4 joint positions."""
    if role == "ecm_joints":
        return np.asarray(msg.position, float).reshape(-1)[:4].copy()
    if role == "instrument_jaw":
        return np.asarray(msg.position, float).reshape(-1)[:1].copy()
    return pose_part(msg)


def open_reader(path):
    """An opened reader over ``path`` (ROS 1 .bag, ROS 2 .db3/.mcap file or directory;
    ``common/ros/reader.py``): an unfinished MCAP file is read up to its last complete chunk
    (``reader.recovered`` says so), a topic of an unresolvable type is listed in
    ``reader.unresolved``."""
    from common.ros.reader import BagReader, UnfinishedMcap, is_mcap, is_unfinished_mcap
    p = Path(path)
    if not p.exists():
        raise BagError(f"{p}: no such bag file or folder")
    mcaps = sorted(p.glob("*.mcap")) if p.is_dir() else [p]
    if len(mcaps) == 1 and is_unfinished_mcap(mcaps[0]):   # a recording, or a bag folder's one file, cut short
        return UnfinishedMcap(mcaps[0])
    try:
        return BagReader(p)
    except Exception as exc:   # rosbags raises its own reader errors for unreadable bags
        first = exc
    if is_mcap(p):                  # an MCAP file whose summary is unreadable
        try:
            return UnfinishedMcap(p, f"a recording whose summary cannot be read ({first})")
        except BagError:
            pass
    raise BagError(f"{p}: not a readable ROS 1 .bag or ROS 2 .db3/.mcap bag: {first}") from None


class StereoAssembler:
    """Turns a stream of deserialised ROS messages into ``StereoSample``s, whatever carries them
    (a bag, or live ROS 2 on Zenoh): ``feed(topic, msg)`` returns the samples completed by that
    message (a list, usually empty or one). ``m`` is a resolved topic map; ``where`` names the
    source in errors. ``roles`` maps each used topic to (role, camera or None).

    A message that cannot serve its role (``message_problem``), or that the owner could not
    decode (``refuse``), is counted in ``refused`` ({topic: count}) and reported through
    ``report(topic, reason)`` (default: logged once per topic); the stream goes on.
    ``check_values`` (live sources): a non-finite or out-of-range calibration, pose or joint state
    is refused too; without it (bags) such values reach the samples, for the caller to name the
    frame (``convert.sample_fault``)."""

    def __init__(self, m: dict, where: str, roles: dict, report=None, check_values: bool = True):
        self.map, self.path, self.topic_role = m, where, roles
        self.check_values = check_values
        self.refused: dict = {}
        self.report = report or self._log_once
        self.info = {"source": where, "preset": m.get("preset"),
                     "topics": {r + (f".{c}" if c else ""): t for t, (r, c) in roles.items()}}
        self.tol_ns = int(m["stereo_tolerance_ms"] * 1e6)
        self.counts = {"unpaired_left": 0, "unpaired_right": 0}
        self.scale = None if m["unit"] == "auto" else unit_scale(m["unit"])
        if self.scale is not None:
            self.info["unit"] = m["unit"]
        self.T_given_needle = m.get("T_given_needle")
        if self.T_given_needle is None:
            self.T_given_needle = T_AMBF_NEEDLE if m["needle_frame"] == "ambf" else np.eye(4)
        self.state: dict = {}
        self.queues = {"left": deque(), "right": deque()}
        self.index = 0
        self.has_role = {r for r, _ in roles.values()}
        self.hist: dict = {}             # time-varying states: role -> deque of (stamp or None, msg)
        self.pending: deque = deque()    # completed pairs waiting for their states

    # ------------------------------------------------------------------ helpers

    def refuse(self, topic: str, reason: str) -> None:
        """Count one refused message of ``topic`` and report it."""
        self.refused[topic] = self.refused.get(topic, 0) + 1
        self.report(topic, reason)

    def refuse_oversized(self, topic: str, nbytes: int, msgtype: str) -> None:
        """Refuse a non-image message of ``nbytes`` over ``MAX_STATE_BYTES``, undecoded."""
        self.refuse(topic, f"{nbytes} bytes for a {msgtype}: more than {MAX_STATE_BYTES} (MAX_STATE_BYTES)")

    def _log_once(self, topic: str, reason: str) -> None:
        if self.refused[topic] == 1:
            log.warning("%s: %s: message refused (further ones on this topic counted, not logged): %s",
                        self.path, topic, reason)

    def needle_model(self) -> NeedleModel:
        """The needle: the map's ``needle`` (radius in metres; the ambf preset's is the challenge's
        10.18 mm whatever the scene's unit), else the default."""
        nd = self.map.get("needle")
        if nd:
            return NeedleModel(radius_m=float(nd["radius_m"]),
                               keypoint_angles_deg=tuple(nd.get("keypoint_angles_deg", (30, 60, 90, 120, 150))))
        return NeedleModel()

    # ------------------------------------------------------------------ iteration

    def _intrinsics(self, cam: str, info_msg, w: int, h: int):
        if info_msg is not None:
            K = np.asarray(getattr(info_msg, "k", getattr(info_msg, "K", None)), float).reshape(3, 3)
            D = np.asarray(getattr(info_msg, "d", getattr(info_msg, "D", [])), float).reshape(-1)
            if (int(info_msg.width), int(info_msg.height)) not in ((w, h), (0, 0)):
                raise BagError(f"{self.path}: {self.info['topics'].get('camera_info.' + cam)}: camera_info says "
                               f"{info_msg.width}x{info_msg.height}, the images are {w}x{h}")
            # K and D were checked (finite, a camera matrix, a supported model) when fed
            return K, (D if len(D) else np.zeros(5))
        if "camera_info" in self.has_role:
            raise _NotReady("camera_info")
        fovy = self.map.get("fovy_rad")
        if fovy is None:
            raise BagError(f"{self.path}: no intrinsics for the {cam} camera: the bag has no camera_info "
                           f"topic and the topic map gives no fovy_rad")
        return intrinsics_from_fovy(w, h, float(fovy)), np.zeros(5)

    def _ensure_scale(self, state: dict) -> None:
        if self.scale is not None:
            return
        cs = state.get("camera_state", {})
        if not ("left" in cs and "right" in cs) and "camera_state" in self.has_role:
            raise _NotReady("camera_states")
        if "left" in cs and "right" in cs:
            b = float(np.linalg.norm(pose_of(cs["left"])[:3, 3] - pose_of(cs["right"])[:3, 3]))
            try:
                unit = infer_ambf_unit(b)
            except ValueError as exc:
                raise BagError(f"{self.path}: {exc}") from None
            self.scale = unit_scale(unit)
            self.info["unit"] = f"{unit} (inferred from the cameras' baseline {b:.6g})"
        else:
            raise BagError(f"{self.path}: unit: auto needs both cameras' State topics to infer the unit "
                           f"from the baseline; set unit: m|dm in a topic map")

    def _camera_poses(self, state: dict) -> dict:
        reg = self.map.get("registration")
        cs = state.get("camera_state", {})
        if "left" in cs and "right" in cs:
            fix = T_AMBFCAM_CV if self.map["camera_axes"] == "ambf" else np.eye(4)
            return {c: pose_of(cs[c], self.scale) @ fix for c in CAMERAS}
        if reg is not None:
            return {c: np.asarray(reg[c], float) for c in CAMERAS}
        if "camera_state" in self.has_role:
            raise _NotReady("camera_states")
        raise BagError(f"{self.path}: no camera poses: the bag has no camera State topics and the topic map "
                       f"gives no registration (T_ecm_cam of left and right)")

    def _sample(self, index: int, left, right, state: dict) -> StereoSample:
        imgs = {}
        for c, (t, msg) in zip(CAMERAS, (left, right)):
            try:
                imgs[c] = image_to_bgr(msg)
            except ImageError as exc:
                raise BadMessage(self.info["topics"]["image." + c], str(exc)) from None
        h, w = imgs["left"].shape[:2]
        if imgs["right"].shape[:2] != (h, w):
            raise BagError(f"{self.path}: left image {w}x{h} and right image "
                           f"{imgs['right'].shape[1]}x{imgs['right'].shape[0]} differ in size")
        self._ensure_scale(state)
        poses = self._camera_poses(state)
        cams = {}
        for c in CAMERAS:
            K, D = self._intrinsics(c, state.get("camera_info", {}).get(c), w, h)
            cams[c] = {"K": K, "dist": D, "T_ecm_cam": poses[c]}
        T_world_ecm = None
        if "camera_frame" in state:
            T_world_ecm = pose_of(state["camera_frame"], self.scale)
        elif "ecm_pose" in state:
            T_world_ecm = pose_of(state["ecm_pose"], self.scale)
        q = None
        if "ecm_joints" in state:
            pos = state["ecm_joints"]          # the first 4 positions (_kept)
            if len(pos) >= 4:
                q = pos[:4].copy()
                q[2] *= self.scale
        if T_world_ecm is None and q is not None and self.map.get("ecm"):
            from common.geometry.ecm_kinematics import EcmArm
            T_world_ecm = EcmArm.from_dict(self.map["ecm"]).T_world_ecm(q)
        T_world_needle = None
        if "needle_pose" in state:
            T_world_needle = pose_of(state["needle_pose"], self.scale) @ self.T_given_needle
        instruments = instrument_poses(self.map, state, self.scale)
        return StereoSample(index, left[0], imgs, cams, (w, h), q, T_world_ecm, T_world_needle,
                            instruments=instruments)

    def feed_bytes(self, topic: str, raw, msgtype: str, decode=None) -> list:
        """``feed`` the message serialised in ``raw``, decoded by ``decode(raw, msgtype)`` (default
        ``common.ros.cdr.decode``: CDR with the project's ROS 2 types; a bag reader's binds its
        own types); bytes that do not decode as ``msgtype`` (``CdrError``), or a non-image
        message over ``MAX_STATE_BYTES``, are refused (counted, reported)."""
        from common.ros import cdr
        if self.topic_role[topic][0] != "image" and len(raw) > MAX_STATE_BYTES:
            self.refuse_oversized(topic, len(raw), msgtype)
            return []
        try:
            msg = (decode or cdr.decode)(raw, msgtype)
        except cdr.CdrError as exc:
            self.refuse(topic, f"cannot deserialise: {exc}")
            return []
        return self.feed(topic, msg)

    def feed(self, topic: str, msg) -> list:
        """Take one message of a used topic; returns the stereo samples it completes.

        A pair goes out once every time-varying state seen so far (ECM joints and pose, needle
        pose, CameraFrame) has a message stamped at or after it (or two newer pairs wait), with
        for each the message stamped last at or before the pair (the one stamped nearest to it
        when none is): states recorded just after their images still belong to them."""
        role, cam = self.topic_role[topic]
        why = message_problem(role, msg, self.check_values)
        if why is not None:
            self.refuse(topic, why)
            return []
        if role == "image":
            self.queues[cam].append((stamp_ns(msg.header), msg))
            L, R = self.queues["left"], self.queues["right"]
            while L and R:
                dl, dr = L[0][0], R[0][0]
                if abs(dl - dr) <= self.tol_ns:
                    self.pending.append((L.popleft(), R.popleft()))
                elif dl < dr:
                    L.popleft()
                    self.counts["unpaired_left"] += 1
                else:
                    R.popleft()
                    self.counts["unpaired_right"] += 1
            for q in (L, R):            # a live stream with one camera gone: do not grow
                while len(q) > IMAGE_QUEUE:
                    q.popleft()
                    self.counts["unpaired_left" if q is L else "unpaired_right"] += 1
        elif role in TIMED_ROLES:
            hdr = getattr(msg, "header", None)
            key = role if cam is None else f"{role}.{cam}"      # an instrument's: one per arm
            self.hist.setdefault(key, deque(maxlen=HISTORY)).append(
                (None if hdr is None else stamp_ns(hdr), _kept(role, msg)))
        elif cam is not None:
            self.state.setdefault(role, {})[cam] = msg
        else:
            self.state[role] = msg
        return self._release(final=False)

    def _caught_up(self, t: int) -> bool:
        return all(h[-1][0] is None or h[-1][0] >= t - self.tol_ns for h in self.hist.values() if h)

    def _state_at(self, t: int) -> dict:
        state = dict(self.state)
        for role, h in self.hist.items():
            best = None
            for st, msg in h:
                if st is None or st <= t + self.tol_ns:
                    if best is None or st is None or best[0] is None or st >= best[0]:
                        best = (st, msg)
            if best is None:   # all stamped after the pair (a recording begun between them): the nearest
                best = min(h, key=lambda e: abs(e[0] - t))
            state[role] = best[1]
        return state

    def _release(self, final: bool) -> list:
        out = []
        while self.pending:
            left, right = self.pending[0]
            if not final and len(self.pending) <= 2 and not self._caught_up(left[0]):
                break
            self.pending.popleft()
            try:
                out.append(self._sample(self.index, left, right, self._state_at(left[0])))
                self.index += 1
            except _NotReady as why:
                key = f"waiting_for_{why}"
                self.counts[key] = self.counts.get(key, 0) + 1
            except BadMessage as exc:            # an image that did not decode: the pair is lost
                self.refuse(*exc.args)
        return out

    def finish(self) -> list:
        """End of stream: the pairs still waiting go out; images without a partner are counted."""
        out = self._release(final=True)
        self.counts["unpaired_left"] += len(self.queues["left"])
        self.counts["unpaired_right"] += len(self.queues["right"])
        self.queues["left"].clear()
        self.queues["right"].clear()
        return out


def resolve_roles(m: dict, topics: dict, where: str) -> dict:
    """``{topic: (role, camera)}`` of a topic map against the available ``topics`` ({topic:
    type}): for each role the first alternative present; BagError naming what is missing."""
    roles = {}

    def pick(role, value, cam=None, required=False, types=None):
        for t in candidates(value):
            if t in topics:
                if types and topics[t] not in types:
                    raise BagError(f"{where}: topic {t} ({role}) has type {topics[t]}, "
                                   f"expected {' or '.join(types)}")
                roles[t] = (role, cam)
                return t
        if required:
            listing = ", ".join(f"{t} ({ty})" for t, ty in sorted(topics.items())) or "none"
            raise BagError(f"{where}: no {role} topic for the {cam} camera: looked for "
                           f"{', '.join(candidates(value))}; the bag has: {listing}")
        return None

    for c in CAMERAS:
        pick("image", m["images"][c], c, required=True, types=IMAGE_TYPES)
        pick("camera_info", (m.get("camera_info") or {}).get(c), c, types=("sensor_msgs/msg/CameraInfo",))
        pick("camera_state", (m.get("camera_states") or {}).get(c), c)
    for role in ("ecm_joints", "ecm_pose", "needle_pose", "camera_frame"):
        pick(role, m.get(role), types=("sensor_msgs/msg/JointState",) if role == "ecm_joints" else None)
    picked = {}
    for t, role, arm in instrument_topics(m):        # the first alternative the bag has, per arm and role
        if t in topics and (role, arm) not in picked:
            if role == "instrument_jaw" and topics[t] != "sensor_msgs/msg/JointState":
                raise BagError(f"{where}: topic {t} ({arm} jaw) has type {topics[t]}, expected sensor_msgs/msg/JointState")
            picked[(role, arm)] = t
            roles[t] = (role, arm)
    return roles


class BagStereo:
    """Iterate a bag's stereo frames (see the module docstring). ``preset`` ambf | dvrk | None;
    ``topics`` a topic map (YAML path or dict). ``info`` says which topics and unit were used;
    ``counts`` how many images went unpaired."""

    def __init__(self, path, preset: str | None = None, topics=None, report=None):
        self.path = str(path)
        self.reader = open_reader(path)
        self.types = {c.topic: c.msgtype for c in self.reader.connections}
        try:
            m = load_topic_map(preset, topics)
            m = resolve_rig(m, set(self.types))
            roles = resolve_roles(m, self.types, self.path)
            for t, (role, cam) in roles.items():
                if t in self.reader.unresolved:
                    raise BagError(f"{self.path}: topic {t} ({role}{'.' + cam if cam else ''}): "
                                   f"{self.reader.unresolved[t]}")
        except (TopicMapError, BagError) as exc:
            self.close()
            msg = str(exc)
            raise BagError(msg if msg.startswith(self.path) else f"{self.path}: {msg}") from None
        self.map = m
        self.asm = StereoAssembler(m, self.path, roles, report, check_values=False)
        self.info = self.asm.info
        self.counts = self.asm.counts
        self.refused = self.asm.refused      # {topic: messages refused}
        if self.reader.recovered:
            self.info["recovered"] = self.reader.recovered

    def needle_model(self) -> NeedleModel:
        return self.asm.needle_model()

    def close(self) -> None:
        try:
            self.reader.close()
        except Exception:
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def frame_count_hint(self) -> int:
        """Images on the left topic (an upper bound of the stereo frames)."""
        t = self.info["topics"]["image.left"]
        return sum(c.msgcount for c in self.reader.connections if c.topic == t)

    def __iter__(self):
        conns = [c for c in self.reader.connections if c.topic in self.asm.topic_role]
        for conn, _t, raw in self.reader.messages(connections=conns):
            try:
                out = self.asm.feed_bytes(conn.topic, raw, conn.msgtype, self.reader.deserialize)
            except BagError:
                raise
            except (AttributeError, TypeError, ValueError, KeyError, IndexError) as exc:   # fields not as its type's
                raise BagError(f"{self.path}: {conn.topic}: a {conn.msgtype} not as the type defines it (the bag's "
                               f"own definition of it?): {type(exc).__name__}: {exc}") from None
            yield from out
        try:
            out = self.asm.finish()
        except BagError:
            raise
        except (AttributeError, TypeError, ValueError, KeyError, IndexError) as exc:
            raise BagError(f"{self.path}: the last frames: {type(exc).__name__}: {exc}") from None
        yield from out
