"""The ``rosbag`` source node in a launched graph: an AMBF ROS 1 bag (decimetres) played through
the oracle detector, the ecm node's measured pose and EPnP: poses exact, in metres."""
import numpy as np
import pytest
import yaml
from graphtools import cli

from common.cli import dataset_main
from common.data.dataset import Dataset
from common.geometry.transforms import pose_error
from common.ros.synth import dataset_to_bag


@pytest.fixture(scope="module")
def ambf_bag(tmp_path_factory):
    root = tmp_path_factory.mktemp("rosbag_node")
    rc = dataset_main(["generate", "--out", str(root / "ds"), "--sequences", "2", "--steps", "2", "--width", "320",
                       "--height", "240", "--seed", "4", "--randomise", "none", "--jobs", "1", "--quiet"])
    assert rc == 0
    dataset_to_bag(str(root / "ds"), str(root / "ambf.bag"), "ambf")
    return root


@pytest.mark.graph
def test_rosbag_source_drives_the_pipeline_exactly(run_graph, ambf_bag):
    ds = Dataset(ambf_bag / "ds")
    stereo = {"left": "detector/left", "right": "detector/right", "calib": "camera/calib", "ecm": "ecm/pose"}
    g = run_graph({"nodes": [
        {"id": "camera", "module": "rosbag", "outputs": ["left", "right", "measured", "truth", "calib", "eos"],
         "params": {"path": str(ambf_bag / "ambf.bag"), "preset": "ambf", "rate": 5, "loop": True}},
        {"id": "detector", "module": "detector", "params": {"backend": "oracle"},
         "inputs": {"left": "camera/left", "right": "camera/right", "truth": "camera/truth",
                    "calib": "camera/calib"}, "outputs": ["left", "right"]},
        {"id": "ecm", "module": "ecm", "inputs": {"measured": "camera/measured", "calib": "camera/calib"},
         "outputs": ["pose"]},
        {"id": "epnp_joint", "module": "epnp", "params": {"method": "joint"}, "inputs": stereo, "outputs": ["pose"]},
    ]}, timeout=90)
    calib = g.collect("camera/calib", 1, timeout=60)[0]
    assert tuple(calib.image_size) == (320, 240)
    np.testing.assert_allclose(np.asarray(calib.cameras["right"]["T_ecm_cam"]), ds.rig.right.T_ecm_cam, atol=1e-12)
    assert abs(calib.needle["radius_m"] - 0.01018) < 1e-12
    poses = g.collect("epnp_joint/pose", 6, timeout=120)
    n = len(ds)
    for p in poses:
        fr = ds[p.seq % n]
        assert p.T_world_needle is not None
        pos, rot = pose_error(p.T_world_needle, fr.T_world_needle)
        assert pos < 1e-7 and rot < 1e-6, (p.seq, pos, rot)
    img = g.collect("camera/left", 1, timeout=30)[0]
    assert img.encoding == "bgr8" and (img.width, img.height) == (320, 240)
    st = g.stats("camera")
    assert st.counters.get("bag_errors", 0) == 0


def test_rosbag_source_refuses_a_bag_without_its_topics(run_graph, ambf_bag, tmp_path):
    graph = {"graph": "bad", "nodes": [{"id": "camera", "module": "rosbag", "outputs": ["left", "right"],
                                        "params": {"path": str(ambf_bag / "ambf.bag"), "preset": "dvrk"}}]}
    path = tmp_path / "g.yaml"
    path.write_text(yaml.safe_dump(graph))
    r = cli("launch", str(path), "--duration", "30", timeout=90)
    assert r.returncode != 0
    assert "rig found" in r.stdout + r.stderr


def _source_graph(bag, **params):
    from common.ros.bagfuzz import topic_map
    return {"nodes": [{"id": "camera", "module": "rosbag", "outputs": ["left", "right", "measured", "calib", "eos"],
                       "params": {"path": str(bag), "topics": topic_map(), "rate": "max", **params}}]}


@pytest.mark.graph
def test_a_bag_that_fails_part_way_stops_the_source_non_zero_and_launch_says_why(tmp_path):
    """A corrupt chunk after the first frames, then a last right image of another size: the
    source stops with status 2 (not `source finished`, not restarted), launch names it, says
    why, and exits non-zero."""
    from graphtools import prepare_graph

    from common.ros.bagfuzz import mcap_records, synthetic_bag
    data = open(synthetic_bag(str(tmp_path / "ok.mcap"), 8), "rb").read()
    op, off, ln = [r for r in mcap_records(data) if r[0] == 0x06][5]
    b = bytearray(data)
    b[off + 9 + 60:off + 9 + 90] = b"\x00" * 30
    (tmp_path / "zstd.mcap").write_bytes(bytes(b))
    synthetic_bag(str(tmp_path / "size.mcap"), 6, last_right_size=(32, 24))
    for name, why in (("zstd.mcap", "unreadable after"), ("size.mcap", "right image 32x24 differ in size")):
        path = prepare_graph(_source_graph(tmp_path / name), tmp_path / name.replace(".", "_"))
        r = cli("launch", str(path), "--duration", "60", timeout=120)
        out = r.stdout + r.stderr
        assert r.returncode != 0, out
        assert "Traceback" not in out and "source finished" not in out and "restart #" not in out, out
        assert "[camera] ERROR source stopped: rosbag: " in out and why in out, out
        line = next(x for x in out.splitlines() if "camera exited with status 2" in x)
        assert name in line and why in line, line            # which node, and why, in the launcher's line
