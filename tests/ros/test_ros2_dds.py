"""ROS 2 without a bridge, end to end against real ROS 2 nodes: an rclpy node (rmw_fastrtps_cpp,
tests/ros_peer.py) publishes a dataset's stereo images (left with ROS's default QoS, right with
the sensor-data QoS), camera_info, positions-only ECM joints and the needle's pose on the dVRK
topics; the graph ``ros2`` (transport dds) -> oracle detector -> ecm (joints through the arm
model) -> EPnP -> ``ros2_out`` (transport dds) sends the poses back, which the rclpy node
receives as ``geometry_msgs/PoseStamped`` in frame ``ECM`` (and PoseWithCovarianceStamped). Their
values equal the native graph's (``replay`` of the same folder, same nodes) on the same frames.

Every DDS process runs in a network namespace of the test's own with only loopback up (DDS
discovery multicasts); the native graph runs on 127.0.0.1 outside it."""
from __future__ import annotations

import json
import sys
import time

import numpy as np
import pytest
from rospeer import ENV, PEER, LoopbackNamespace, need_rclpy

from common.cli import dataset_main
from common.data.dataset import Dataset
from common.geometry.transforms import inv_T, pose_error
from common.bench.ros_bench import pose_pipeline
from common.ros.conventions import pose_to_T, ros_covariance

RIG = "jhu_daVinci"


@pytest.fixture(scope="module")
def ds(tmp_path_factory):
    path = tmp_path_factory.mktemp("dds") / "ds"
    rc = dataset_main(["generate", "--out", str(path), "--sequences", "2", "--steps", "2", "--width", "320",
                       "--height", "240", "--seed", "8", "--randomise", "none", "--jobs", "1", "--quiet"])
    assert rc == 0
    return Dataset(path)


def dds_graph(ds) -> dict:
    tmap = {"preset": "dvrk", "needle_pose": "/needle/measured_cp", "ecm": ds.arm.to_dict(),
            "registration": {c: ds.rig[c].T_ecm_cam.tolist() for c in ("left", "right")}}
    return {"nodes": pose_pipeline(
        {"id": "camera", "module": "ros2", "outputs": ["left", "right", "measured", "truth", "calib"],
         "params": {"preset": "dvrk", "rig": RIG, "topics": tmap, "transport": "dds"}},
        {"id": "out", "module": "ros2_out", "inputs": {"pose": "epnp_joint/pose"},
         "params": {"transport": "dds", "frame": "ecm"}})}


def native_poses(ds, tmp_path) -> dict:
    """frame index -> PoseEstimate of the native graph (replay of the folder, looping, same nodes;
    a frame a node skips at start-up comes again)."""
    from graphtools import free_port

    from common.evaluation.pipeline_graph import GraphRun
    from common.runtime.graph import output_key
    from common.runtime.messages import PoseEstimate, decode
    doc = {"graph": f"native{free_port()}", "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{free_port()}"]},
           "nodes": pose_pipeline({"id": "camera", "module": "replay",
                              "outputs": ["left", "right", "joints", "measured", "truth", "calib", "eos"],
                              "params": {"path": str(ds.path), "rate": 4.0, "loop": True}})}
    got: dict = {}
    with open(tmp_path / "native.log", "w") as log, GraphRun(doc, log, source="camera") as run:
        run.start_consumers()
        sub = run.client_session().declare_subscriber(
            output_key(doc["graph"], "epnp_joint", "pose"),
            lambda s: got.setdefault(decode(s.payload.to_bytes(), PoseEstimate).seq % len(ds),   # seq: frame + loop
                                     decode(s.payload.to_bytes(), PoseEstimate)))
        run.start_source()
        deadline = time.monotonic() + 120
        while len(got) < len(ds) and time.monotonic() < deadline:
            time.sleep(0.1)
        sub.undeclare()
    assert len(got) == len(ds), f"native graph: poses for frames {sorted(got)} of {len(ds)}"
    return got


@pytest.mark.netns
def test_rclpy_nodes_in_poses_out_over_dds(ds, tmp_path):
    need_rclpy()
    from graphtools import prepare_graph
    native = native_poses(ds, tmp_path)
    graph = prepare_graph(dds_graph(ds), tmp_path / "graph")
    out = tmp_path / "peer.json"
    with LoopbackNamespace("rospeerE") as ns:
        launcher = ns.popen([sys.executable, "-m", "common.cli", "launch", graph], tmp_path / "launch.log")
        peer = ns.popen([sys.executable, PEER, "live", ds.path, out, "--rig", RIG, "--frames", len(ds),
                         "--timeout", 150], tmp_path / "peer.log", env=ENV)
        try:
            peer.wait(200)
        finally:
            logs = (tmp_path / "peer.log").read_text()[-3000:] + (tmp_path / "launch.log").read_text()[-6000:]
        assert peer.returncode == 0, logs
        assert launcher.poll() is None, "the graph died:\n" + logs
    res = json.loads(out.read_text())
    assert res["subscriptions"]["left"] >= 1 and res["subscriptions"]["right"] >= 1, res["subscriptions"]
    from ros_peer import frame_of
    seen = set()
    for p in res["poses"]:
        assert p["frame_id"] == "ECM"
        k = frame_of(p["stamp_ns"], ds)                  # the image's stamp comes back in the header
        assert k >= 0, p["stamp_ns"]
        seen.add(k)

        class _Pose:
            position = type("P", (), dict(zip("xyz", p["position"])))
            orientation = type("Q", (), dict(zip("xyzw", p["orientation"])))
        T = pose_to_T(_Pose)
        err = pose_error(T, np.asarray(native[k].T_ecm_needle, float))
        assert err[0] < 1e-9 and err[1] < 1e-8, (k, err)
        fr = ds[k]
        truth = pose_error(T, inv_T(fr.T_world_ecm) @ fr.T_world_needle)
        assert truth[0] < 1e-6 and truth[1] < 1e-5, (k, truth)
    assert seen == set(range(len(ds))), f"poses came back for frames {sorted(seen)} of {len(ds)}: {logs}"
    # PoseWithCovarianceStamped: ROS's covariance of the native estimate's (ros_covariance, frame ECM)
    assert res["with_covariance"], "no PoseWithCovarianceStamped came back"
    for p in res["with_covariance"]:
        k = frame_of(p["stamp_ns"], ds)
        assert p["frame_id"] == "ECM" and native[k].covariance is not None
        np.testing.assert_allclose(p["position"], np.asarray(native[k].T_ecm_needle)[:3, 3], rtol=0, atol=1e-9)
        ref = ros_covariance(np.asarray(native[k].covariance, float), np.eye(3), 1.0).reshape(-1)
        np.testing.assert_allclose(p["covariance"], ref, rtol=1e-6, atol=1e-15)


LOCALHOST_CONFIG = ('<CycloneDDS><Domain><General><Interfaces><NetworkInterface name="lo"/></Interfaces>'
                    '<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto'
                    '</ParticipantIndex><Peers><Peer address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>')
PROBE = """
import sys, time
from common.ros.dds import DdsLink
got = []
link = DdsLink(0, sys.argv[1])
link.subscribe("/needletrack/probe", "sensor_msgs/msg/JointState", lambda cdr, ts: got.append(cdr))
t_end = time.monotonic() + 30
while not got and time.monotonic() < t_end:
    time.sleep(0.05)
link.close()
print(len(got), got[0].hex() if got else "")
"""


@pytest.mark.netns
def test_localhost_only_discovery_as_docs_say(tmp_path):
    """docs/ros.md: an rclpy node with ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST, on a loopback
    without the MULTICAST flag (as a host has it), is found by a DDS link with the documented
    localhost-only Cyclone config (unicast peers). Its positions-only JointState arrives as the
    CDR written, without the slack ``serialize_message`` returns (docs/ros.md)."""
    need_rclpy()
    with LoopbackNamespace("rospeerL", multicast=False) as ns:
        talker = ns.popen([sys.executable, PEER, "talk", "/needletrack/probe", 40], tmp_path / "talker.log",
                          env=dict(ENV, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
        import subprocess
        res = subprocess.run(ns.argv([sys.executable, "-c", PROBE, LOCALHOST_CONFIG]), capture_output=True,
                             text=True, env=ENV, timeout=120)
        talker.kill()
    assert res.returncode == 0, res.stderr[-2000:]
    n, cdr = res.stdout.split()[-2:] if len(res.stdout.split()) >= 2 else (res.stdout.strip() or "0", "")
    assert int(n) >= 1, (res.stdout, (tmp_path / "talker.log").read_text()[-2000:])
    from common.ros.cdr import decode, encode, fastcdr_estimate
    msg = decode(bytes.fromhex(cdr), "sensor_msgs/msg/JointState")
    assert list(msg.name) == ["outer_yaw"] and list(msg.position) == [0.25] and len(msg.velocity) == 0
    assert len(bytes.fromhex(cdr)) == len(encode(msg)) < 4 + fastcdr_estimate(msg, msg.__msgtype__)


def test_a_bad_dds_config_is_a_clear_error():
    """A Cyclone config that cannot be applied fails the link with DdsError naming the domain and
    Cyclone's reason (the nodes turn it into their configuration error)."""
    from rospeer import need_cyclonedds
    need_cyclonedds()
    import subprocess
    code = ("from common.ros.dds import DdsError, DdsLink\n"
            "try:\n    DdsLink(3, '<CycloneDDS><Domain><General><Interfaces><NetworkInterface name=\"nosuch0\"/>"
            "</Interfaces></General></Domain></CycloneDDS>')\nexcept DdsError as e:\n    print('DdsError:', e)\n")
    with LoopbackNamespace("rospeerC") as ns:
        res = subprocess.run(ns.argv([sys.executable, "-c", code]), capture_output=True, text=True, env=ENV,
                             timeout=120)
    assert "DdsError: cannot join DDS domain 3" in res.stdout, res.stdout + res.stderr
    assert "nosuch0" in res.stdout and "nosuch0" in res.stderr      # the config, and Cyclone's reason
