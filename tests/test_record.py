"""``needletrack record``: a running graph to MCAP with ROS 2 schemas, read back with rosbags, and
replayed through the ``rosbag`` source: the same poses come out."""
import threading

import numpy as np
import pytest

from common.ros.bag import open_reader
from common.ros.conventions import pose_to_T, stamp_ns
from common.ros.record import record
from common.ros.synth import dataset_to_bag
from common.runtime.graph import load_graph
from common.sim.cli import main as dataset_main


@pytest.fixture(scope="module")
def ambf_bag(tmp_path_factory):
    root = tmp_path_factory.mktemp("record")
    rc = dataset_main(["generate", "--out", str(root / "ds"), "--sequences", "3", "--steps", "1", "--width", "640",
                       "--height", "480", "--seed", "6", "--randomise", "test", "--jobs", "1", "--quiet"])
    assert rc == 0
    dataset_to_bag(str(root / "ds"), str(root / "ambf.bag"), "ambf")
    return root / "ambf.bag"


def pipeline(source: dict) -> dict:
    stereo = {"left": "detector/left", "right": "detector/right", "calib": "camera/calib", "ecm": "ecm/pose"}
    return {"nodes": [
        {"id": "camera", "module": "rosbag", "outputs": ["left", "right", "measured", "truth", "calib", "eos"],
         "params": source},
        {"id": "detector", "module": "detector", "params": {"backend": "oracle"},
         "inputs": {"left": "camera/left", "right": "camera/right", "truth": "camera/truth",
                    "calib": "camera/calib"}, "outputs": ["left", "right"]},
        {"id": "ecm", "module": "ecm", "inputs": {"measured": "camera/measured", "calib": "camera/calib"},
         "outputs": ["pose"]},
        {"id": "epnp_joint", "module": "epnp", "params": {"method": "joint"}, "inputs": stereo, "outputs": ["pose"]},
    ]}


def read_poses(path, topic):
    r = open_reader(path)
    try:
        conns = [c for c in r.connections if c.topic == topic]
        return {stamp_ns(m.header): pose_to_T(m.pose) for m in
                (r.deserialize(raw, c.msgtype) for c, _, raw in r.messages(connections=conns))}
    finally:
        r.close()


@pytest.mark.graph
def test_record_then_replay_gives_the_same_poses(run_graph, ambf_bag, tmp_path):
    g = run_graph(pipeline({"path": str(ambf_bag), "preset": "ambf", "rate": 6, "loop": True}), timeout=90)
    out = str(tmp_path / "run.mcap")
    stop = threading.Event()
    result = {}
    t = threading.Thread(target=lambda: result.update(record(load_graph(g.path), out, stop=stop)), daemon=True)
    t.start()
    g.collect("epnp_joint/pose", 20, timeout=120)    # ~3 s: the calibration goes out once a second
    stop.set()
    t.join(timeout=30)
    assert result["messages"] > 0 and result["topic_map"]
    topics = result["topics"]
    for name in ("/camera/left/image_raw", "/camera/right/image_raw", "/camera/calib/left/camera_info",
                 "/tf_static", "/camera/measured", "/camera/truth/needle", "/detector/left", "/epnp_joint/pose",
                 "/ecm/pose"):
        assert topics.get(name, 0) >= 1, (name, topics)
    # a ROS 2 bag as rosbags sees it: schemas and types
    r = open_reader(out)
    types = {c.topic: c.msgtype for c in r.connections}
    r.close()
    assert types["/camera/left/image_raw"] == "sensor_msgs/msg/Image"
    assert types["/detector/left"] == "needletrack_msgs/msg/Keypoints"
    assert types["/epnp_joint/pose/with_covariance"] == "geometry_msgs/msg/PoseWithCovarianceStamped"
    recorded = read_poses(out, "/epnp_joint/pose")
    assert len(recorded) >= 2
    g.stop()
    # replay the recording through the rosbag source with the topic map written beside it
    g2 = run_graph(pipeline({"path": out, "topics": result["topic_map"], "rate": 6, "loop": True}), timeout=90)
    replayed = g2.collect("epnp_joint/pose", 12, timeout=120)
    matched = 0
    # The first replayed frame is left out: the recording starts mid-stream, and its first
    # frame can be on record before that frame's ground truth, so on replay the oracle draws it
    # from a neighbouring frame's truth (seen in about 1 run in 4, always frame 0 of the replay).
    for p in replayed[1:]:
        # a pose flagged ambiguous is one of near-equal solutions: a last-bit difference in the
        # replayed calibration may pick the other (its covariance spans both)
        if p.stamp_ns in recorded and not p.ambiguous:
            assert np.abs(p.T_ecm_needle - recorded[p.stamp_ns]).max() < 1e-9
            matched += 1
    assert matched >= 3, (matched, sorted(recorded), [p.stamp_ns for p in replayed])
