"""``needletrack label`` without a browser: the fit through clicks, the labels in the folder
(atomic, resumable, never over a render's truth), the order of the frames, and the page's server
refusing requests that are not its own page's (Host, Origin) or malformed, changing nothing."""
import json
import socket

import cv2
import numpy as np
import pytest

from common.data.check import check_frame
from common.data.dataset import Dataset, Frame
from common.data.meta import DatasetMeta
from common.data.writer import DatasetWriter
from common.detector.backends import KeypointBackend, register_backend
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.oracle import true_keypoints
from common.geometry.transforms import inv_T, make_T, pose_error, rotvec_to_R, transform_points
from common.label.fit import CameraClicks, LabelError, LabelFitter, LabelInputError, clicks_from_json
from common.label.proposals import detect_folder, doubt, label_order
from common.label.server import LabelApp, proposals_for
from common.label.store import SESSION_FILE, LabelStore
from common.runtime.messages import Keypoints
from common.viewer.http_server import HttpServer

W, H = 960, 540
RIG = StereoRig.default(W, H)
NEEDLE = NeedleModel()
# 8 cm in front of the cameras (which look along -z of the ECM frame), tilted about 50 degrees
T_NEEDLE = make_T(rotvec_to_R([2.4, 0.5, 0.3]), [0.004, -0.002, -0.08])


WIRE_DEG = (45, 70, 90, 110, 135)


def _clicks(T=T_NEEDLE, noise=None, cams=("left", "right"), wire_deg=WIRE_DEG):
    out = {}
    for c in cams:
        cam = RIG[c]
        uv, _ = true_keypoints(cam, T, NEEDLE)
        wire = cam.project(transform_points(cam.T_cam_ecm @ T, NEEDLE.arc_points(np.deg2rad(wire_deg))))
        d = (lambda: np.zeros(2)) if noise is None else noise
        out[c] = CameraClicks(uv[0] + d(), uv[4] + d(), np.array([p + d() for p in wire]))
    return out


def test_exact_clicks_give_the_keypoints_and_the_pose():
    fit = LabelFitter(RIG, NEEDLE).fit(_clicks())
    for c in ("left", "right"):
        uv, _ = true_keypoints(RIG[c], T_NEEDLE, NEEDLE)
        assert np.abs(fit.keypoints[c] - uv).max() < 0.05
        assert fit.visible[c].all() and fit.bbox[c] is not None
    dt, dr = pose_error(fit.T_ecm_needle, T_NEEDLE)
    assert dt < 2e-4 and np.rad2deg(dr) < 0.5
    assert fit.stereo and fit.pose_known and fit.snapped == 0
    assert fit.covariance.shape == (6, 6) and all(s.shape == (5,) for s in fit.sigma_px.values())
    # two wire points a camera: the projections as sure, but the arc's mirror image fits about as
    # well at 1 px of stated click noise: the pose is not claimed (the images' wire decides it)
    few = LabelFitter(RIG, NEEDLE).fit(_clicks(wire_deg=(70, 110)))
    assert few.ambiguous and not few.pose_known and few.alternatives
    assert max(np.abs(few.keypoints[c] - true_keypoints(RIG[c], T_NEEDLE, NEEDLE)[0]).max() for c in ("left", "right")) < 0.05


def test_one_camera_labels_that_camera_and_writes_no_pose():
    clicks = _clicks(cams=("left",))
    clicks["right"] = CameraClicks(unseen=True)
    fit = LabelFitter(RIG, NEEDLE).fit(clicks)
    uv, _ = true_keypoints(RIG["left"], T_NEEDLE, NEEDLE)
    assert np.abs(fit.keypoints["left"] - uv).max() < 0.3
    assert not fit.stereo and not fit.pose_known and fit.cameras == ("left",)
    assert not fit.visible["right"].any() and fit.bbox["right"] is None


def test_a_hidden_keypoint_is_not_visible_and_missing_clicks_are_said():
    clicks = _clicks()
    clicks["left"].hidden[2] = True
    fit = LabelFitter(RIG, NEEDLE).fit(clicks)
    assert fit.visible["left"].tolist() == [True, True, False, True, True] and fit.visible["right"].all()
    with pytest.raises(LabelError, match="no clicks"):
        LabelFitter(RIG, NEEDLE).fit({"left": CameraClicks(), "right": CameraClicks()})
    only_wire = {c: CameraClicks(wire=k.wire) for c, k in _clicks().items()}
    with pytest.raises(LabelError, match="tip or the tail and a point on the wire"):
        LabelFitter(RIG, NEEDLE).fit(only_wire)
    # with a prior pose (a proposal, the previous label) the wire alone is enough to start
    near = make_T(T_NEEDLE[:3, :3], T_NEEDLE[:3, 3] + [0.001, 0.0, 0.0])
    tip_tail = {c: CameraClicks(k.tip, k.tail, k.wire) for c, k in _clicks().items()}
    assert LabelFitter(RIG, NEEDLE).fit(tip_tail, priors=[near]).pose_known


def test_with_the_tail_hidden_the_tip_and_the_seen_wire_give_the_arc():
    """An instrument's jaws over D and E: the user clicks the tip and the wire up to C."""
    clicks = _clicks(wire_deg=(45, 60, 75, 90))
    for k in clicks.values():
        k.tail, k.hidden = None, np.array([False, False, False, True, True])
    fit = LabelFitter(RIG, NEEDLE).fit(clicks)
    for c in ("left", "right"):
        uv, _ = true_keypoints(RIG[c], T_NEEDLE, NEEDLE)
        assert np.abs(fit.keypoints[c] - uv).max() < 0.05
        assert fit.visible[c].tolist() == [True, True, True, False, False]
    assert pose_error(fit.T_ecm_needle, T_NEEDLE)[0] < 2e-4


def test_a_camera_with_lens_distortion_is_fitted_in_its_own_pixels():
    import dataclasses
    dist = np.array([-0.2, 0.05, 0.001, -0.001, 0.0])
    rig = StereoRig(*(dataclasses.replace(c, dist=dist) for c in RIG.cameras))
    clicks = {}
    for c in ("left", "right"):
        cam = rig[c]
        uv, _ = true_keypoints(cam, T_NEEDLE, NEEDLE)             # distorted pixels, as the image shows
        wire = cam.project(transform_points(cam.T_cam_ecm @ T_NEEDLE, NEEDLE.arc_points(np.deg2rad(WIRE_DEG))))
        clicks[c] = CameraClicks(uv[0], uv[4], wire)
    fit = LabelFitter(rig, NEEDLE).fit(clicks)
    for c in ("left", "right"):
        assert np.abs(fit.keypoints[c] - true_keypoints(rig[c], T_NEEDLE, NEEDLE)[0]).max() < 0.05
    assert pose_error(fit.T_ecm_needle, T_NEEDLE)[0] < 2e-4


def test_clicks_are_read_strictly():
    good = {"left": {"tip": [10, 20], "tail": [30.5, 40], "wire": [[20, 25]], "hidden": [False] * 5}}
    c = clicks_from_json(good, (W, H))
    assert c["left"].count == 3 and c["right"].count == 0
    for bad, msg in [({"left": {"tip": [5000, 1]}}, "outside the 960x540 image"),
                     ({"left": {"tip": "here"}}, r"clicks.left.tip: expected \[u, v\]"),
                     ({"middle": {}}, "unknown camera 'middle'"),
                     ({"left": {"hidden": [True]}}, "expected 5 booleans"),
                     ({"left": {"wire": [[1, 2]] * 40}}, "at most 32 points"),
                     ({"left": {"tip": [float("nan"), 1]}}, "outside"),
                     ({"left": {"colour": 1}}, "unknown field 'colour'")]:
        with pytest.raises(LabelInputError, match=msg):
            clicks_from_json(bad, (W, H))


# ------------------------------------------------------------------ the folder

def _folder(path, n=3, truth_at=(), endoscope=True):
    """A folder of ``n`` frames (plain images), the endoscope at the world's origin turned a
    little (``endoscope`` False: its pose not recorded); frames in ``truth_at`` carry a render's
    ground truth."""
    meta = DatasetMeta((W, H), RIG, NEEDLE)
    img = np.full((H, W, 3), 90, np.uint8)
    with DatasetWriter(str(path), meta) as w:
        for i in range(n):
            T_world_ecm = make_T(rotvec_to_R([0.0, 0.02 * i, 0.0]), [0.001 * i, 0.0, 0.0])
            paths = w.write_images(i, {"left": img, "right": img})
            fr = Frame(index=i, stamp_ns=i * 1000, left=paths["left"], right=paths["right"], sequence=0,
                       step=i, T_world_ecm=T_world_ecm if endoscope else None)
            if i in truth_at:
                fr.T_world_needle = T_world_ecm @ T_NEEDLE
                fr.keypoints = {c: true_keypoints(RIG[c], T_NEEDLE, NEEDLE)[0] for c in ("left", "right")}
            w.append(fr)
    return path


def test_a_label_is_saved_as_the_contracts_truth_and_read_back(tmp_path):
    folder = _folder(tmp_path / "ds")
    store = LabelStore(str(folder))
    fit = LabelFitter(RIG, NEEDLE).fit(_clicks())
    store.save(0, fit, _clicks(), click_sigma_px=1.0, start="none", edits=8)
    store.save(1, None, {"left": CameraClicks(), "right": CameraClicks()}, click_sigma_px=1.0)
    ds = Dataset(str(folder))
    fr = ds[0]
    assert fr.label["by"] == "needletrack label" and fr.label["fit"] == "stereo" and fr.label["edits"] == 8
    errs, reproj, _ = check_frame(ds.meta, fr, tol_px=1e-3)       # keypoints = the pose's projections
    assert errs == [] and reproj < 1e-3
    dt, dr = pose_error(inv_T(fr.T_world_ecm) @ fr.T_world_needle, T_NEEDLE)
    assert dt < 2e-4 and np.rad2deg(dr) < 0.5
    assert fr.visible["left"].all() and fr.bbox["left"] is not None
    assert ds[1].keypoints is None and not ds[1].visible["left"].any() and ds[1].bbox == {"left": None, "right": None}
    assert ds[1].label["no_needle"] and ds[2].label is None
    again = LabelStore(str(folder))
    assert [again.status(i) for i in range(3)] == ["labelled", "no_needle", "unlabelled"]
    assert not [p for p in folder.iterdir() if p.name.startswith(".")]           # no temporary left
    # the next frame of the take starts from this label, seen from its own endoscope pose
    prior = again.prior_pose(2)
    T2 = inv_T(ds[2].T_world_ecm) @ fr.T_world_needle
    assert np.allclose(prior, T2, atol=1e-9)


def test_without_the_endoscopes_pose_the_pose_stays_in_the_label(tmp_path):
    folder = _folder(tmp_path / "ds", endoscope=False)
    store = LabelStore(str(folder))
    store.save(0, LabelFitter(RIG, NEEDLE).fit(_clicks()), _clicks(), click_sigma_px=1.0)
    fr = Dataset(str(folder))[0]
    assert fr.T_world_needle is None and fr.keypoints is not None
    assert np.allclose(fr.label["T_ecm_needle"], LabelStore(str(folder)).label_pose(0))
    assert pose_error(np.array(fr.label["T_ecm_needle"]), T_NEEDLE)[0] < 2e-4


def test_a_renders_truth_is_never_overwritten_and_a_changed_file_is_not_clobbered(tmp_path):
    folder = _folder(tmp_path / "ds", truth_at=(1,))
    store = LabelStore(str(folder))
    before = (folder / "frames.jsonl").read_bytes()
    fit = LabelFitter(RIG, NEEDLE).fit(_clicks())
    assert store.status(1) == "truth"
    with pytest.raises(LabelError, match="not made by needletrack label"):
        store.save(1, fit, _clicks(), click_sigma_px=1.0)
    with (folder / "frames.jsonl").open("a") as f:      # someone else writes the file meanwhile
        f.write("")
    import os
    os.utime(folder / "frames.jsonl", ns=(1, 1))
    with pytest.raises(LabelError, match="changed on disk"):
        store.save(0, fit, _clicks(), click_sigma_px=1.0)
    assert (folder / "frames.jsonl").read_bytes() == before


def test_frames_the_detector_is_least_sure_of_come_first():
    sure = {c: {"found": True, "confidence": 0.99, "end_identity": 0.99} for c in ("left", "right")}
    unsure_tip = {c: {"found": True, "confidence": 0.99, "end_identity": 0.55} for c in ("left", "right")}
    none_sure = {c: {"found": False, "confidence": 0.01, "end_identity": None} for c in ("left", "right")}
    maybe = {"left": {"found": False, "confidence": 0.45, "end_identity": None}, "right": sure["right"]}
    props = [sure, unsure_tip, none_sure, maybe, None]
    assert doubt(sure) < 0.05 and doubt(none_sure) < 0.05 and doubt(None) == 1.0
    assert label_order(props, 5) == [4, 1, 3, 0, 2]
    assert label_order(None, 3) == [0, 1, 2]


class FixedBackend(KeypointBackend):
    """A backend proposing the true keypoints of T_NEEDLE in every frame (for the tests)."""

    name = "label-test-fixed"

    def detect(self, image, camera, truth, calib, *, seq=0, stamp_ns=0):
        uv, _ = true_keypoints(RIG[camera], T_NEEDLE, NEEDLE)
        return Keypoints(camera, seq, stamp_ns, True, uv, np.ones(5), 0.9 if seq else 0.6, detector=self.name)


def test_proposals_come_through_the_backend_api_and_are_kept(tmp_path):
    register_backend("label-test-fixed", "test_label:FixedBackend")
    store = LabelStore(str(_folder(tmp_path / "ds")))
    props = proposals_for(store, "label-test-fixed", {}, progress=False)
    assert len(props) == 3 and props[0]["left"]["found"] and props[0]["left"]["confidence"] == 0.6
    assert json.loads((tmp_path / "ds" / SESSION_FILE).read_text())["proposals"]["frames"] == props
    assert proposals_for(LabelStore(str(tmp_path / "ds")), "label-test-fixed", {}, progress=False) == props
    app = LabelApp(store, props)
    assert app.order[0] == 0                                    # the least sure
    fr = app.frame(1)
    assert fr["start"] == "proposal" and fr["fit"]["stereo"]
    uv, _ = true_keypoints(RIG["left"], T_NEEDLE, NEEDLE)
    assert np.abs(np.array(fr["fit"]["keypoints"]["left"]) - uv).max() < 0.05   # a right proposal: one key
    assert detect_folder(store.ds, "label-test-fixed", {}, progress=False)[2]["right"]["uv"] == props[2]["right"]["uv"]


# ------------------------------------------------------------------ the page's server

def _exchange(port, raw: bytes) -> tuple:
    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        s.sendall(raw)
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), body


def _post(port, path, body, host=None, origin="same", ctype="application/json"):
    host = host or f"127.0.0.1:{port}"
    origin = f"http://127.0.0.1:{port}" if origin == "same" else origin
    data = body if isinstance(body, bytes) else json.dumps(body).encode()
    head = (f"POST {path} HTTP/1.1\r\nHost: {host}\r\nContent-Type: {ctype}\r\nContent-Length: {len(data)}\r\n"
            + (f"Origin: {origin}\r\n" if origin else "") + "Connection: close\r\n\r\n")
    return _exchange(port, head.encode() + data)


@pytest.fixture
def label_server(tmp_path):
    folder = _folder(tmp_path / "ds")
    store = LabelStore(str(folder))
    app = LabelApp(store, None)
    server = HttpServer("127.0.0.1", 0, app.handle, name="label page", methods=("GET", "HEAD", "POST"),
                        blocking=True)
    yield server, folder
    server.close()


def test_the_page_refuses_other_sites_and_bad_requests_and_changes_nothing(label_server):
    server, folder = label_server
    port = server.port
    clicks = {c: k.to_json() for c, k in _clicks().items()}
    good = {"frame": 0, "clicks": clicks}
    before = (folder / "frames.jsonl").read_bytes()
    refused = [
        (_post(port, "/api/save", good, host="rebind.attacker.test"), 403),            # DNS rebinding
        (_post(port, "/api/save", good, origin="http://evil.example"), 403),           # another site's page
        (_post(port, "/api/save", good, origin=f"http://localhost:{port}"), 403),      # not the Host's origin
        (_post(port, "/api/save", good, origin=None), 403),                             # no Origin on a change
        (_post(port, "/api/save", good, ctype="text/plain"), 415),                     # a form's body
        (_post(port, "/api/save", b"{not json"), 400),
        (_post(port, "/api/save", {"frame": 99, "clicks": clicks}), 400),
        (_post(port, "/api/save", {"frame": 0, "clicks": {"left": {"tip": [1e6, 0]}}}), 400),
        (_post(port, "/api/save", {"frame": 0, "clicks": {"left": {"tip": [10, 10]}}}), 422),   # right unclicked
        (_post(port, "/api/save", b"x" * 70000), 413),
    ]
    for (status, body), want in refused:
        assert status == want, (status, body[:200])
    assert (folder / "frames.jsonl").read_bytes() == before and not (folder / SESSION_FILE).exists()
    status, body = _exchange(port, f"GET /api/session HTTP/1.1\r\nHost: evil.example:{port}\r\nConnection: close\r\n\r\n".encode())
    assert status == 403
    status, body = _exchange(port, (f"GET /api/session HTTP/1.1\r\nHost: localhost:{port}\r\nOrigin: http://evil.example\r\n"
                                    "Connection: close\r\n\r\n").encode())
    assert status == 403
    status, body = _exchange(port, (f"GET /image?i=0&camera=left HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
                                    "Sec-Fetch-Site: cross-site\r\nSec-Fetch-Mode: no-cors\r\nConnection: close\r\n\r\n").encode())
    assert status == 403                                      # another site's <img> of the endoscope
    status, body = _exchange(port, (f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nSec-Fetch-Site: cross-site\r\n"
                                    "Sec-Fetch-Mode: navigate\r\nConnection: close\r\n\r\n").encode())
    assert status == 200                                      # a link to the page opens it
    assert server.counters["http_bad_host"] == 2 and server.counters["http_bad_origin"] == 5
    status, body = _post(port, "/api/save", good)
    assert status == 200 and json.loads(body) == {"ok": True, "status": "labelled"}
    assert Dataset(str(folder))[0].label is not None
    assert json.loads((folder / SESSION_FILE).read_text())["position"] == 1
    status, body = _exchange(port, f"GET /image?i=0&camera=left HTTP/1.1\r\nHost: localhost:{port}\r\nConnection: close\r\n\r\n".encode())
    assert status == 200 and cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_COLOR).shape == (H, W, 3)


def test_the_command_prints_its_url_and_says_what_is_wrong_with_a_folder(tmp_path):
    from graphtools import cli
    folder = _folder(tmp_path / "ds")
    p = cli("label", folder, "--detector", "none", "--port", "0", "--duration", "0.5")
    assert p.returncode == 0, p.stderr
    assert "label: http://127.0.0.1:" in p.stdout and "(3 frames, 3 to label" in p.stdout
    (tmp_path / "bad").mkdir()
    p = cli("label", tmp_path / "bad", "--detector", "none")
    assert p.returncode == 1 and "dataset.yaml: file missing" in p.stderr and "Traceback" not in p.stderr
    p = cli("label", folder, "--detector", "no-such-backend", "--port", "0")
    assert p.returncode == 1 and "no-such-backend" in p.stderr and "Traceback" not in p.stderr


def test_simulated_clicks_label_a_folder_through_the_pages_path(tmp_path):
    from common.bench.label_bench import run
    from common.label.simulate import simulated_clicks
    rng = np.random.default_rng(0)
    clicks = simulated_clicks(RIG, NEEDLE, T_NEEDLE, rng, end_px=1.0, wire_px=2.0, wire=3)
    for c in ("left", "right"):
        uv, _ = true_keypoints(RIG[c], T_NEEDLE, NEEDLE)
        assert np.linalg.norm(clicks[c].tip - uv[0]) <= 1.0 and np.linalg.norm(clicks[c].tail - uv[4]) <= 1.0
        assert len(clicks[c].wire) == 3 and not clicks[c].hidden.any()
    hidden = simulated_clicks(RIG, NEEDLE, T_NEEDLE, rng, visible={"left": [False] * 5, "right": [True] * 4 + [False]})
    assert hidden["left"].unseen and hidden["right"].tail is None and hidden["right"].hidden.tolist() == [False] * 4 + [True]
    away = make_T(np.eye(3), [0.0, 0.0, 0.5])                       # behind the cameras
    assert simulated_clicks(RIG, NEEDLE, away, rng) is None
    folder = _folder(tmp_path / "ds", truth_at=(0, 1, 2))
    r = run(str(folder), end_px=0.0, wire_px=0.0, wire=5, progress=False)
    assert r["frames"] == 3 and not r["failed"] and r["clicks_per_frame"] == 14.0
    assert r["keypoint_px"]["max"] < 0.05 and r["posed_share"] == 1.0 and r["pose_mm"]["max"] < 0.2
    assert (folder / "frames.jsonl").exists() and Dataset(str(folder))[0].label is None   # the folder untouched
    register_backend("label-test-fixed", "test_label:FixedBackend")
    r = run(str(folder), detector="label-test-fixed", progress=False)
    assert r["proposals_accepted"] == 3 and r["proposals_within_1px"] == 3 and r["clicks_per_frame"] == 0


def test_a_write_cut_short_leaves_the_folder_as_it_was(tmp_path, monkeypatch):
    import os

    from common.data import writer
    folder = _folder(tmp_path / "ds")
    store = LabelStore(str(folder))
    fit = LabelFitter(RIG, NEEDLE).fit(_clicks())
    store.save(0, fit, _clicks(), click_sigma_px=1.0)
    before = (folder / "frames.jsonl").read_bytes()

    def killed(src, dst):
        raise KeyboardInterrupt("killed while writing")
    monkeypatch.setattr(writer.os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        store.save(1, fit, _clicks(), click_sigma_px=1.0)
    monkeypatch.setattr(writer.os, "replace", os.replace)
    assert (folder / "frames.jsonl").read_bytes() == before
    assert sorted(p.name for p in folder.iterdir()) == ["dataset.yaml", "frames.jsonl", "images"]
    again = LabelStore(str(folder))
    assert [again.status(i) for i in range(3)] == ["labelled", "unlabelled", "unlabelled"]


def test_an_unreadable_image_is_said_and_the_page_goes_on(tmp_path):
    folder = _folder(tmp_path / "ds")
    (folder / "images" / "left" / "000001.jpg").write_bytes(b"not a jpeg")
    app = LabelApp(LabelStore(str(folder)), None)
    from common.viewer.http_request import Request
    post = lambda body: app.handle(Request("POST", "/api/fit", (1, 1), {}), json.dumps(body).encode())
    a = post({"frame": 1, "clicks": {c: k.to_json() for c, k in _clicks().items()}})
    assert a.status == 422 and b"images/left/000001.jpg: not a readable PNG or JPEG image" in a.body
    a = post({"frame": 0, "clicks": {c: k.to_json() for c, k in _clicks().items()}})
    assert a.status == 200 and json.loads(a.body)["fit"]["stereo"]
