"""``needletrack label`` in a real browser (headless Chromium, real mouse and key events): on a
rendered stereo frame stripped of its truth, clicks within 2 px of the true tip, tail and wire
(the tip and tail within 1 px: they set the arc's ends) give keypoints within 1 px of the truth
and a pose within 1 mm / 2 deg; the next frame of the take starts from that label and costs one
key; undo takes a click back; the labels are in the folder when it is opened again; a page of
another site open in the same browser changes and reads nothing.
"""

import numpy as np
import pytest

from common.data.dataset import Dataset
from common.geometry.transforms import inv_T, pose_error, transform_points
from common.label.server import serve
from common.label.store import LabelStore
from common.viewer.browser import Chromium, find_chromium

CAMS = ("left", "right")


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """One needle at rest seen from three endoscope poses, 960x540 (the needle 12.7 cm away spans
    about 50 px: the smaller renders of the other tests' fixtures leave a pose to 1 mm / 2 deg
    out of reach of any click), and a copy without its truth to label."""
    from common.cli import dataset_main
    root = tmp_path_factory.mktemp("label")
    assert dataset_main(["generate", "--out", str(root / "truth"), "--sequences", "1", "--steps", "3",
                         "--width", "960", "--height", "540", "--seed", "3", "--randomise", "none",
                         "--jobs", "1", "--quiet"]) == 0
    assert dataset_main(["strip-truth", str(root / "truth"), "--out", str(root / "work")]) == 0
    return Dataset(str(root / "truth")), root / "work"


def _offset(r, deg):
    return r * np.array([np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))])


def _click_image(b, cam, uv):
    x, y = b.evaluate(f"label.toScreen('{cam}', {float(uv[0])!r}, {float(uv[1])!r})")
    b.click(round(x), round(y))                 # a mouse is at whole CSS pixels


def _idle(b):
    b.wait_for("window.label && label.idle()", 60)


@pytest.mark.browser
def test_clicks_in_the_browser_give_the_truth_within_a_pixel_and_the_pose(rendered):
    assert find_chromium() is not None, "needs Debian's chromium: apt-get install -y chromium"
    truth, work = rendered
    rig, needle = truth.rig, truth.needle
    server, app = serve(str(work), port=0, detector="none", progress=False)
    try:
        with Chromium(size=(1500, 640)) as b:
            b.navigate(server.url)
            _idle(b)
            assert b.evaluate("label.S.frame.index") == 0 and b.evaluate("label.S.frame.start") == "none"
            x, y = np.round(b.evaluate("label.toScreen('left', 480, 270)"))   # the wheel zooms about the pointer
            s0, under = b.evaluate("label.S.views.left.s"), b.evaluate(f"label.toImage('left', {x}, {y})")
            b.wheel(x, y, -100)
            b.wait_for(f"label.S.views.left.s > {s0} * 1.2", 10)
            assert np.allclose(b.evaluate(f"label.toImage('left', {x}, {y})"), under, atol=1e-6)
            T = truth[0].T_ecm_needle
            for k, cam in enumerate(CAMS):
                c = rig[cam]
                uv = truth[0].keypoints[cam]
                b.evaluate(f"label.setView('{cam}', 4, {float(uv[:, 0].mean())!r}, {float(uv[:, 1].mean())!r})")
                wire = c.project(transform_points(c.T_cam_ecm @ T, needle.arc_points(np.deg2rad([70, 110]))))
                # tip and tail 1 px off, the wire points 2 px off, in directions of no pattern (aimed
                # a little nearer: the page takes a click at a whole CSS pixel, 1/4 image px here)
                for p, (r, deg) in zip([uv[0], uv[4], wire[0], wire[1]],
                                       [(0.8, 40 + 90 * k), (0.8, 250 - 60 * k), (1.8, 120 + 45 * k), (1.8, 300 - 70 * k)]):
                    _click_image(b, cam, p + _offset(r, deg))
            _idle(b)
            # a stray click, taken back with undo
            _click_image(b, "left", truth[0].keypoints["left"][2] + [12.0, 9.0])
            _idle(b)
            assert b.evaluate("label.S.clicks.left.wire.length") == 3
            b.key("u")
            _idle(b)
            assert b.evaluate("label.S.clicks.left.wire.length") == 2
            fit = b.wait_for("label.S.fit", 30)
            assert fit["stereo"] and fit["snapped"] > 100 and fit["pose_known"], fit
            b.key("Enter")                                          # accept: saved, next frame
            b.wait_for("label.S.session.statuses[0] === 'labelled' && label.S.frame.index === 1", 30)
            _idle(b)
            assert b.evaluate("label.S.frame.start") == "previous"   # the needle at rest, seen anew
            b.key("Enter")                                          # a right start costs one key
            b.wait_for("label.S.session.statuses[1] === 'labelled' && label.S.frame.index === 2", 30)
            _idle(b)
            b.key("0")                                              # no needle (the keys' test)
            b.wait_for("label.S.session.statuses[2] === 'no_needle'", 30)
            _idle(b)
            b.key("p")
            b.wait_for("label.S.frame.index === 1 && label.S.frame.start === 'saved'", 30)
            b.key("ArrowLeft")
            b.wait_for("label.S.frame.index === 0", 30)
            b.key("n")
            b.wait_for("label.S.frame.index === 1", 30)
            _idle(b)
    finally:
        server.close()

    labelled = Dataset(str(work))
    arc = {c: rig[c].project(transform_points(rig[c].T_cam_ecm @ truth[0].T_ecm_needle, needle.sample_arc(2000)))
           for c in CAMS}
    for i in range(2):
        fr, true = labelled[i], truth[i]
        assert fr.label["start"] == ("none" if i == 0 else "previous") and fr.label["edits"] == (0 if i else 10)
        err = {cam: np.linalg.norm(fr.keypoints[cam] - true.keypoints[cam], axis=1) for cam in CAMS}
        if i == 0:                  # the clicks as the page took them (whole CSS pixels at 4x zoom)
            ends = [np.linalg.norm(np.array(fr.label["clicks"][c][k]) - true.keypoints[c][j])
                    for c in CAMS for k, j in (("tip", 0), ("tail", 4))]
            off_wire = [float(np.min(np.linalg.norm(arc[c] - np.array(p), axis=1)))
                        for c in CAMS for p in fr.label["clicks"][c]["wire"]]
            print(f"clicks: tip and tail {max(ends):.2f} px from the truth at most, wire points "
                  f"{max(off_wire):.2f} px from the true arc at most")
            assert max(ends) <= 1.0 and max(off_wire) <= 2.0
        assert fr.T_world_needle is not None, fr.label
        dt, dr = pose_error(inv_T(fr.T_world_ecm) @ fr.T_world_needle, true.T_ecm_needle)
        print(f"frame {i}: keypoints off by {max(e.max() for e in err.values()):.2f} px at most "
              f"({np.mean(list(err.values())):.2f} mean), pose {dt * 1e3:.2f} mm {np.rad2deg(dr):.2f} deg, "
              f"stated {fr.label['pose_sigma_mm']:.2f} mm {fr.label['pose_sigma_deg']:.2f} deg")
        for cam in CAMS:
            assert err[cam].max() < 1.0, (i, cam, err[cam])
            assert fr.visible[cam].all()
        assert dt < 1e-3 and np.rad2deg(dr) < 2.0, (i, dt, np.rad2deg(dr))
    assert labelled[2].label["no_needle"] and labelled[2].keypoints is None
    store = LabelStore(str(work))                                  # reopened: where the user stopped
    assert [store.status(i) for i in range(3)] == ["labelled", "labelled", "no_needle"]
    assert store.session["position"] == 1


EVIL = """<!doctype html><html><body><script>
window.tries = {};
const L = 'http://127.0.0.1:@PORT@/';
const body = JSON.stringify({frame: 0, no_needle: true, clicks: {}});
(async () => {
  // a form-like POST (no preflight) and a JSON POST (preflighted) from another origin
  try { await fetch(L + 'api/save', {method: 'POST', mode: 'no-cors', body, headers: {'Content-Type': 'text/plain'}});
        window.tries.plain = 'sent'; } catch (e) { window.tries.plain = 'error'; }
  try { const r = await fetch(L + 'api/save', {method: 'POST', body, headers: {'Content-Type': 'application/json'}});
        window.tries.json = r.status; } catch (e) { window.tries.json = 'blocked'; }
  try { const r = await fetch(L + 'api/session'); window.tries.read = await r.text(); } catch (e) { window.tries.read = 'blocked'; }
  const img = new Image();
  img.onload = () => { window.tries.img = 'loaded'; }; img.onerror = () => { window.tries.img = 'refused'; };
  img.src = L + 'image?i=0&camera=left';
})();
</script></body></html>"""


@pytest.mark.browser
def test_another_sites_page_in_the_same_browser_changes_and_reads_nothing(rendered, tmp_path):
    """A page of another origin (here another port of 127.0.0.1) open in the browser tries to
    save a label, read the session and show an endoscope image: all refused, nothing written."""
    from common.data.writer import without_truth
    from common.viewer.http_server import Answer, HttpServer
    truth, _ = rendered
    work = tmp_path / "work"
    without_truth(truth.path, str(work))
    before = (work / "frames.jsonl").read_bytes()
    server, app = serve(str(work), port=0, detector="none", progress=False)
    evil = HttpServer("127.0.0.1", 0, lambda req, body: Answer(
        200, "text/html", EVIL.replace("@PORT@", str(server.port)).encode()), name="other site")
    try:
        with Chromium(size=(800, 600)) as b:
            b.navigate(evil.url)
            tries = b.wait_for("window.tries && Object.keys(window.tries).length === 4 && window.tries", 30)
        assert tries["json"] == "blocked" and tries["read"] == "blocked" and tries["img"] == "refused", tries
        assert (work / "frames.jsonl").read_bytes() == before and not (work / "label-session.json").exists()
        assert server.counters["http_bad_origin"] >= 2                 # the POST and the image: 403
        assert app.store.status(0) == "unlabelled"
    finally:
        evil.close()
        server.close()
