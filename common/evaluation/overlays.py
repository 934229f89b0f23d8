"""An evaluation's overlays (``overlays/`` of ``common/evaluation/report.py``): per chosen frame
(``select_overlay_frames``: the worst, a typical and the best), a crop of the left and right
images around the needle: the true arc and keypoints in green (``common.palette``), each method's
estimated arc in its colour, and the detector's keypoints as circles. Pixels as OpenCV's, BGR.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from common.evaluation.collect import Collected, Evaluation
from common.frames import CAMERAS
from common.geometry.needle import KEYPOINT_NAMES, NeedleModel
from common.geometry.transforms import transform_points
from common import palette
from common.methods import FINAL_ORDER, MULTIVIEW_METHODS
from common.viewer.draw import DETECTION_BGR, TRUTH_BGR, crop_box

def select_overlay_frames(ev: Evaluation, k_worst: int = 3) -> list[tuple[int, str]]:
    """Frames worth looking at: the worst ``k_worst`` of the best-scored single-frame method and
    of the multi-view method, failures first, plus a typical (median) and the best frame."""
    chosen: dict[int, str] = {}

    def pick(m):
        t = ev.pose.get(m)
        if not t or not t["seqs"]:
            return
        pos = np.where(np.isfinite(t["position_m"]), t["position_m"], np.inf)
        order = np.argsort(-pos, kind="stable")
        failed = [i for i in order if not np.isfinite(pos[i])]
        fin = [i for i in order if np.isfinite(pos[i])]
        for i in failed[:2]:
            chosen.setdefault(t["seqs"][i], f"nopose_{m}")
        for i in fin[:k_worst]:
            chosen.setdefault(t["seqs"][i], f"worst_{m}_{pos[i] * 1e3:.2f}mm")
        if fin:
            chosen.setdefault(t["seqs"][fin[len(fin) // 2]], f"median_{m}")
            chosen.setdefault(t["seqs"][fin[-1]], f"best_{m}")

    single = [m for m in FINAL_ORDER if m not in MULTIVIEW_METHODS and m in ev.pose]
    if single:
        pick(single[0])
    for m in (m for m in FINAL_ORDER if m in MULTIVIEW_METHODS):
        if m in ev.pose and ev.pose[m]["seqs"]:
            pick(m)
            break
    return sorted(chosen.items(), key=lambda kv: kv[0])


def draw_overlay(images: dict, rig, needle: NeedleModel, T_true, estimates: dict,
                 detections: dict, title: str = "", panel_px: int = 480) -> np.ndarray:
    """One picture: for each camera a zoomed crop around the needle with the true arc and
    keypoints (green, crosses), every method's estimated arc (its colour) and the detector's
    keypoints (circles, labelled A..E). ``estimates``: method -> T_ecm_needle;
    ``detections``: camera -> (5, 2) px or None; ``images``: camera -> BGR image or None."""
    import cv2

    arc = needle.sample_arc(64)
    kps = needle.keypoints()
    panels = []
    for cam_name in CAMERAS:
        cam = rig[cam_name]
        img = images.get(cam_name)
        if img is None:
            img = np.zeros((cam.height, cam.width, 3), np.uint8)
        h, w = img.shape[:2]

        def proj(T, pts):
            p = transform_points(cam.T_cam_ecm @ T, pts)
            uv = cam.project(p)
            uv[p[:, 2] <= 0] = np.nan
            return uv

        true_arc, true_kp = proj(T_true, arc), proj(T_true, kps)
        est = {m: proj(T, arc) for m, T in estimates.items() if T is not None}
        det = detections.get(cam_name)
        x0, y0, x1, y1 = crop_box([true_arc, true_kp, det], w, h)
        scale = panel_px / max(x1 - x0, y1 - y0)
        crop = cv2.resize(np.ascontiguousarray(img[y0:y1, x0:x1]),
                          (max(1, int((x1 - x0) * scale)), max(1, int((y1 - y0) * scale))),
                          interpolation=cv2.INTER_LINEAR)
        canvas = np.zeros((panel_px, panel_px, 3), np.uint8)
        canvas[:crop.shape[0], :crop.shape[1]] = crop

        def to_px(uv):
            return np.round((np.asarray(uv) - [x0 - 0.5, y0 - 0.5]) * scale - 0.5).astype(np.int64)

        def polyline(uv, colour, thick):
            ok = np.all(np.isfinite(uv), axis=1)
            if ok.sum() >= 2:
                cv2.polylines(canvas, [to_px(uv[ok]).reshape(-1, 1, 2).astype(np.int32)], False,
                              colour, thick, cv2.LINE_AA)

        polyline(true_arc, TRUTH_BGR, 2)
        for p in true_kp:
            if np.all(np.isfinite(p)):
                cv2.drawMarker(canvas, tuple(int(c) for c in to_px(p)), TRUTH_BGR,
                               cv2.MARKER_CROSS, 14, 2)
        for m, uv in est.items():
            polyline(uv, palette.bgr(palette.method(m)), 1)
        if det is not None:
            for name, p in zip(KEYPOINT_NAMES, np.asarray(det, float).reshape(5, 2)):
                if np.all(np.isfinite(p)):
                    q = tuple(int(c) for c in to_px(p))
                    cv2.circle(canvas, q, 6, DETECTION_BGR, 1, cv2.LINE_AA)
                    cv2.putText(canvas, name, (q[0] + 7, q[1] - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                                DETECTION_BGR, 1, cv2.LINE_AA)
        cv2.putText(canvas, cam_name, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1,
                    cv2.LINE_AA)
        panels.append(canvas)
    body = np.concatenate([panels[0], np.full((panel_px, 4, 3), 255, np.uint8), panels[1]], axis=1)
    rows = [("truth (arc, + keypoints)", TRUTH_BGR), ("detector keypoints (o)", DETECTION_BGR)]
    rows += [(m, palette.bgr(palette.method(m))) for m in estimates]
    head = title.split("\n")
    legend = np.zeros((12 + 20 * len(head) + 20 * ((len(rows) + 2) // 3), body.shape[1], 3), np.uint8)
    for i, line in enumerate(head):
        cv2.putText(legend, line, (8, 18 + 20 * i), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255),
                    1, cv2.LINE_AA)
    for i, (label, colour) in enumerate(rows):
        x, y = 8 + (i % 3) * 300, 22 + 20 * len(head) + (i // 3) * 20
        cv2.line(legend, (x, y - 4), (x + 24, y - 4), colour, 2)
        cv2.putText(legend, label, (x + 30, y), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1,
                    cv2.LINE_AA)
    return np.concatenate([legend, body], axis=0)


def write_overlays(outdir, col: Collected, ev: Evaluation, rig, needle: NeedleModel,
                   load_images: Callable[[int], dict], k_worst: int = 3) -> list[str]:
    """Write ``overlays/NNNNNN_<why>.png`` for the frames ``select_overlay_frames`` picks.
    ``load_images(seq)`` returns {camera: BGR image or None}. Returns the file names."""
    import cv2

    out = Path(outdir) / "overlays"
    out.mkdir(parents=True, exist_ok=True)
    names = []
    for seq, why in select_overlay_frames(ev, k_worst):
        if seq not in ev.T_true:
            continue
        estimates = {m: col.poses.get(m, {}).get(seq).T_ecm_needle
                     for m in ev.pose if col.poses.get(m, {}).get(seq) is not None}
        dets = {}
        for cam in CAMERAS:
            kp = col.keypoints.get((cam, seq))
            dets[cam] = kp.uv if kp is not None and kp.found else None
        errs = []
        for m in estimates:
            t = ev.pose[m]
            if seq in t["seqs"]:
                i = t["seqs"].index(seq)
                errs.append(f"{m} {t['position_m'][i] * 1e3:.2f}mm/"
                            f"{np.degrees(t['orientation_rad'][i]):.1f}deg")
        title = f"frame {seq}  ({why})\n" + "  ".join(errs[:3]) + ("\n" + "  ".join(errs[3:]) if errs[3:] else "")
        try:
            images = load_images(seq)
        except Exception as exc:  # a missing image still gives an overlay on black
            images = {}
            title += f"\n[image not loaded: {exc}]"
        pic = draw_overlay(images, rig, needle, ev.T_true[seq], estimates, dets, title)
        name = f"{seq:06d}_{why}.png"
        cv2.imwrite(str(out / name), pic)
        names.append(name)
    return names
