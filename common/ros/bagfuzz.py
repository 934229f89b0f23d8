"""Damaged bag files for the readers (``needletrack bench fuzz --bags N``, tests/ros/test_bag_errors.py):
a small synthetic stereo recording (an MCAP written the way ``needletrack record`` writes, zstd
chunks, and a ROS 1 bag), then copies of it cut short, with a chunk's bytes overwritten, a CRC
changed, a record length made absurd (4 GiB, 2^63), bit flips, or the summary and footer
dropped (an unfinished recording). ``fuzz_bags`` reads each through ``BagStereo`` to the end:
it must give its frames (an unfinished file: those of its complete chunks, said in
``info["recovered"]``) or raise ``BagError``; anything else is a crash.
"""
from __future__ import annotations

import os
import random
import struct
import tempfile
import time
from dataclasses import dataclass, field

import numpy as np

from common.frames import CAMERAS

MCAP_KINDS = ("truncated", "chunk_bytes", "chunk_crc", "length_4g", "length_huge", "bit_flips", "unfinished")
ROS1_KINDS = ("truncated", "bit_flips", "length_4g")


def topic_map(rig=None) -> dict:
    """The topic map of ``synthetic_bag``'s topics."""
    from common.geometry.camera import StereoRig
    rig = rig or StereoRig.default()
    return {"images": {"left": "/cam/left/image_raw", "right": "/cam/right/image_raw"},
            "camera_info": {"left": "/cam/left/camera_info", "right": "/cam/right/camera_info"},
            "ecm_pose": "/ecm/pose", "unit": "m",
            "registration": {c: rig[c].T_ecm_cam.tolist() for c in CAMERAS}}


def synthetic_bag(path: str, frames: int = 6, ros: int = 2, size=(64, 48), seed: int = 0, chunk_every: int = 1,
                  nan_pose_at: int | None = None, nan_info_at: int | None = None, last_right_size=None,
                  finish: bool = True, extra=None) -> str:
    """A stereo bag of random images with camera_info and an ECM pose per frame, 100 ms apart:
    ros 2 a bare MCAP written by ``McapRos2Writer`` (a chunk closed every ``chunk_every`` frames;
    ``finish=False`` leaves it unfinished, as a killed recorder), ros 1 a ``.bag``. NaN in the
    ECM pose or K of frame ``nan_*_at``; ``last_right_size`` (w, h) for the last right image;
    ``extra(writer)`` adds topics. Returns ``path``."""
    from common.ros import build
    from common.ros.types import typestore
    st = typestore(ros)
    rng = np.random.default_rng(seed)
    w, h = size
    K = np.array([[50.0, 0, w / 2], [0, 50.0, h / 2], [0, 0, 1]])
    if ros == 2:
        from common.ros.record import McapRos2Writer
        out = McapRos2Writer(path)
        put = out.write
    else:
        from common.ros.synth import BagWriter
        out = BagWriter(path, 1, "")

        def put(topic, msg, t):
            out.write(topic, msg, t)
    if extra is not None:
        extra(out)
    for i in range(frames):
        t = 10**18 + i * 100_000_000
        for c in CAMERAS:
            ww, hh = last_right_size if (c == "right" and i == frames - 1 and last_right_size) else (w, h)
            Ki = K.copy()
            if nan_info_at == i:
                Ki[0, 0] = np.nan
            put(f"/cam/{c}/camera_info", build.camera_info(st, t, Ki, [0.0] * 5, (w, h)), t)
            put(f"/cam/{c}/image_raw", build.image(st, t, rng.integers(0, 255, (hh, ww, 3), np.uint8), "bgr8"), t)
        T = np.eye(4)
        T[2, 3] = 0.1
        if nan_pose_at == i:
            T[0, 3] = np.nan
        put("/ecm/pose", build.make(st, "geometry_msgs/msg/PoseStamped", header=build.header(st, t, "world"),
                                    pose=build.pose(st, T)), t)
        if ros == 2 and (i + 1) % chunk_every == 0:
            out._flush()
    if ros == 2 and not finish:
        out._flush()
        out.f.close()
    else:
        out.close()
    return path


def mcap_records(data: bytes) -> list:
    """(opcode, offset, length) of an MCAP file's top-level records (after the magic)."""
    out, off = [], 8
    while off + 9 <= len(data):
        op, ln = data[off], struct.unpack_from("<Q", data, off + 1)[0]
        out.append((op, off, ln))
        if op == 0x02 or off + 9 + ln > len(data):      # the footer, or a record cut short
            break
        off += 9 + ln
    return out


def damage_mcap(data: bytes, kind: str, rng: random.Random) -> bytes:
    """A copy of an MCAP file damaged as ``kind`` (MCAP_KINDS)."""
    recs = mcap_records(data)
    chunks = [r for r in recs if r[0] == 0x06] or recs
    b = bytearray(data)
    op, off, ln = rng.choice(chunks)
    if kind == "truncated":
        return bytes(b[:rng.randrange(8, len(b))])
    if kind == "chunk_bytes":              # inside the compressed data (after 9 + 36 bytes of header)
        a = off + 9 + min(ln - 1, 45 + rng.randrange(max(1, ln - 45)))
        n = rng.randrange(1, 32)
        b[a:a + n] = bytes(rng.randrange(256) for _ in range(len(b[a:a + n])))
        return bytes(b)
    if kind == "chunk_crc":
        struct.pack_into("<I", b, off + 9 + 24, rng.randrange(2**32))
        return bytes(b)
    if kind in ("length_4g", "length_huge"):
        op, off, ln = rng.choice(recs)
        struct.pack_into("<Q", b, off + 1, 4 * 2**30 + rng.randrange(64) if kind == "length_4g" else 2**63 - 1)
        return bytes(b)
    if kind == "bit_flips":
        for _ in range(rng.randrange(1, 8)):
            i = rng.randrange(len(b))
            b[i] ^= 1 << rng.randrange(8)
        return bytes(b)
    if kind == "unfinished":               # everything from the data end on dropped, a chunk maybe cut
        end = next((o for op_, o, _ in recs if op_ == 0x0F), len(b))
        cut = off + rng.randrange(ln + 9) if rng.random() < 0.5 else end
        return bytes(b[:min(cut, end)])
    raise ValueError(f"unknown kind {kind!r}")


def damage_ros1(data: bytes, kind: str, rng: random.Random) -> bytes:
    """A copy of a ROS 1 bag damaged as ``kind`` (ROS1_KINDS)."""
    b = bytearray(data)
    if kind == "truncated":
        return bytes(b[:rng.randrange(13, len(b))])
    if kind == "bit_flips":
        for _ in range(rng.randrange(1, 8)):
            i = rng.randrange(13, len(b))
            b[i] ^= 1 << rng.randrange(8)
        return bytes(b)
    if kind == "length_4g":                # a record's header or data length
        offs, off = [], 13
        while off + 4 <= len(b):
            offs.append(off)
            hl = struct.unpack_from("<I", b, off)[0]
            if off + 4 + hl + 4 > len(b):
                break
            offs.append(off + 4 + hl)
            dl = struct.unpack_from("<I", b, off + 4 + hl)[0]
            off += 8 + hl + dl
        struct.pack_into("<I", b, rng.choice(offs), 0xFFFFFFFF - rng.randrange(64))
        return bytes(b)
    raise ValueError(f"unknown kind {kind!r}")


@dataclass
class BagFuzzResult:
    files: int = 0
    read: int = 0                  # read to the end (frames, maybe fewer)
    recovered: int = 0             # of those, recovered from an unfinished file
    refused: int = 0               # BagError
    crashes: int = 0
    first_crash: str = ""
    kinds: dict = field(default_factory=dict)
    seconds: float = 0.0


def read_all(path: str, tm: dict) -> tuple[int, str | None]:
    """Frames ``BagStereo`` gives from ``path`` (and its ``recovered`` note); BagError passes."""
    from common.ros.bag import BagStereo
    from common.ros.convert import sample_fault
    with BagStereo(path, topics=tm) as src:
        n = 0
        for s in src:
            sample_fault(s, src.info["topics"])
            n += 1
        return n, src.info.get("recovered")


def fuzz_bags(n: int, seed: int = 0, log=print) -> BagFuzzResult:
    """``n`` damaged copies of each base bag (MCAP and ROS 1) read through ``BagStereo``."""
    from common.ros.bag import BagError
    rng = random.Random(seed)
    r = BagFuzzResult()
    t0 = time.perf_counter()
    tm = topic_map()
    with tempfile.TemporaryDirectory(prefix="needletrack-bagfuzz-") as d:
        bases = {"mcap": (synthetic_bag(os.path.join(d, "base.mcap"), 8, 2, seed=seed), MCAP_KINDS, damage_mcap),
                 "ros1": (synthetic_bag(os.path.join(d, "base.bag"), 8, 1, seed=seed), ROS1_KINDS, damage_ros1)}
        for name, (path, kinds, damage) in bases.items():
            data = open(path, "rb").read()
            for i in range(n):
                kind = kinds[i % len(kinds)]
                bad = os.path.join(d, f"bad{os.path.splitext(path)[1]}")
                with open(bad, "wb") as f:
                    f.write(damage(data, kind, rng))
                r.files += 1
                key = f"{name}.{kind}"
                r.kinds[key] = r.kinds.get(key, 0) + 1
                try:
                    _, recovered = read_all(bad, tm)
                    r.read += 1
                    r.recovered += recovered is not None
                except BagError:
                    r.refused += 1
                except Exception as exc:
                    r.crashes += 1
                    r.first_crash = r.first_crash or f"{key}: {type(exc).__name__}: {exc}"
                    log(f"  bag crash {key}: {type(exc).__name__}: {exc}")
    r.seconds = time.perf_counter() - t0
    return r
