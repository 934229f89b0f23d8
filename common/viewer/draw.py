"""The viewer's pictures: the paper's Fig. 1 (the endoscope image with the tracked needle drawn
on it), computed with no process and no network.

Conventions: images are BGR uint8; pixel coordinates have their origin at the centre of the
top-left pixel (OpenCV); poses are 4x4 ``T_a_b`` (frame b to frame a, metres). A picture is drawn
on the *downscaled* image: a full-size pixel ``uv`` lands at ``(uv + 0.5) * scale - 0.5``.

What ``draw_fig1`` draws on one camera's image:

- the final pose's projected arc (thick, the method's colour; dashed and labelled AMBIGUOUS
  when the pose is ``ambiguous``) with its keypoints A..E (filled dots, labelled);
- the needle's axes at its origin (x red, y green, z blue, one radius long);
- every other method's arc (thin, its colour);
- the detector's keypoints (yellow circles);
- the ground truth's arc and keypoints (green crosses) when known;
- each instrument's jaw frame (``InstrumentToDraw``): its axes (x red, y green, z blue, 5 mm)
  at the jaws' pivot, labelled with its name; the one that holds the needle ringed and labelled
  "holds".

``draw_detection`` draws a detector's ``Keypoints`` message alone on its image (no pose, no
truth; ``needletrack detect``'s overlays): A..E coloured by score, the centreline, a zoomed inset.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from common import palette
from common.geometry.needle import KEYPOINT_NAMES, NeedleModel
from common.geometry.transforms import inv_T, transform_points

TRUTH_BGR = palette.bgr(palette.TRUTH)
DETECTION_BGR = palette.bgr(palette.DETECTION)
AMBIGUOUS_BGR = palette.bgr(palette.AMBIGUOUS)
AXIS_BGR = tuple(palette.bgr(c) for c in palette.AXES)     # x red, y green, z blue
TEXT_BGR = palette.bgr(palette.TEXT)


def crop_box(uv_list, w, h, min_size=40, margin=0.2):
    """(x0, y0, x1, y1) px of a square crop of a ``w x h`` image around the finite points of
    ``uv_list`` (arrays (N, 2) or None): their extent (at least ``min_size``) widened by
    ``margin`` on each side, clipped to the image; the whole image when there is no point."""
    pts = np.concatenate([u for u in uv_list if u is not None and len(u)], axis=0)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if not len(pts):
        return 0, 0, w, h
    (x0, y0), (x1, y1) = pts.min(0), pts.max(0)
    size = max(x1 - x0, y1 - y0, min_size) * (1 + 2 * margin)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    x0, y0 = int(max(0, cx - size / 2)), int(max(0, cy - size / 2))
    x1, y1 = int(min(w, cx + size / 2)), int(min(h, cy + size / 2))
    return x0, y0, max(x1, x0 + 2), max(y1, y0 + 2)


def method_bgr(method: str) -> tuple:
    """A method's colour (as in the evaluation's figures), BGR."""
    return palette.bgr(palette.method(method))


def fit_size(width: int, height: int, max_width: int, max_height: int) -> tuple[int, int]:
    """The largest (w, h) with the image's aspect that fits ``max_width x max_height``; never
    larger than the image itself."""
    s = min(1.0, max_width / width, max_height / height)
    return max(1, int(round(width * s))), max(1, int(round(height * s)))


def downscale(img: np.ndarray, max_width: int, max_height: int) -> tuple[np.ndarray, float]:
    """(image, scale): ``img`` shrunk to fit (area averaging), and the factor applied."""
    h, w = img.shape[:2]
    w2, h2 = fit_size(w, h, max_width, max_height)
    if (w2, h2) == (w, h):
        return np.ascontiguousarray(img), 1.0
    return cv2.resize(img, (w2, h2), interpolation=cv2.INTER_AREA), w2 / w


_REDUCED = ((8, cv2.IMREAD_REDUCED_COLOR_8), (4, cv2.IMREAD_REDUCED_COLOR_4),
            (2, cv2.IMREAD_REDUCED_COLOR_2))


def decode_small(data, encoding: str, width: int, height: int, max_width: int,
                 max_height: int) -> tuple[np.ndarray, float]:
    """(image, scale): a camera image's bytes (``bgr8`` raw, or a JPEG/PNG file of
    ``width x height``) decoded and shrunk to fit ``max_width x max_height``. A JPEG is decoded
    at 1/2, 1/4 or 1/8 size directly when that is still at least the target (libjpeg's DCT
    scaling: a 1080p frame at 960x540 costs about a quarter of a full decode). Raises
    ValueError on corrupt data."""
    if encoding == "bgr8":
        if len(data) != width * height * 3:
            raise ValueError(f"bgr8 {width}x{height} needs {width * height * 3} bytes, got {len(data)}")
        return downscale(np.frombuffer(data, np.uint8).reshape(height, width, 3), max_width, max_height)
    tw, th = fit_size(width, height, max_width, max_height)
    flag = cv2.IMREAD_COLOR
    if encoding == "jpeg":
        flag = next((f for k, f in _REDUCED if width // k >= tw and height // k >= th), flag)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flag)
    if img is None:
        raise ValueError(f"corrupt {encoding} ({len(data)} bytes)")
    small, s = downscale(img, tw, th)
    return small, small.shape[1] / width


def to_picture(uv, scale: float, offset=(0.0, 0.0)) -> np.ndarray:
    """Full-size pixels -> a picture scaled by ``scale`` and shifted by ``offset`` (px of the
    scaled picture): ``(uv + 0.5) * scale - 0.5 - offset``."""
    return (np.asarray(uv, float) + 0.5) * scale - 0.5 - np.asarray(offset, float)


def project(cam, T_ecm_needle: np.ndarray, pts_needle: np.ndarray, scale: float = 1.0,
            offset=(0.0, 0.0)) -> np.ndarray:
    """(N, 2) pixels in a picture (``to_picture``) of needle-frame points (N, 3) at pose
    ``T_ecm_needle``; NaN for points behind the camera."""
    p = transform_points(cam.T_cam_ecm @ np.asarray(T_ecm_needle, float), pts_needle)
    uv = cam.project(p)
    uv[p[:, 2] <= 1e-6] = np.nan
    return to_picture(uv, scale, offset)


def _ipt(p) -> tuple:
    return int(round(float(p[0]))), int(round(float(p[1])))


def _polyline(img, uv, colour, thick, dashed=False) -> None:
    uv = np.asarray(uv, float)
    ok = np.all(np.isfinite(uv), axis=1) & (np.abs(uv) < 1e5).all(axis=1)
    pts = np.round(uv[ok]).astype(np.int32)
    if len(pts) < 2:
        return
    if not dashed:
        cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, colour, thick, cv2.LINE_AA)
        return
    for i in range(0, len(pts) - 1, 2):
        cv2.line(img, tuple(map(int, pts[i])), tuple(map(int, pts[i + 1])), colour, thick, cv2.LINE_AA)


def _label(img, text, org, colour, size=0.45) -> None:
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, size, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, size, colour, 1, cv2.LINE_AA)


JAW_AXIS_M = 0.005
HOLDER_BGR = palette.bgr(palette.HOLDER)


@dataclass
class InstrumentToDraw:
    """An instrument for one frame: its name, ``T_ecm_jaw`` (m) and whether it holds the needle."""
    name: str
    T_ecm_jaw: np.ndarray
    holds_needle: Optional[bool] = None


def instruments_to_draw(states: dict, T_world_ecm) -> list:
    """A frame's instruments in the ECM frame: ``states`` {name: ``InstrumentState``} (its
    ``T_world_jaw``, ``holds_needle``), by name; none without ``T_world_ecm``."""
    if T_world_ecm is None:
        return []
    T_ecm_world = inv_T(np.asarray(T_world_ecm, float))
    return [InstrumentToDraw(n, T_ecm_world @ np.asarray(m.T_world_jaw, float), m.holds_needle)
            for n, m in sorted(states.items())]


def draw_instruments(out: np.ndarray, scale: float, cam, instruments, offset=(0.0, 0.0), lw: int = 1) -> None:
    """Each instrument's jaw axes and name on ``out`` (in place); the holder ringed."""
    axes = np.vstack([np.zeros(3), np.eye(3) * JAW_AXIS_M])
    for ins in instruments:
        o, *ends = project(cam, ins.T_ecm_jaw, axes, scale, offset)
        if not np.all(np.isfinite(o)) or np.abs(o).max() > 1e5:
            continue
        for e, c in zip(ends, AXIS_BGR, strict=True):
            if np.all(np.isfinite(e)) and np.abs(e).max() < 1e5:
                cv2.arrowedLine(out, _ipt(o), _ipt(e), c, lw, cv2.LINE_AA, tipLength=0.2)
        text = ins.name + (" holds" if ins.holds_needle else "")
        if ins.holds_needle:
            cv2.circle(out, _ipt(o), 6 + 2 * lw, HOLDER_BGR, lw + 1, cv2.LINE_AA)
        _label(out, text, (_ipt(o)[0] + 8, _ipt(o)[1] + 14), HOLDER_BGR if ins.holds_needle else TEXT_BGR)


@dataclass
class PoseToDraw:
    """A method's pose for one frame: ``T_ecm_needle`` (m) and whether it is ambiguous."""
    T_ecm_needle: np.ndarray
    ambiguous: bool = False


def draw_fig1(img: np.ndarray, scale: float, cam, needle: NeedleModel, poses: dict,
              final: Optional[str], keypoints: Optional[np.ndarray] = None,
              T_true: Optional[np.ndarray] = None, caption: str = "", offset=(0.0, 0.0),
              instruments=()) -> np.ndarray:
    """Fig. 1 on a copy of ``img`` (``cam``'s full-size image through ``to_picture(scale, offset)``):
    ``poses`` method -> PoseToDraw, ``final`` the method drawn in full (module docstring),
    ``keypoints`` the detector's (5, 2) full-size pixels (NaN rows: not found), ``T_true`` the
    true ``T_ecm_needle``, ``instruments`` InstrumentToDraw. ``caption`` goes top left (a line per
    newline)."""
    out = img.copy()
    arc, kps = needle.sample_arc(48), needle.keypoints()
    lw = max(1, int(round(2 * max(1.0, out.shape[1] / 960))))
    draw_instruments(out, scale, cam, instruments, offset, max(1, lw // 2))
    if T_true is not None:
        _polyline(out, project(cam, T_true, arc, scale, offset), TRUTH_BGR, 1)
        for p in project(cam, T_true, kps, scale, offset):
            if np.all(np.isfinite(p)):
                cv2.drawMarker(out, _ipt(p), TRUTH_BGR, cv2.MARKER_CROSS, 10, 1)
    for m, pose in poses.items():
        if m != final and pose is not None:
            _polyline(out, project(cam, pose.T_ecm_needle, arc, scale, offset), method_bgr(m), lw,
                      dashed=bool(pose.ambiguous))
    if keypoints is not None:
        for p in to_picture(np.asarray(keypoints, float).reshape(-1, 2), scale, offset):
            if np.all(np.isfinite(p)):
                cv2.circle(out, _ipt(p), 6, DETECTION_BGR, 1, cv2.LINE_AA)
    pose = poses.get(final) if final else None
    if pose is not None:
        colour = method_bgr(final)
        _polyline(out, project(cam, pose.T_ecm_needle, arc, scale, offset), colour, 2 * lw,
                  dashed=bool(pose.ambiguous))
        for name, p in zip(KEYPOINT_NAMES, project(cam, pose.T_ecm_needle, kps, scale, offset), strict=True):
            if np.all(np.isfinite(p)):
                cv2.circle(out, _ipt(p), 2 + lw, colour, -1, cv2.LINE_AA)
                _label(out, name, (_ipt(p)[0] + 6, _ipt(p)[1] - 6), colour)
        axes = np.vstack([np.zeros(3), np.eye(3) * needle.radius_m])
        o, *ends = project(cam, pose.T_ecm_needle, axes, scale, offset)
        if np.all(np.isfinite(o)):
            for e, c in zip(ends, AXIS_BGR, strict=True):
                if np.all(np.isfinite(e)):
                    cv2.arrowedLine(out, _ipt(o), _ipt(e), c, lw, cv2.LINE_AA, tipLength=0.15)
        if pose.ambiguous:
            _label(out, "AMBIGUOUS", (8, out.shape[0] - 10), AMBIGUOUS_BGR, 0.6)
    for i, line in enumerate(caption.split("\n") if caption else ()):
        _label(out, line, (8, 20 + 20 * i), TEXT_BGR, 0.5)
    return out


def fig1_with_zoom(img: np.ndarray, scale: float, cam, needle: NeedleModel, poses: dict,
                   final: Optional[str], keypoints: Optional[np.ndarray] = None,
                   T_true: Optional[np.ndarray] = None, caption: str = "",
                   zoom_frac: float = 0.42, instruments=()) -> np.ndarray:
    """``draw_fig1`` plus, in the top right corner, a zoomed crop around the needle (the final
    pose's arc, else the truth, else the detections) drawn at the zoomed resolution; its box is
    outlined on the picture. Same arguments as ``draw_fig1``; ``zoom_frac``: the inset's width
    over the picture's."""
    out = draw_fig1(img, scale, cam, needle, poses, final, keypoints, T_true, caption, instruments=instruments)
    arc = needle.sample_arc(24)
    pose = poses.get(final) if final else None
    if pose is not None:
        pts = project(cam, pose.T_ecm_needle, arc, scale)
    elif T_true is not None:
        pts = project(cam, T_true, arc, scale)
    elif keypoints is not None:
        pts = to_picture(np.asarray(keypoints, float).reshape(-1, 2), scale)
    else:
        return out
    h, w = img.shape[:2]
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if not len(pts) or not ((pts[:, 0] > 0) & (pts[:, 0] < w) & (pts[:, 1] > 0) & (pts[:, 1] < h)).any():
        return out
    x0, y0, x1, y1 = crop_box([pts], w, h, min_size=24, margin=0.35)
    side = int(w * zoom_frac)
    z = side / max(x1 - x0, y1 - y0)
    if z <= 1.2:
        return out
    crop = cv2.resize(np.ascontiguousarray(img[y0:y1, x0:x1]),
                      (max(1, int(round((x1 - x0) * z))), max(1, int(round((y1 - y0) * z)))),
                      interpolation=cv2.INTER_CUBIC)
    inset = draw_fig1(crop, scale * z, cam, needle, poses, final, keypoints, T_true,
                      f"x{z:.1f}", offset=(x0 * z, y0 * z), instruments=instruments)
    ih, iw = inset.shape[:2]
    ih, iw = min(ih, h - 4), min(iw, w - 4)
    cv2.rectangle(out, (x0, y0), (x1, y1), TEXT_BGR, 1)
    out[2:2 + ih, w - 2 - iw:w - 2] = inset[:ih, :iw]
    cv2.rectangle(out, (w - 3 - iw, 1), (w - 1, 2 + ih), TEXT_BGR, 1)
    return out


def score_bgr(score: float) -> tuple:
    """A detector's score in [0, 1] as a colour: red (0) through yellow (0.5) to green (1), BGR."""
    s = float(np.clip(score if np.isfinite(score) else 0.0, 0.0, 1.0))
    return 0, int(round(220 * min(1.0, 2 * s))), int(round(230 * min(1.0, 2 * (1 - s))))


def _draw_detected(out: np.ndarray, kp, scale: float, offset=(0.0, 0.0), radius: int = 5) -> None:
    """A found ``Keypoints`` message on ``out`` (a picture, ``to_picture(scale, offset)``): its
    centreline (thin, ``DETECTION_BGR``) and A..E as discs coloured by score, labelled."""
    if kp.centreline is not None:
        line = np.asarray(kp.centreline, float)
        if kp.centreline_w is not None:
            line = line[np.asarray(kp.centreline_w, float) > 0]
        _polyline(out, to_picture(line, scale, offset), DETECTION_BGR, 1)
    for name, p, s in zip(KEYPOINT_NAMES, to_picture(np.asarray(kp.uv, float), scale, offset), kp.scores, strict=True):
        if np.all(np.isfinite(p)) and (np.abs(p) < 1e5).all():
            cv2.circle(out, _ipt(p), radius + 1, (0, 0, 0), -1, cv2.LINE_AA)
            cv2.circle(out, _ipt(p), radius, score_bgr(s), -1, cv2.LINE_AA)
            _label(out, name, (_ipt(p)[0] + radius + 3, _ipt(p)[1] - radius - 3), score_bgr(s), 0.5)


def draw_detection(img: np.ndarray, kp, caption: str = "", max_width: int = 1280, max_height: int = 1024,
                   zoom_frac: float = 0.4) -> np.ndarray:
    """One camera image (BGR, full size) with a detector's ``Keypoints`` message drawn on it,
    shrunk to fit ``max_width x max_height``: the keypoints A..E coloured by score
    (``score_bgr``) and labelled, the centreline, and, in the top right corner, a zoomed crop
    of the needle (from the full-size image; ``zoom_frac`` of the picture's width). Not found:
    "no needle" and the reason. ``caption`` goes top left (a line per newline)."""
    out, scale = downscale(img, max_width, max_height)
    out = out.copy()
    h, w = img.shape[:2]
    found = bool(kp.found) and np.isfinite(np.asarray(kp.uv, float)).any()
    if found:
        _draw_detected(out, kp, scale, radius=max(3, int(round(4 * out.shape[1] / 960))))
        x0, y0, x1, y1 = crop_box([np.asarray(kp.uv, float)], w, h, min_size=24, margin=0.35)
        side = int(out.shape[1] * zoom_frac)
        z = side / max(x1 - x0, y1 - y0)
        if z > 1.2 * scale:
            crop = cv2.resize(np.ascontiguousarray(img[y0:y1, x0:x1]),
                              (max(1, int(round((x1 - x0) * z))), max(1, int(round((y1 - y0) * z)))),
                              interpolation=cv2.INTER_CUBIC if z > 1 else cv2.INTER_AREA)
            _draw_detected(crop, kp, z, (x0 * z, y0 * z), radius=6)
            _label(crop, f"x{z / scale:.1f}", (6, crop.shape[0] - 8), TEXT_BGR, 0.5)
            ow = out.shape[1]
            ih, iw = min(crop.shape[0], out.shape[0] - 4), min(crop.shape[1], ow - 4)
            b = to_picture(np.array([[x0, y0], [x1, y1]], float) - 0.5, scale)
            cv2.rectangle(out, _ipt(b[0]), _ipt(b[1]), TEXT_BGR, 1)
            out[2:2 + ih, ow - 2 - iw:ow - 2] = crop[:ih, :iw]
            cv2.rectangle(out, (ow - 3 - iw, 1), (ow - 1, 2 + ih), TEXT_BGR, 1)
    else:
        _label(out, "no needle", (8, out.shape[0] // 2), AMBIGUOUS_BGR, 1.2)
        if kp.reason:
            _label(out, kp.reason[:110], (8, out.shape[0] // 2 + 28), TEXT_BGR, 0.5)
    for i, line in enumerate(caption.split("\n") if caption else ()):
        _label(out, line, (8, 22 + 22 * i), TEXT_BGR, 0.55)
    return out


def side_by_side(left: np.ndarray, right: np.ndarray, gap: int = 4) -> np.ndarray:
    """The two camera pictures next to each other (the right one padded/cropped to the left's
    height), separated by a ``gap``-pixel grey bar."""
    h = left.shape[0]
    r = right[:h]
    if r.shape[0] < h:
        r = np.vstack([r, np.zeros((h - r.shape[0],) + r.shape[1:], np.uint8)])
    return np.hstack([left, np.full((h, gap, 3), 90, np.uint8), r])


def encode_jpeg(img: np.ndarray, quality: int = 80) -> bytes:
    """``img`` (BGR) as a JPEG file's bytes."""
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()
