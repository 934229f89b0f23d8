"""``needletrack record``: a running graph to MCAP with ROS 2 schemas, read back with rosbags, and
replayed through the ``rosbag`` source: the same poses come out."""
import threading

import numpy as np
import pytest

from common.cli import dataset_main
from common.ros.bag import open_reader
from common.ros.conventions import pose_to_T, stamp_ns
from common.ros.record import record
from common.ros.synth import dataset_to_bag
from common.runtime.graph import load_graph


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


# ---------------------------------------------------------------- recordings that survive their end

def _camera_graph(bag):
    """A rosbag source alone, playing a small synthetic bag at 5 Hz in a loop (about 90 KB/s)."""
    from common.ros.bagfuzz import topic_map
    return {"nodes": [{"id": "camera", "module": "rosbag", "outputs": ["left", "right", "measured", "calib", "eos"],
                       "params": {"path": str(bag), "topics": topic_map(), "rate": 5, "loop": True}}]}


def _recorder(graph_path, out, *args, preexec_fn=None):
    import os
    import subprocess
    import sys
    from graphtools import REPO
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "common.cli", "record", "-g", str(graph_path), "--out", str(out),
                             *args], cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=preexec_fn)


def _wait_for(pred, timeout, what):
    import time
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def _frames(path, topics):
    from common.ros.bag import BagStereo
    with BagStereo(path, topics=topics) as src:
        return list(src), src.info.get("recovered")


@pytest.fixture()
def small_bag(tmp_path):
    from common.ros.bagfuzz import synthetic_bag
    return synthetic_bag(str(tmp_path / "src.mcap"), 10)


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGHUP"])
def test_sigterm_and_sighup_finish_the_recording_like_ctrl_c(run_graph, small_bag, tmp_path, sig):
    import signal

    from mcap.reader import make_reader
    g = run_graph(_camera_graph(small_bag), timeout=90)
    out = tmp_path / "run.mcap"
    rec = _recorder(g.path, out)
    tm = tmp_path / "run.mcap.topics.yaml"
    _wait_for(tm.exists, 60, "the topic map, written once the calibration and images came")
    assert rec.poll() is None                                    # still recording
    g.collect("camera/left", 5, timeout=60)
    rec.send_signal(getattr(signal, sig))
    stdout, stderr = rec.communicate(timeout=60)
    assert rec.returncode == 0, stderr
    assert "Traceback" not in stderr and " messages on " in stdout
    with open(out, "rb") as f:                                   # mcap's seeking reader: a summary
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count > 0
    frames, recovered = _frames(out, str(tm))
    assert frames and recovered is None


def test_a_killed_recorder_plays_back_up_to_its_last_complete_chunk(run_graph, small_bag, tmp_path, capsys):
    """kill -9 after 10 s: the file holds no summary; the readers give the frames of its complete
    chunks (closed every second: about 90 KB/s would fill a 1 MB chunk only after 11 s) and say so."""
    import signal
    import time

    from common.ros.reader import is_unfinished_mcap
    g = run_graph(_camera_graph(small_bag), timeout=90)
    out = tmp_path / "killed.mcap"
    rec = _recorder(g.path, out)
    tm = tmp_path / "killed.mcap.topics.yaml"
    _wait_for(tm.exists, 60, "the topic map")
    time.sleep(10)
    t_kill = time.time_ns()
    rec.send_signal(signal.SIGKILL)
    rec.communicate(timeout=30)
    assert is_unfinished_mcap(out)
    frames, recovered = _frames(out, str(tm))
    assert len(frames) >= 10, len(frames)
    assert "complete chunks of an unfinished recording" in recovered
    from common.ros.bag import open_reader
    r = open_reader(out)
    last = max(t for _, t, _ in r.messages(r.connections))
    r.close()
    assert (t_kill - last) / 1e9 < 5.0, "the chunk in progress held more than a few seconds"
    rc = dataset_main(["from-bag", str(out), "--topics", str(tm), "--out", str(tmp_path / "ds"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0 and "recovered" in err, err


def test_a_full_disk_stops_the_recorder_in_one_line(run_graph, small_bag, tmp_path):
    """A file-size limit (RLIMIT_FSIZE, 300 KB) stands in for a full disk: one error line, exit 1,
    and the file cut back to its complete chunks, readable."""
    import resource

    limit = 300_000

    def small_files():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    g = run_graph(_camera_graph(small_bag), timeout=90)
    out = tmp_path / "full.mcap"
    rec = _recorder(g.path, out, preexec_fn=small_files)
    stdout, stderr = rec.communicate(timeout=120)
    assert rec.returncode == 1, (stdout, stderr)
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {out}: cannot write"), stderr
    assert "File too large" in lines[0], stderr
    assert out.stat().st_size <= limit
    frames, recovered = _frames(out, str(tmp_path / "full.mcap.topics.yaml"))
    assert frames and recovered


def test_record_refuses_a_missing_folder_and_a_recording_of_nothing(run_graph, small_bag, tmp_path):
    from graphtools import cli
    g = run_graph(_camera_graph(small_bag), timeout=90)
    r = cli("record", "-g", g.path, "--out", tmp_path / "nope" / "x.mcap", timeout=60)
    assert r.returncode == 2 and "no folder" in r.stderr and "Traceback" not in r.stderr, r.stderr
    out = tmp_path / "nothing.mcap"
    r = cli("record", "-g", g.path, "--out", out, "camera/nothing", "--duration", "2", timeout=60)
    assert r.returncode == 1 and "nothing recorded" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not out.exists()
