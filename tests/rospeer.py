"""What the tests that talk to real ROS 2 code share: the rclpy peer (tests/ros_peer.py, run as
its own process), the project's messages as plain data, and network namespaces for DDS.

A missing rclpy (the ``test`` extra not installed) or a kernel that refuses network namespaces
skips these tests, with the reason printed, and fails them under CI (``CI`` set: CI installs the
extra and allows namespaces)."""
from __future__ import annotations

import base64
import dataclasses
import json
import os
import secrets
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent
PEER = REPO / "tests" / "ros_peer.py"
ENV = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")


def skip_or_fail(reason: str):
    print(reason)
    if os.environ.get("CI"):
        pytest.fail(reason)
    pytest.skip(reason)


def need_rclpy() -> None:
    """rclpy with the message packages, checked in a subprocess (rclpy never loads here)."""
    res = subprocess.run([sys.executable, "-c", "import rclpy, sensor_msgs.msg, geometry_msgs.msg"],
                         capture_output=True, text=True, env=ENV, timeout=120)
    if res.returncode != 0:
        skip_or_fail("rclpy is not installed (pip install -e '.[test]'): "
                     + (res.stderr.strip().splitlines() or ["?"])[-1])


def need_cyclonedds() -> None:
    try:
        import cyclonedds  # noqa: F401
    except ImportError as exc:
        skip_or_fail(f"cyclonedds is not installed (pip install -e '.[test]'): {exc}")


def plain(msg):
    """A rosbags message as plain data (tests/ros_peer.py's form: uint8 arrays as base64)."""
    if dataclasses.is_dataclass(msg):
        return {f.name: plain(getattr(msg, f.name)) for f in dataclasses.fields(msg) if not f.name.startswith("__")}
    if isinstance(msg, np.ndarray):
        if msg.dtype == np.uint8:
            return {"b64": base64.b64encode(msg.tobytes()).decode()}
        return msg.tolist()
    if isinstance(msg, (list, tuple)):
        return [plain(x) for x in msg]
    if isinstance(msg, np.generic):
        return msg.item()
    return msg


def rclpy_bytes(items: list) -> list:
    """Run the peer's ``bytes`` command on ``[{"type", "values", "cdr"}]``: serialisation only (no
    ``rclpy.init``, no participant), still in a loopback-only namespace like every rclpy process."""
    with LoopbackNamespace("rospeerB", multicast=False) as ns:
        res = subprocess.run(ns.argv([sys.executable, str(PEER), "bytes"]), input=json.dumps(items),
                             capture_output=True, text=True, env=ENV, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout)


def _ip(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)


class LoopbackNamespace:
    """A network namespace with only loopback up, multicast on it and a route for 224.0.0.0/4
    (``multicast=False``: loopback as Linux sets it up, without the MULTICAST flag): DDS
    discovery stays inside. ``popen`` runs a command in it; ``close`` deletes it."""

    def __init__(self, tag: str = "rospeer", multicast: bool = True):
        self.name = f"{tag}{os.getpid()}x{secrets.token_hex(2)}"
        self.procs: list = []
        res = _ip("netns", "add", self.name)
        if res.returncode != 0:
            skip_or_fail(f"the kernel refuses a network namespace here (ip netns add: {res.stderr.strip()})")
        try:
            steps = [("link", "set", "lo", "up")]
            if multicast:
                steps += [("link", "set", "lo", "multicast", "on"), ("route", "add", "224.0.0.0/4", "dev", "lo")]
            for args in steps:
                res = _ip("-n", self.name, *args)
                assert res.returncode == 0, f"ip -n {self.name} {' '.join(args)}: {res.stderr.strip()}"
        except BaseException:
            self.close()
            raise

    def argv(self, argv: list) -> list:
        return ["ip", "netns", "exec", self.name, *map(str, argv)]

    def popen(self, argv: list, log: Path, env: dict | None = None) -> subprocess.Popen:
        with open(log, "wb") as f:
            p = subprocess.Popen(self.argv(argv), cwd=REPO, env=env or ENV, stdout=f, stderr=subprocess.STDOUT,
                                 start_new_session=True)
        self.procs.append(p)
        return p

    def close(self) -> None:
        import signal
        for p in self.procs:
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                    p.wait(20)
                except (ProcessLookupError, subprocess.TimeoutExpired):
                    try:
                        os.killpg(p.pid, signal.SIGKILL)
                    except ProcessLookupError:
                        pass
                    p.wait(10)
        _ip("netns", "del", self.name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


_SIZES = {"bool": 1, "byte": 1, "char": 1, "int8": 1, "uint8": 1, "int16": 2, "uint16": 2, "int32": 4,
          "uint32": 4, "float32": 4, "int64": 8, "uint64": 8, "float64": 8}


def cdr_padding(msg) -> tuple[set, int]:
    """(padding, length) of ``msg`` (a rosbags message) in plain little-endian CDR, worked out
    independently of the encoder (a walk over the type definitions): the offsets in the CDR
    bytes (4-byte encapsulation header included) of the alignment padding, bytes that carry no
    value, and the length."""
    from common.ros.types import typestore
    st = typestore(2)
    pad: set = set()
    pos = 0

    def align(n: int) -> None:
        nonlocal pos
        k = (-pos) % n
        pad.update(range(4 + pos, 4 + pos + k))
        pos += k

    def node(nd, v) -> None:
        nonlocal pos
        kind, desc = nd
        k = int(kind)
        if k == 1:
            name = desc[0]
            if name == "string":
                align(4)
                pos += 4 + len(v.encode()) + 1
            else:
                align(_SIZES[name])
                pos += _SIZES[name]
        elif k == 2:
            message(desc, v)
        else:
            if k == 4:
                align(4)
                pos += 4
            for x in v:
                node(desc[0], x)

    def message(typename: str, v) -> None:
        for name, nd in st.fielddefs[typename][1]:
            node(nd, getattr(v, name))
    message(msg.__msgtype__, msg)
    return pad, 4 + pos
