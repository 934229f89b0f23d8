"""The viewer's parts with no graph: downscaling, Fig. 1 drawing, numbers, the page server, the
node offline, ``needletrack launch --no-viewer`` and ``needletrack view``."""
import json
import os
import subprocess
import sys
import time
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest
from graphtools import REPO, cli, free_port

from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import make_T, rotvec_to_R
from common.runtime.messages import (
    Calibration,
    CameraImage,
    GroundTruth,
    Keypoints,
    PoseEstimate,
)
from common.viewer.draw import (
    AMBIGUOUS_BGR,
    DETECTION_BGR,
    HOLDER_BGR,
    TRUTH_BGR,
    InstrumentToDraw,
    PoseToDraw,
    decode_small,
    downscale,
    draw_fig1,
    fig1_with_zoom,
    fit_size,
    method_bgr,
    project,
)
from common.viewer.page import PageServer
from common.viewer.state import RateMeter, ViewerState

W, H = 960, 540
RIG = StereoRig.default(W, H)
NEEDLE = NeedleModel()
# the needle 7 cm in front of the cameras (they look along -z of the ECM frame), tilted
T_NEEDLE = make_T(rotvec_to_R([2.9, 0.3, 0.0]), [0.0, 0.0, -0.07])


def _count(img, bgr, tol=30):
    return int((np.abs(img.astype(int) - np.array(bgr)).max(axis=2) <= tol).sum())


def test_fit_size_keeps_the_aspect_and_never_enlarges():
    assert fit_size(1920, 1080, 960, 540) == (960, 540)
    assert fit_size(1920, 1080, 960, 960) == (960, 540)
    assert fit_size(640, 360, 960, 540) == (640, 360)
    assert fit_size(1000, 2000, 960, 540) == (270, 540)


def test_decode_small_matches_a_full_decode_then_resize():
    rng = np.random.default_rng(0)
    img = cv2.GaussianBlur(rng.integers(0, 255, (1080, 1920, 3), dtype=np.uint8), (31, 31), 8)
    jpeg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
    small, s = decode_small(jpeg, "jpeg", 1920, 1080, 960, 540)
    assert small.shape == (540, 960, 3) and s == 0.5
    ref, _ = downscale(img, 960, 540)
    assert np.abs(small.astype(int) - ref).mean() < 4
    raw, s2 = decode_small(img.tobytes(), "bgr8", 1920, 1080, 480, 480)
    assert raw.shape == (270, 480, 3) and s2 == 0.25
    with pytest.raises(ValueError):
        decode_small(b"not a jpeg", "jpeg", 1920, 1080, 960, 540)
    with pytest.raises(ValueError):
        decode_small(b"\0" * 10, "bgr8", 1920, 1080, 960, 540)


def test_project_scales_pixels_and_drops_points_behind_the_camera():
    cam = RIG.left
    full = project(cam, T_NEEDLE, NEEDLE.keypoints())
    half = project(cam, T_NEEDLE, NEEDLE.keypoints(), 0.5)
    assert np.allclose(half, (full + 0.5) * 0.5 - 0.5)
    assert np.allclose(full, cam.project_from_ecm((T_NEEDLE[:3, :3] @ NEEDLE.keypoints().T).T + T_NEEDLE[:3, 3]))
    behind = make_T(np.eye(3), [0, 0, 0.12])
    assert np.isnan(project(cam, behind, NEEDLE.keypoints())).all()


def test_fig1_draws_the_final_arc_truth_detections_and_ambiguity():
    img = np.zeros((H // 2, W // 2, 3), np.uint8)
    cam = RIG.left
    uv = cam.project_from_ecm((T_NEEDLE[:3, :3] @ NEEDLE.keypoints().T).T + T_NEEDLE[:3, 3])
    other = T_NEEDLE.copy()
    other[:3, 3] += [0.004, 0.0, 0.0]
    poses = {"refined": PoseToDraw(T_NEEDLE), "pnp_joint": PoseToDraw(other)}
    pic = draw_fig1(img, 0.5, cam, NEEDLE, poses, "refined", uv, T_NEEDLE, "left")
    assert pic.shape == img.shape and not img.any()           # drawn on a copy
    assert _count(pic, method_bgr("refined")) > 100
    assert _count(pic, method_bgr("pnp_joint")) > 20
    assert _count(pic, DETECTION_BGR) > 20
    # the final arc passes through its keypoints, drawn where the camera sees them
    for p in (uv + 0.5) * 0.5 - 0.5:
        x, y = np.round(p).astype(int)
        assert _count(pic[y - 3:y + 4, x - 3:x + 4], method_bgr("refined")) > 0
    no_truth = draw_fig1(img, 0.5, cam, NEEDLE, {}, None, None, None)
    assert not no_truth.any()
    truth_only = draw_fig1(img, 0.5, cam, NEEDLE, {}, None, None, T_NEEDLE)
    assert _count(truth_only, TRUTH_BGR) > 20
    amb = draw_fig1(img, 0.5, cam, NEEDLE, {"refined": PoseToDraw(T_NEEDLE, ambiguous=True)}, "refined")
    assert _count(amb, AMBIGUOUS_BGR, 10) > 30                # the AMBIGUOUS label
    assert _count(amb, method_bgr("refined")) < _count(pic, method_bgr("refined"))   # dashed


def test_fig1_draws_each_instruments_jaw_frame_and_rings_the_holder():
    img = np.zeros((H // 2, W // 2, 3), np.uint8)
    cam = RIG.left
    T_a = make_T(rotvec_to_R([2.5, 0.2, 0.4]), [-0.012, 0.004, -0.07])
    T_b = make_T(rotvec_to_R([2.5, -0.3, 0.1]), [0.03, -0.012, -0.075])
    pic = draw_fig1(img, 0.5, cam, NEEDLE, {}, None,
                    instruments=[InstrumentToDraw("psm1", T_a, True), InstrumentToDraw("psm2", T_b, False)])
    for T, holds in ((T_a, True), (T_b, False)):
        x, y = np.round((cam.project_from_ecm(T[:3, 3][None])[0] + 0.5) * 0.5 - 0.5).astype(int)
        near = pic[max(0, y - 12):y + 13, max(0, x - 12):x + 13]
        assert near.any()                                              # its axes start at the pivot
        assert (_count(near, HOLDER_BGR, 10) > 5) == holds             # the holder alone ringed
    assert not draw_fig1(img, 0.5, cam, NEEDLE, {}, None).any()


def test_the_zoomed_inset_shows_the_needle_large_in_the_top_right_corner():
    img = np.full((H // 2, W // 2, 3), 60, np.uint8)
    poses = {"refined": PoseToDraw(T_NEEDLE)}
    plain = draw_fig1(img, 0.5, RIG.left, NEEDLE, poses, "refined")
    zoomed = fig1_with_zoom(img, 0.5, RIG.left, NEEDLE, poses, "refined")
    corner = (slice(0, H // 4), slice(W // 4, W // 2))
    assert _count(zoomed[corner], method_bgr("refined")) > 5 * max(1, _count(plain[corner], method_bgr("refined")))
    assert (fig1_with_zoom(img, 0.5, RIG.left, NEEDLE, {}, None) == img).all()   # nothing to zoom on


def test_state_rows_errors_rates_and_series():
    st = ViewerState(keep_s=5.0, every_s=0.2)
    T_off = T_NEEDLE.copy()
    T_off[:3, 3] += [0.001, 0, 0]
    for i in range(20):
        row = st.add_pose("refined", i, T_off, T_NEEDLE, 20.0, False, t=i * 0.1)
    assert row["pos_err_mm"] == pytest.approx(1.0, abs=1e-6) and row["rot_err_deg"] == pytest.approx(0, abs=1e-6)
    assert row["rate_hz"] == pytest.approx(10.5, abs=1.0)
    js = st.to_json(now=2.0)
    assert set(js) == {"head", "final", "methods", "series", "keep_s", "colours"} and js["keep_s"] == 5.0
    pts = js["series"]["pos_err_mm"]["refined"]
    assert 8 <= len(pts) <= 11 and pts[-1][0] <= 0                 # thinned to every 0.2 s
    st.add_pose("pnp_joint", 30, T_off, None, 5.0, True, t=3.0, end_identity=0.6234)
    assert st.methods["pnp_joint"]["pos_err_mm"] is None and st.methods["pnp_joint"]["ambiguous"]
    assert st.methods["pnp_joint"]["tip_p"] == 0.62 and row["tip_p"] is None
    json.dumps(st.to_json(now=3.0))
    m = RateMeter(1.0)
    for t in np.arange(0, 3, 0.05):
        m.add(t)
    assert m.rate(3.0) == pytest.approx(20, abs=1) and m.rate(10.0) == 0


def test_page_server_serves_the_page_frames_and_state():
    s = PageServer(port=0, poll_ms=50, rerun_url="http://127.0.0.1:1/?url=x")
    try:
        page = urllib.request.urlopen(s.url, timeout=5).read().decode()
        assert "left.jpg" in page and "state.json" in page and "http://127.0.0.1:1/?url=x" in page
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(s.url + "left.jpg", timeout=5)
        assert e.value.code == 503
        s.set_frame("left", b"\xff\xd8jpeg")
        s.set_state({"head": "seq 3"})
        assert urllib.request.urlopen(s.url + "left.jpg?t=1", timeout=5).read() == b"\xff\xd8jpeg"
        assert json.load(urllib.request.urlopen(s.url + "state.json", timeout=5)) == {"head": "seq 3"}
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(s.url + "nope", timeout=5)
        assert e.value.code == 404
    finally:
        s.close()


def _calib():
    return Calibration(0, np.array([W, H]), RIG.to_dict(), NEEDLE.to_dict())


def test_viewer_node_offline_draws_sampled_frames_with_their_pose(capsys):
    from nodes.viewer import ViewerNode
    node = ViewerNode.offline({"port": 0, "rerun": False, "rate_hz": 1000, "width": 480, "height": 270},
                              wired=["left", "right", "keypoints_left", "keypoints_right", "truth",
                                     "calib", "refined", "pnp_joint"])
    try:
        assert node.final == "refined"
        assert f"viewer: {node.page.url}" in capsys.readouterr().out
        node.on_calib(_calib())
        img = np.full((H, W, 3), 90, np.uint8)
        uv = {c: RIG[c].project_from_ecm((T_NEEDLE[:3, :3] @ NEEDLE.keypoints().T).T + T_NEEDLE[:3, 3])
              for c in ("left", "right")}
        for seq in range(3):
            node.on_truth(GroundTruth(seq, seq, T_world_ecm=np.eye(4), T_world_needle=T_NEEDLE))
            for c in ("left", "right"):
                node.on_left(CameraImage.from_bgr(c, seq, seq, img, "jpeg")) if c == "left" else \
                    node.on_right(CameraImage.from_bgr(c, seq, seq, img, "jpeg"))
                kp = Keypoints(c, seq, seq, True, uv[c], np.ones(5), 0.9)
                (node.on_keypoints_left if c == "left" else node.on_keypoints_right)(kp)
            assert node.counters["frames_drawn"] == seq                 # waits for the final pose
            node.on_pnp_joint(PoseEstimate(seq, time.time_ns(), "pnp_joint", T_NEEDLE))
            node.on_refined(PoseEstimate(seq, time.time_ns(), "refined", T_NEEDLE))
            assert node.counters["frames_drawn"] == seq + 1
        st = json.load(urllib.request.urlopen(node.page.url + "state.json", timeout=5))
        assert st["methods"]["refined"]["pos_err_mm"] == 0 and "seq 2" in st["head"]
        jpeg = urllib.request.urlopen(node.page.url + "right.jpg", timeout=5).read()
        pic = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        assert pic.shape == (270, 480, 3) and _count(pic, method_bgr("refined"), 50) > 50
        # an instrument holding the needle: ringed in the next picture
        from common.runtime.messages import InstrumentState
        T_jaw = make_T(rotvec_to_R([2.5, 0.2, 0.4]), [-0.015, -0.01, -0.07])   # clear of the inset
        assert _count(pic, HOLDER_BGR, 10) == 0
        node.on_truth(GroundTruth(3, 3, T_world_ecm=np.eye(4), T_world_needle=T_NEEDLE))
        node.on_instruments(InstrumentState("psm1", 3, 3, T_jaw, 0.05, True))
        for c in ("left", "right"):
            (node.on_left if c == "left" else node.on_right)(CameraImage.from_bgr(c, 3, 3, img, "jpeg"))
        node.on_refined(PoseEstimate(3, time.time_ns(), "refined", T_NEEDLE))
        jpeg = urllib.request.urlopen(node.page.url + "left.jpg", timeout=5).read()
        pic = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        assert node.counters["frames_drawn"] == 4, node.counters
        assert [i.name for i in node._instruments_to_draw(3)] == ["psm1"]
        assert _count(pic, HOLDER_BGR, 60) > 10
        node.on_left(CameraImage("left", 9, 9, W, H, "jpeg", b"broken"))
        assert node.counters["bad_input"] == 1
    finally:
        node.teardown()


def test_a_taken_port_falls_back_to_a_free_one(capsys):
    import socket

    from nodes.viewer import ViewerNode, port_or_free
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert port_or_free(port) != port
        node = ViewerNode.offline({"port": port, "rerun": False}, wired=["left", "right", "calib"])
        try:
            assert node.page.port != port
            assert f"viewer: http://127.0.0.1:{node.page.port}/" in capsys.readouterr().out
        finally:
            node.teardown()


def test_a_frame_without_its_pose_is_drawn_after_pose_wait():
    from nodes.viewer import ViewerNode
    node = ViewerNode.offline({"port": 0, "rerun": False, "rate_hz": 1000, "pose_wait_s": 0.05},
                              wired=["left", "right", "calib", "refined"])
    try:
        node.on_calib(_calib())
        img = np.zeros((H, W, 3), np.uint8)
        node.on_left(CameraImage.from_bgr("left", 0, 0, img))
        node.on_right(CameraImage.from_bgr("right", 0, 0, img))
        assert node.counters["frames_drawn"] == 0
        time.sleep(0.1)
        node.on_left(CameraImage.from_bgr("left", 1, 1, img))
        assert node.counters["frames_drawn"] == 1 and node.rendered == 0
    finally:
        node.teardown()


@pytest.mark.graph
def test_launch_save_records_and_no_viewer_leaves_the_viewer_out(tmp_path):
    port = free_port()
    graph = tmp_path / "g.yaml"
    graph.write_text(json.dumps({"graph": f"nv{os.getpid()}", "zenoh": {"listen": [f"tcp/127.0.0.1:{free_port()}"]},
                                 "nodes": [{"id": "count", "module": "counter", "params": {"rate_hz": 5}},
                                           {"id": "viewer", "module": "viewer",
                                            "params": {"port": port, "grpc_port": 0, "web_port": 0}}]}))
    rrd = tmp_path / "s.rrd"
    with_viewer = cli("launch", graph, "--duration", "6", "--save", rrd, timeout=90)
    assert f"viewer: http://127.0.0.1:{port}/" in with_viewer.stdout, with_viewer.stdout + with_viewer.stderr
    assert f"viewer: recording to {rrd}" in with_viewer.stdout and rrd.stat().st_size > 0
    without = cli("launch", graph, "--duration", "3", "--no-viewer", timeout=90)
    assert without.returncode == 0 and "viewer" not in without.stdout, without.stdout


@pytest.mark.slow
def test_view_serves_a_recording_on_loopback(tmp_path):
    import rerun  # noqa: F401  (the viewer extra: pip install -e '.[viewer]')

    from common.viewer import rerun_log
    rrd = tmp_path / "r.rrd"
    rec = rerun_log.new_recording()
    rerun_log.set_sinks(rec, save=str(rrd))
    rerun_log.log_rig(rec, RIG, 0.5)
    for seq in range(3):
        rerun_log.set_frame(rec, seq, seq * 10**8)
        rerun_log.log_needle(rec, "refined", NEEDLE.sample_arc(16), T_NEEDLE)
        rerun_log.log_scalar(rec, "pos_err_mm", "refined", 0.1 * seq)
    rec.flush()
    rec.disconnect()
    assert rrd.stat().st_size > 1000
    web, grpc = free_port(), free_port()
    proc = subprocess.Popen([sys.executable, "-m", "common.cli", "view", str(rrd), "--port", str(web),
                             "--grpc-port", str(grpc), "--duration", "60"], cwd=REPO,
                            stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.startswith(f"viewer: http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}")
        deadline, code = time.monotonic() + 60, None
        while time.monotonic() < deadline and code is None:
            try:
                code = urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=5).status
            except (urllib.error.URLError, ConnectionError):
                time.sleep(0.3)
        assert code == 200
    finally:
        proc.terminate()
        proc.wait(20)
    deadline = time.monotonic() + 20          # the server went with it
    while time.monotonic() < deadline:
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{web}/", timeout=2)
            time.sleep(0.3)
        except (urllib.error.URLError, ConnectionError):
            break
    else:
        raise AssertionError("the web viewer outlived `needletrack view`")
    assert cli("view", tmp_path / "missing.rrd").returncode == 2
