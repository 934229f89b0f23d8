"""A small needle dataset drawn with OpenCV, in the format of docs/dataset.md: an arc with a
tapered tip and a thread on a textured background. For tests, and as a stand-in when the
simulator is not available."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import yaml

from common.frames import CAMERAS
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T, make_T, rotvec_to_R, transform_points


def _background(rng, h, w):
    base = np.array([rng.uniform(60, 140), rng.uniform(70, 150), rng.uniform(140, 220)], np.float32)
    img = np.zeros((h, w, 3), np.float32)
    for scale, amp in ((max(h, w) / 4, 40), (max(h, w) / 20, 25), (6, 10)):
        n = cv2.resize(rng.random((int(h / scale) + 2, int(w / scale) + 2)).astype(np.float32), (w, h),
                       interpolation=cv2.INTER_CUBIC)
        img += (n[..., None] - 0.5) * amp
    img += base
    return np.clip(img, 0, 255).astype(np.uint8)


def render_synthetic(rig: StereoRig, needle: NeedleModel, T_cam_needle: dict, rng, cam: str,
                     background: np.ndarray) -> np.ndarray:
    """Draw the needle (grey wire, tapered tip at A, dark thread leaving E) over a background."""
    cm = rig[cam]
    img = background.copy()
    T = T_cam_needle[cam]
    ang = np.linspace(*needle.arc_span_rad, 200)
    p = transform_points(T, needle.arc_points(ang))
    uv = cm.project(p)
    width = cm.K[0, 0] * needle.wire_diameter_m / p[:, 2]
    frac = np.linspace(0, 1, len(uv))
    width = width * np.clip(frac / 0.08, 0.15, 1.0)            # taper to the tip A
    # thread: leaves E along the tangent then curls
    a_e = needle.arc_span_rad[1]
    tang = np.array([-np.sin(a_e), np.cos(a_e), 0.0])
    tpts = [needle.arc_points([a_e])[0]]
    d = tang.copy()
    for _ in range(60):
        d = d + rng.normal(0, 0.15, 3) * np.array([1, 1, 0.3])
        d /= np.linalg.norm(d)
        tpts.append(tpts[-1] + 0.0008 * d)
    tuv = cm.project(transform_points(T, np.asarray(tpts)))
    sh = 4  # draw with sub-pixel precision
    cv2.polylines(img, [np.round(tuv * 2 ** sh).astype(np.int32).reshape(-1, 1, 2)], False,
                  (40, 30, 30), max(1, int(round(width.mean() * 0.4))), cv2.LINE_AA, sh)
    for i in range(len(uv) - 1):
        t = max(1, int(round(width[i])))
        shade = 150 + 80 * np.cos(3 * frac[i] + rng.uniform(0, 0.1))
        a = np.round(uv[i] * 2 ** sh).astype(np.int32)
        b = np.round(uv[i + 1] * 2 ** sh).astype(np.int32)
        cv2.line(img, tuple(int(v) for v in a), tuple(int(v) for v in b), (shade, shade, shade + 5), t,
                 cv2.LINE_AA, sh)
    return img


def write_synthetic_dataset(folder, n_frames: int, seed: int = 0, size=(640, 360),
                            n_empty: int = 0, depth_m=(0.08, 0.14)) -> Path:
    """Write a needle dataset of ``n_frames`` stereo frames (the last ``n_empty`` without a
    needle) drawn with OpenCV, following the dataset spec; returns the folder."""
    folder = Path(folder)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    w, h = size
    rig = StereoRig.default(w, h)
    needle = NeedleModel()
    rng = np.random.default_rng(seed)
    meta = {"format": "needle-dataset", "version": 1, "image_size": [w, h],
            "cameras": rig.to_dict(), "needle": needle.to_dict(),
            "source": f"needletrack synthetic OpenCV drawing, seed {seed}"}
    (folder / "dataset.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    T_world_ecm = np.eye(4)
    lines = []
    for i in range(n_frames):
        empty = i >= n_frames - n_empty
        for _ in range(100):
            R = rotvec_to_R(rng.normal(size=3) * 2.0)
            z = rng.uniform(*depth_m)
            uvc = np.array([rng.uniform(0.2, 0.8) * w, rng.uniform(0.2, 0.8) * h])
            Kinv = np.linalg.inv(rig.left.K)
            t_cam = Kinv @ np.array([uvc[0], uvc[1], 1.0]) * z
            T_left_needle = make_T(R, t_cam - R @ np.array([0, needle.radius_m * 0.8, 0]))
            T_ecm_needle = rig.left.T_ecm_cam @ T_left_needle
            Tcn = {c: inv_T(rig[c].T_ecm_cam) @ T_ecm_needle for c in CAMERAS}
            kps = {c: rig[c].project(transform_points(Tcn[c], needle.keypoints())) for c in CAMERAS}
            if all(rig[c].in_image(kps[c]).all() for c in CAMERAS):
                break
        bg = _background(rng, h, w)
        rec = {"index": i, "stamp_ns": i * 33_333_333}
        for c in CAMERAS:
            img = bg.copy() if empty else render_synthetic(rig, needle, Tcn, rng, c, bg)
            name = f"images/{i:06d}_{c}.png"
            cv2.imwrite(str(folder / name), img)
            rec[c] = name
        if not empty:
            T_world_needle = T_world_ecm @ T_ecm_needle
            rec.update({"T_world_ecm": T_world_ecm.tolist(), "T_world_needle": T_world_needle.tolist(),
                        "keypoints": {c: kps[c].tolist() for c in CAMERAS},
                        "visible": {c: [True] * 5 for c in CAMERAS}})
            boxes = {}
            for c in CAMERAS:
                lo, hi = kps[c].min(0), kps[c].max(0)
                boxes[c] = [float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])]
            rec["bbox"] = boxes
        else:
            rec.update({"visible": {c: [False] * 5 for c in CAMERAS}, "bbox": {c: None for c in CAMERAS}})
        lines.append(json.dumps(rec))
    (folder / "frames.jsonl").write_text("\n".join(lines) + "\n")
    return folder
