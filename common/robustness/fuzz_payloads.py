"""What ``needletrack bench fuzz`` sends (``common.robustness.fuzz``): the clean stream (the
oracle's still needle seen by the default rig while the ECM yaws, through the library's nodes
offline) and the poison payloads made from its messages (``KINDS``)."""
from __future__ import annotations

import dataclasses
import random
from typing import Optional

import msgpack
import numpy as np

from common.frames import CAMERAS
from common.runtime.messages import (
    Calibration,
    CameraImage,
    EcmJoints,
    GroundTruth,
    InstrumentState,
    NoPoseNotice,
    PoseEstimate,
    encode,
)

FRAME_HZ = 30.0


# ====================================================================== the clean stream

class CleanStream:
    """Messages of frame ``seq`` per graph key (``camera/left``, ``ecm/pose``, ...), built once
    for ``period`` frames from the library nodes offline and re-stamped per seq."""

    def __init__(self, period: int = 16, seed: int = 0, image_size=(1920, 1080)):
        from common.geometry.camera import StereoRig
        from common.geometry.ecm_kinematics import EcmArm
        from common.geometry.needle import NeedleModel
        from common.geometry.oracle import random_needle_pose
        from common.geometry.transforms import make_T, rotvec_to_R
        from common.runtime.node import node_class
        EcmNode, DetectorNode, EpnpNode, TriangulateNode, FusionNode = map(
            node_class, ("ecm", "detector", "epnp", "triangulate", "fusion"))
        w, h = image_size
        rig, model = StereoRig.default(w, h), NeedleModel()
        arm = EcmArm(make_T(rotvec_to_R([0, 0, 0.2]), [0.1, 0.0, 0.3]), 0.01, 0.02)
        self.calib = Calibration(0, np.array([w, h]), rig.to_dict(), model.to_dict(), arm.to_dict(), "fuzz")
        rng = np.random.default_rng(seed)
        T_en = random_needle_pose(rng, rig, model, max_offaxis=0.15)
        T_wn = arm.T_world_ecm([0, 0, 0.05, 0]) @ T_en
        import cv2
        img = np.full((h, w, 3), 90, np.uint8)
        jpeg = cv2.imencode(".jpg", img)[1].tobytes()
        ecm = EcmNode.offline({}, wired=["joints", "calib"])
        det = DetectorNode.offline({"backend": "oracle", "noise_px": 0.2, "seed": seed},
                                   wired=["truth", "calib"])
        stereo = ["left", "right", "calib", "ecm"]
        poses = {"pnp_average": EpnpNode.offline({"method": "average"}, wired=stereo),
                 "pnp_joint": EpnpNode.offline({"method": "joint"}, wired=stereo),
                 "triangulation": TriangulateNode.offline({}, wired=stereo)}
        fusion = FusionNode.offline({}, wired=["pose", "ecm", "truth"])
        for n in (ecm, det, *poses.values()):
            n.deliver("calib", self.calib)
        self.frames = []
        for i in range(period):
            k = i % 8 if i % 8 < 5 else 8 - i % 8
            q = np.array([-0.1 + 0.05 * k, 0.0, 0.05, 0.0])
            T_we = arm.T_world_ecm(q)
            stamp = int(i * 1e9 / FRAME_HZ)
            f = {"camera/joints": EcmJoints(i, stamp, q),
                 "camera/truth": GroundTruth(i, stamp, sequence=0, step=i, ecm_joints=q, T_world_ecm=T_we,
                                             T_world_needle=T_wn)}
            for cam in CAMERAS:
                f[f"camera/{cam}"] = CameraImage(cam, i, stamp, w, h, "jpeg", jpeg)
            f["camera/instruments"] = InstrumentState("psm1", i, stamp, T_wn @ make_T(np.eye(3), [0, 0, 0.01]), 0.06, True)
            for node, key, msg in ((ecm, "joints", f["camera/joints"]), (det, "truth", f["camera/truth"])):
                node.published.clear()
                node.deliver(key, msg)
            f["ecm/pose"] = ecm.published[-1][1]
            kps = {o: m for o, m in det.published}
            f["detector_left/left"], f["detector_right/right"] = kps["left"], kps["right"]
            for name, node in poses.items():
                node.published.clear()
                node.deliver("ecm", f["ecm/pose"])
                node.deliver("left", kps["left"])
                node.deliver("right", kps["right"])
                out = [m for o, m in node.published if o == "pose"]
                if out:
                    f[f"{name}/pose"] = out[-1]
            # the refine node's and the tracker's: the joint pose (the tracker's of a needle at rest)
            # on even frames; on odd ones neither gives a pose and each says so (NoPoseNotice)
            if i % 2:
                f["refine/no_pose"] = NoPoseNotice(i, stamp, "refined", "too_few_points")
                f["tracker/no_pose"] = NoPoseNotice(i, stamp, "tracked", "no_track")
            elif "pnp_joint/pose" in f:
                f["refine/pose"] = dataclasses.replace(f["pnp_joint/pose"], method="refined")
                f["tracker/pose"] = dataclasses.replace(f["pnp_joint/pose"], method="tracked", mode="rest")
            fusion.published.clear()
            fusion.deliver("ecm", f["ecm/pose"])
            fusion.deliver("truth", f["camera/truth"])
            if "pnp_joint/pose" in f:
                fusion.deliver("pose", f["pnp_joint/pose"])
            if fusion.published:
                f["fusion/pose"] = fusion.published[-1][1]
            self.frames.append(f)
        self.aliases = {"epnp_average/pose": "pnp_average/pose", "epnp_joint/pose": "pnp_joint/pose",
                        "triangulate/pose": "triangulation/pose"}

    def message(self, key: str, seq: int, epoch: Optional[int] = None):
        """The clean message on ``key`` (a graph key) for frame ``seq``; None if there is none."""
        if key.endswith("/calib"):
            return self.calib
        f = self.frames[seq % len(self.frames)]
        msg = f.get(self.aliases.get(key, key))
        if msg is None:
            return None
        kw = {"seq": seq, "stamp_ns": int(seq * 1e9 / FRAME_HZ)}
        if hasattr(msg, "epoch"):
            kw["epoch"] = epoch
        if isinstance(msg, PoseEstimate) and msg.T_world_needle is not None:
            kw["T_world_needle"] = msg.T_world_needle.copy()
        return dataclasses.replace(msg, **kw)


# ====================================================================== poison

KINDS = ("random_bytes", "truncated", "bit_flips", "type_confused", "missing_field", "extra_field",
         "wrong_schema", "non_finite", "huge", "far_seq", "negative_seq", "new_epoch", "epoch_run")


def _ext_keep(code, data):
    return msgpack.ExtType(code, data)


def _random_value(rng: random.Random):
    return rng.choice([None, True, 0, -1, 2 ** 63, 2 ** 64 - 1, -2 ** 63, 1.5, float("nan"), float("inf"),
                       -float("inf"), 1e300, "", "x" * 1000, b"\x00" * 7, [], [1, "a"], [[1.0, 2.0], [3.0]],
                       {"a": 1}, {1: 2}, [[float("nan")] * 2] * 5, msgpack.ExtType(1, b"\x92\xa7float64\x91\xcf"
                       + (2 ** 40).to_bytes(8, "big")), msgpack.ExtType(7, b"zz")])


def poison(msg, kind: str, rng: random.Random, np_rng: np.random.Generator) -> bytes:
    """One poison payload of ``kind`` made from the clean message ``msg``."""
    payload = encode(msg)
    if kind == "random_bytes":
        return bytes(np_rng.integers(0, 256, rng.randint(0, 2048), dtype=np.uint8))
    if kind == "truncated":
        return payload[:rng.randint(0, max(0, len(payload) - 1))]
    if kind == "bit_flips":
        b = bytearray(payload[:4096]) if len(payload) > 4096 and rng.random() < 0.5 else bytearray(payload)
        for _ in range(rng.randint(1, 8)):
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
        return bytes(b)
    if kind in ("type_confused", "missing_field", "extra_field", "wrong_schema"):
        d = msgpack.unpackb(payload, raw=False, ext_hook=_ext_keep, strict_map_key=False)
        body = d["body"]
        if kind == "type_confused":
            body[rng.choice(list(body))] = _random_value(rng)
        elif kind == "missing_field":
            body.pop(rng.choice(list(body)), None)
        elif kind == "extra_field":
            body[rng.choice(["zzz", "seq2", 7])] = _random_value(rng)
        else:
            r = rng.random()
            if r < 0.3:
                d["schema"] = rng.choice(["needletrack.PoseEstimate", "needletrack.Calibration", "x", 5])
            elif r < 0.6:
                d["version"] = rng.choice([0, 2, "1", None])
            else:
                d["body"] = _random_value(rng)
        return msgpack.packb(d, use_bin_type=True)
    m = dataclasses.replace(msg)
    fields = {f.name: getattr(m, f.name) for f in dataclasses.fields(m)}
    if kind in ("non_finite", "huge"):
        arrays = [k for k, v in fields.items() if isinstance(v, np.ndarray) and v.dtype.kind == "f" and v.size]
        floats = [k for k, v in fields.items() if isinstance(v, float)]
        dicts = [k for k, v in fields.items() if isinstance(v, dict)]
        bad = rng.choice([float("nan"), float("inf"), -float("inf")]) if kind == "non_finite" else \
            rng.choice([1e300, -1e300, 1e12, 3.4e38])
        choice = rng.random()
        if arrays and choice < 0.6:
            k = rng.choice(arrays)
            a = fields[k].copy()
            if kind == "huge" and rng.random() < 0.3:
                a = np.resize(a, (10 ** 6,) + a.shape[1:]) if a.ndim else a
            else:
                a.flat[rng.randrange(a.size)] = bad
            setattr(m, k, a)
        elif dicts and choice < 0.8:                       # nested (Calibration, GroundTruth maps)
            k = rng.choice(dicts)
            d = {kk: (dict(v) if isinstance(v, dict) else v) for kk, v in fields[k].items()}
            kk = rng.choice(list(d))
            if isinstance(d[kk], dict) and d[kk]:
                d[kk][rng.choice(list(d[kk]))] = bad
            else:
                d[kk] = bad if rng.random() < 0.5 else [bad, 1.0]
            setattr(m, k, d)
        elif floats:
            setattr(m, rng.choice(floats), bad)
        elif isinstance(m, CameraImage):
            m.width, m.height = rng.choice([(10 ** 9, 1080), (0, 0), (20000, 20000), (-5, 3)])
        else:
            ints = [k for k, v in fields.items() if isinstance(v, int) and not isinstance(v, bool)]
            if ints:
                setattr(m, rng.choice(ints), rng.choice([2 ** 64 - 1, 2 ** 63, -2 ** 63]))
        return _encode_any(m)
    if kind == "far_seq" and hasattr(m, "seq"):
        m.seq = rng.choice([2 ** 62, 2 ** 63 - 1, m.seq + 10 ** 6, rng.randrange(2 ** 40, 2 ** 62)])
    elif kind == "negative_seq" and hasattr(m, "seq"):
        m.seq = -rng.randint(1, 2 ** 40)
    elif kind in ("new_epoch", "epoch_run") and hasattr(m, "epoch"):
        m.epoch = rng.randrange(1, 2 ** 56)
    return _encode_any(m)


def _encode_any(m) -> bytes:
    try:
        return encode(m)
    except (TypeError, ValueError, OverflowError):      # not encodable as such: the raw body
        body = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in m.to_body().items()}
        try:
            return msgpack.packb({"schema": m.SCHEMA, "version": m.VERSION, "body": body}, use_bin_type=True)
        except (TypeError, ValueError, OverflowError):
            return b"\xc1"
