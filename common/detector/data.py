"""Needle datasets -> training samples for the learned keypoint detector.

Each camera image of a dataset folder (``docs/dataset.md``) becomes one ``ImageRecord``:
the image downscaled for stage 1, a full-resolution region around the needle for stage 2 (so
training never touches the 1080p image again), a needle-free background region (stage-2
negatives), and the ground truth in full-image pixels: keypoints A..E, their visibility, the
projected arc (the centreline target) and the needle's box. Records are cached in one ``.npz``
(no pickle). ``crop_sample`` / ``global_sample`` draw augmented training samples from a record.

A small dataset drawn with OpenCV, for tests: ``common.detector.synthetic``.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from common.detector.model import (
    BOX_UNIT,
    GLOBAL_STRIDE,
    ModelConfig,
    apply_affine,
    crop_affine,
    crop_side,
    global_size,
)
from common.data.dataset import DatasetError  # noqa: F401  (raised here; one class for a bad dataset folder)
from common.frames import CAMERAS
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T, transform_points

ARC_SAMPLES = 96


@dataclass
class ImageRecord:
    """One camera image prepared for training (all coordinates in full-image pixels)."""

    small: np.ndarray            # (hs, ws, 3) uint8, the image downscaled by global_downscale
    region: np.ndarray           # (hr, wr, 3) uint8 full-res region around the needle
    origin: np.ndarray           # (2,) region's top-left pixel in the image
    neg: np.ndarray              # (hn, wn, 3) uint8 full-res region without the needle
    neg_origin: np.ndarray       # (2,)
    kp: np.ndarray               # (5, 2) keypoints A..E (NaN if unknown)
    vis: np.ndarray              # (5,) bool
    arc: np.ndarray              # (ARC_SAMPLES, 2) projected arc A..E (NaN where not visible)
    box: np.ndarray              # (4,) cx, cy, w, h; NaN when no needle is visible
    image_size: tuple            # (w, h)
    frame: int = 0
    camera: str = "left"

    @property
    def has_needle(self) -> bool:
        return bool(np.isfinite(self.box).all())


# ---------------------------------------------------------------- reading a dataset folder

def read_dataset(folder) -> tuple[dict, list[dict]]:
    """(dataset.yaml as a dict, list of frame dicts) of a dataset folder, with the checks that
    training needs; raises DatasetError naming the file, line and field."""
    folder = Path(folder)
    meta_path = folder / "dataset.yaml"
    if not meta_path.is_file():
        raise DatasetError(f"{meta_path}: missing (is {folder} a needle dataset folder?)")
    try:
        meta = yaml.safe_load(meta_path.read_text())
    except yaml.YAMLError as exc:
        raise DatasetError(f"{meta_path}: not valid YAML: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") != "needle-dataset":
        raise DatasetError(f"{meta_path}: field 'format' must be 'needle-dataset'")
    if meta.get("version") != 1:
        raise DatasetError(f"{meta_path}: field 'version': unsupported {meta.get('version')!r} (known: 1)")
    for key in ("image_size", "cameras"):
        if key not in meta:
            raise DatasetError(f"{meta_path}: field '{key}' missing")
    frames_path = folder / "frames.jsonl"
    if not frames_path.is_file():
        raise DatasetError(f"{frames_path}: missing")
    frames = []
    with open(frames_path) as f:
        for ln, line in enumerate(f, 1):
            if not line.strip():
                continue
            try:
                fr = json.loads(line)
            except json.JSONDecodeError as exc:
                raise DatasetError(f"{frames_path}:{ln}: not valid JSON: {exc}") from None
            for key in ("index", "left", "right"):
                if key not in fr:
                    raise DatasetError(f"{frames_path}:{ln}: field '{key}' missing")
            fr["_line"] = ln
            frames.append(fr)
    return meta, frames


def true_arc_pixels(rig: StereoRig, needle: NeedleModel, cam: str, fr: dict) -> np.ndarray | None:
    """The true arc (``ARC_SAMPLES`` points) in camera ``cam``'s image, px, from the frame's
    true poses; None when the frame has none or the arc is behind the camera."""
    if fr.get("T_world_needle") is None or fr.get("T_world_ecm") is None:
        return None
    T_cam_needle = (inv_T(rig[cam].T_ecm_cam) @ inv_T(np.asarray(fr["T_world_ecm"], float))
                    @ np.asarray(fr["T_world_needle"], float))
    p = transform_points(T_cam_needle, needle.sample_arc(ARC_SAMPLES))
    if np.any(p[:, 2] <= 1e-6):
        return None
    return rig[cam].project(p)


JAW_CENTRE_M = 0.005   # the jaws' middle, along their z from the pivot (the dataset's T_world_jaw)


def jaw_pixels(rig: StereoRig, cam: str, fr: dict) -> np.ndarray:
    """(n, 2) pixels of the middle of each instrument's jaws in camera ``cam`` (in front of it),
    from the frame's true jaw poses where it has them (``T_world_jaw_truth``: a reported pose may
    be millimetres off), else the reported ones; (0, 2) without instruments or an endoscope pose."""
    if fr.get("T_world_ecm") is None or not fr.get("instruments"):
        return np.zeros((0, 2))
    T_cam_world = inv_T(rig[cam].T_ecm_cam) @ inv_T(np.asarray(fr["T_world_ecm"], float))
    pts = []
    for inst in fr["instruments"].values():
        T = inst.get("T_world_jaw_truth") or inst.get("T_world_jaw") if isinstance(inst, dict) else None
        if T is not None:
            pts.append(transform_points(T_cam_world @ np.asarray(T, float), np.array([[0.0, 0.0, JAW_CENTRE_M]]))[0])
    pts = np.asarray([p for p in pts if p[2] > 1e-3]).reshape(-1, 3)
    return rig[cam].project(pts) if len(pts) else np.zeros((0, 2))


def _arc_through(kp: np.ndarray) -> np.ndarray:
    """Arc samples through the 5 keypoints (Catmull-Rom), when no pose is given."""
    t = np.linspace(0, 4, ARC_SAMPLES)
    P = np.vstack([2 * kp[0] - kp[1], kp, 2 * kp[4] - kp[3]])
    out = []
    for ti in t:
        i = min(int(ti), 3)
        u = ti - i
        p0, p1, p2, p3 = P[i], P[i + 1], P[i + 2], P[i + 3]
        out.append(0.5 * (2 * p1 + (-p0 + p2) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u * u
                          + (-p0 + 3 * p1 - 3 * p2 + p3) * u ** 3))
    return np.asarray(out)


def make_record(img: np.ndarray, kp, vis, arc, cfg: ModelConfig, rng: np.random.Generator,
                frame: int = 0, camera: str = "left", bbox=None, arc_seen=None, jaws=None,
                jaw_share: float = 0.0) -> ImageRecord:
    """ImageRecord of one BGR image and its ground truth (kp (5,2) or None, vis (5,),
    arc (P,2) or None; full-image pixels). ``arc_seen`` (N,) bool: which of N points equally
    spaced along the arc the render shows (the dataset's ``arc_seen``); without it an arc point
    counts as seen when its nearest keypoint is. Without ``arc`` the arc goes through the keypoints
    where all five are placed (seen or hidden: a hand label's). The needle is there (a box, a positive) when
    ``PRESENT_ARC_SHARE`` of the arc is seen (without ``arc_seen``: two keypoints). ``bbox``
    [x0, y0, x1, y1]: the needle's box when no keypoints give one (a record for distillation
    only, ``load_records(boxes_only=True)``). ``jaws`` (n, 2): pixels of the instruments' jaws
    (``jaw_pixels``); in ``jaw_share`` of the records that have one away from the needle, the
    negative region is centred on it (a hard negative: a jaw must not pass for a needle)."""
    h, w = img.shape[:2]
    ws, hs, _, _ = global_size(cfg, w, h)
    small = cv2.resize(img, (ws, hs), interpolation=cv2.INTER_AREA)
    kp = np.full((5, 2), np.nan) if kp is None else np.asarray(kp, float).reshape(5, 2)
    vis = np.zeros(5, bool) if vis is None else np.asarray(vis, bool).reshape(5)
    inside = lambda p: (p[:, 0] >= -0.5) & (p[:, 0] <= w - 0.5) & (p[:, 1] >= -0.5) & (p[:, 1] <= h - 0.5)
    vis = vis & np.isfinite(kp).all(1) & inside(np.nan_to_num(kp, nan=-1e9))
    if arc is None and (vis.all() or (np.isfinite(kp).all() and vis.sum() >= 2)):
        arc = _arc_through(kp)      # no pose: through the keypoints (a hand label places hidden ones too)
    if arc is not None:
        arc = np.asarray(arc, float).copy()
        if arc_seen is not None:
            seen = np.asarray(arc_seen)
            if seen.dtype != bool or seen.ndim != 1 or len(seen) < 2:
                raise ValueError(f"arc_seen: expected a list of at least 2 booleans, got {arc_seen!r}"[:120])
            seen = seen[np.round(np.linspace(0, len(seen) - 1, len(arc))).astype(int)]
        else:   # an arc sample is seen when its nearest keypoint is
            seen = vis[np.clip(np.round(np.linspace(0, 4, len(arc))).astype(int), 0, 4)]
        arc[~(inside(arc) & seen)] = np.nan
    else:
        arc = np.full((ARC_SAMPLES, 2), np.nan)
    good = np.isfinite(arc).all(1)
    present = vis.sum() >= 2 if arc_seen is None else _arc_present(good)
    if good.sum() >= 2 and present:
        lo, hi = arc[good].min(0), arc[good].max(0)
        box = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[0] - lo[0] + 4, hi[1] - lo[1] + 4])
    elif bbox is not None and np.isfinite(np.asarray(bbox, float)).all():
        x0, y0, x1, y1 = (float(v) for v in bbox)
        box = np.array([(x0 + x1) / 2, (y0 + y1) / 2, x1 - x0 + 4, y1 - y0 + 4])
    else:
        box = np.full(4, np.nan)
    # positive region: enough for the crop jitter and rotation of crop_sample
    if np.isfinite(box).all():
        side = int(2.6 * max(box[2], box[3]) + 48)
        x0, y0 = int(round(box[0] - side / 2)), int(round(box[1] - side / 2))
    else:
        side, x0, y0 = 0, 0, 0
    region, origin = cut_square(img, x0, y0, side)
    # negative region: a random square away from the needle's box (or one on a jaw, jaw_share)
    nside = int(rng.uniform(96, 320))

    def far(nx0, ny0):
        if not np.isfinite(box).all():
            return True
        far_x = nx0 > box[0] + box[2] / 2 + 8 or nx0 + nside < box[0] - box[2] / 2 - 8
        far_y = ny0 > box[1] + box[3] / 2 + 8 or ny0 + nside < box[1] - box[3] / 2 - 8
        return far_x or far_y
    on_jaw = None
    if jaw_share > 0 and jaws is not None and len(jaws) and rng.random() < jaw_share:
        inside_jaws = [j for j in np.asarray(jaws, float).reshape(-1, 2) if inside(j[None])[0]]
        if inside_jaws:
            j = inside_jaws[int(rng.integers(len(inside_jaws)))]
            nside = int(rng.uniform(96, 160))   # small: crop_sample's negative crops centre within it
            jx0, jy0 = int(round(j[0] - nside / 2)), int(round(j[1] - nside / 2))
            on_jaw = (jx0, jy0) if far(jx0, jy0) else None
    if on_jaw is not None:
        nx0, ny0 = on_jaw
    else:
        for _ in range(20):
            nx0 = int(rng.integers(-nside // 4, max(1, w - 3 * nside // 4)))
            ny0 = int(rng.integers(-nside // 4, max(1, h - 3 * nside // 4)))
            if far(nx0, ny0):
                break
        else:
            nside = 0
    neg, neg_origin = cut_square(img, nx0, ny0, nside)
    return ImageRecord(small, region, origin, neg, neg_origin, kp, vis, arc.astype(np.float32),
                       box, (w, h), frame, camera)


PRESENT_ARC_SHARE = 0.1
"""The share of the arc that must be seen for a needle to be there (a positive sample): less is
"no needle" (issue 34: under 10% seen, "no needle" or only unsure keypoints)."""


def _arc_present(seen: np.ndarray) -> bool:
    """Whether the seen arc samples (bool, over the whole arc) make a needle: PRESENT_ARC_SHARE
    of them, and at least two."""
    n = int(np.count_nonzero(seen))
    return n >= 2 and n >= PRESENT_ARC_SHARE * len(seen)


def cut_square(img, x0, y0, side):
    """Sub-image [x0, x0+side) x [y0, y0+side) clipped to the image; (pixels, top-left)."""
    h, w = img.shape[:2]
    xa, ya = max(0, x0), max(0, y0)
    xb, yb = min(w, x0 + side), min(h, y0 + side)
    if xb <= xa or yb <= ya:
        return np.zeros((0, 0, 3), np.uint8), np.zeros(2)
    return np.ascontiguousarray(img[ya:yb, xa:xb]), np.array([xa, ya], float)


def load_records(folder, cfg: ModelConfig, seed: int = 0, max_frames: int | None = None,
                 progress: bool = True, boxes_only: bool = False, jaw_share: float = 0.0) -> list[ImageRecord]:
    """All camera images of a dataset folder as ImageRecords (both cameras per frame);
    ``jaw_share``: of the negative regions, the share centred on an instrument's jaws (``make_record``).
    ``boxes_only``: the images whose frame gives a ``bbox`` for the camera, with that box and no
    keypoints: inputs for distillation (``train``'s teacher), never targets."""
    from common.progress import progress_bar
    folder = Path(folder)
    meta, frames = read_dataset(folder)
    try:
        rig = StereoRig.from_dict(meta["cameras"], meta["image_size"])
        needle = NeedleModel.from_dict(meta.get("needle") or {})
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{folder / 'dataset.yaml'}: field 'cameras' or 'needle': {exc}") from None
    if max_frames:
        frames = frames[:max_frames]
    rng = np.random.default_rng(seed)
    out = []
    for fr in progress_bar(frames, desc=f"reading {folder.name}", unit="frame", show=progress):
        for cam in CAMERAS:
            box = (fr.get("bbox") or {}).get(cam)
            if boxes_only and box is None:
                continue
            path = folder / fr[cam]
            img = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if img is None:
                raise DatasetError(f"{folder / 'frames.jsonl'}:{fr['_line']}: field '{cam}': "
                                   f"cannot read image {path}")
            if boxes_only:
                try:
                    out.append(make_record(img, None, None, None, cfg, rng, int(fr["index"]), cam, bbox=box))
                except (ValueError, TypeError) as exc:
                    raise DatasetError(f"{folder / 'frames.jsonl'}:{fr['_line']}: field 'bbox' of {cam}: "
                                       f"{exc}") from None
                continue
            kps = (fr.get("keypoints") or {}).get(cam)
            viss = (fr.get("visible") or {}).get(cam)
            if kps is not None and viss is None:
                viss = [True] * 5
            arc = true_arc_pixels(rig, needle, cam, fr)
            seen = (fr.get("arc_seen") or {}).get(cam)
            try:
                jaws = jaw_pixels(rig, cam, fr) if jaw_share > 0 else None
                out.append(make_record(img, kps, viss, arc, cfg, rng, int(fr["index"]), cam, arc_seen=seen,
                                       jaws=jaws, jaw_share=jaw_share))
            except (ValueError, TypeError) as exc:
                raise DatasetError(f"{folder / 'frames.jsonl'}:{fr['_line']}: field 'keypoints'/"
                                   f"'visible'/'arc_seen' of {cam}: {exc}") from None
    return out


# ---------------------------------------------------------------- cache (npz, no pickle)

_ARRAYS = ("small", "region", "neg")


def save_records(path, records: list[ImageRecord]) -> None:
    """Write records to one .npz: image arrays concatenated flat, with their shapes."""
    data = {}
    for name in _ARRAYS:
        arrs = [getattr(r, name) for r in records]
        data[name + "_shape"] = np.array([a.shape for a in arrs], np.int64).reshape(len(arrs), 3)
        data[name + "_flat"] = (np.concatenate([a.reshape(-1) for a in arrs]) if arrs
                                else np.zeros(0, np.uint8))
    for name in ("origin", "neg_origin", "kp", "vis", "arc", "box"):
        data[name] = np.stack([getattr(r, name) for r in records]) if records else np.zeros(0)
    data["image_size"] = np.array([r.image_size for r in records], np.int64)
    data["frame"] = np.array([r.frame for r in records], np.int64)
    data["camera"] = np.array([CAMERAS.index(r.camera) for r in records], np.int64)
    tmp = str(path) + ".tmp.npz"
    np.savez(tmp, **data)
    os.replace(tmp, path)


def load_cached(path) -> list[ImageRecord]:
    """Records written by ``save_records`` (each array read from the file once: an ``NpzFile``
    reads a member anew on every subscript)."""
    with np.load(path, allow_pickle=False) as z:
        a = {k: z[k] for k in z.files}
    n = len(a["frame"])
    parts = {}
    for name in _ARRAYS:
        shapes, flat = a[name + "_shape"], a[name + "_flat"]
        offs = np.concatenate([[0], np.cumsum(shapes.prod(1))])
        parts[name] = [flat[offs[i]:offs[i + 1]].reshape(shapes[i]) for i in range(n)]
    return [ImageRecord(parts["small"][i], parts["region"][i], a["origin"][i], parts["neg"][i],
                        a["neg_origin"][i], a["kp"][i], a["vis"][i].astype(bool), a["arc"][i],
                        a["box"][i], tuple(int(v) for v in a["image_size"][i]), int(a["frame"][i]),
                        CAMERAS[int(a["camera"][i])]) for i in range(n)]


# ---------------------------------------------------------------- augmentation

@dataclass
class AugConfig:
    """Training-time augmentation (the paper's flips and colour changes, plus crop jitter)."""

    shift: float = 0.12          # crop centre jitter, fraction of the crop side
    scale: float = 0.25          # crop side jitter, log-uniform +-
    rotate: bool = True          # any in-plane rotation of the crop
    flip: float = 0.5            # probability of a left-right mirror
    neg_prob: float = 0.15       # fraction of stage-2 samples that are needle-free crops
    brightness: float = 35.0     # +- added intensity
    contrast: float = 0.35       # gain 1 +- contrast
    colour: float = 0.12         # per-channel gain 1 +- colour
    blur: float = 0.3            # probability of a Gaussian blur (sigma 0.3 .. 1.2 px)
    noise: float = 6.0           # max Gaussian noise sigma (intensity levels)
    jpeg: float = 0.2            # probability of JPEG re-compression (quality 55 .. 95)
    hue: float = 0.0             # probability of turning the hue by any angle (colours no render has)
    motion_blur: float = 0.0     # probability of a linear motion blur of a stage-2 crop ...
    motion_blur_px: float = 6.0  # ... up to this long in full-image px, any direction (a needle at
                                 # 20 mm/s or 90 deg/s, 10-16 cm away, over a 1/60 s exposure)
    global_window: tuple = (0, 0)  # stage 1 trains on random (w, h) windows of the downscaled
                                   # image, multiples of 8 (0 = the whole image): cheaper steps
    window_needle: float = 0.7   # probability that a window holds the needle's centre

    @classmethod
    def from_dict(cls, d: dict | None) -> "AugConfig":
        d = d or {}
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"augment: unknown field(s) {sorted(unknown)}")
        return cls(**d)


def motion_blur(img: np.ndarray, length_px: float, angle_rad: float) -> np.ndarray:
    """A linear motion blur: the mean of the image over a ``length_px`` segment at ``angle_rad``
    (an exposure during which the scene moves uniformly that far)."""
    n = int(np.ceil(length_px)) | 1
    if n < 2 or length_px < 1.0:
        return img
    k = np.zeros((n, n), np.float32)
    c = (n - 1) / 2.0
    d = np.array([np.cos(angle_rad), np.sin(angle_rad)]) * (length_px - 1) / 2.0
    cv2.line(k, (int(round(c - d[0])), int(round(c - d[1]))), (int(round(c + d[0])), int(round(c + d[1]))), 1.0, 1,
             cv2.LINE_AA)
    return cv2.filter2D(img, -1, k / max(k.sum(), 1e-6), borderType=cv2.BORDER_REPLICATE)


def turn_hue(img: np.ndarray, angle_deg: float) -> np.ndarray:
    """The BGR uint8 image with every colour's hue turned by ``angle_deg`` (saturation and value
    kept, so a white wire stays white; OpenCV's 256-step full hue circle)."""
    hsv = cv2.cvtColor(img, cv2.COLOR_BGR2HSV_FULL)
    hsv[..., 0] = ((hsv[..., 0].astype(np.int32) + int(round(angle_deg * 256 / 360))) % 256).astype(np.uint8)
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR_FULL)


def photometric(img: np.ndarray, aug: AugConfig, rng: np.random.Generator) -> np.ndarray:
    """Random hue, brightness, contrast, colour balance, blur, noise and JPEG on a uint8 BGR image."""
    if aug.hue > 0 and rng.random() < aug.hue:
        img = turn_hue(img, rng.uniform(0, 360))
    x = img.astype(np.float32)
    gain = (1 + rng.uniform(-aug.contrast, aug.contrast)) * (1 + rng.uniform(-aug.colour, aug.colour, 3))
    mean = x.mean()
    x = (x - mean) * gain + mean + rng.uniform(-aug.brightness, aug.brightness)
    if rng.random() < aug.blur:
        x = cv2.GaussianBlur(x, (0, 0), rng.uniform(0.3, 1.2))
    if aug.noise > 0:
        x = x + rng.normal(0, rng.uniform(0, aug.noise), x.shape).astype(np.float32)
    out = np.clip(x, 0, 255).astype(np.uint8)
    if rng.random() < aug.jpeg:
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(rng.uniform(55, 95))])
        if ok:
            out = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    return out


def crop_from(region: np.ndarray, origin: np.ndarray, M_img_to_crop: np.ndarray, crop: int) -> np.ndarray:
    """Warp a stored region (top-left ``origin`` in the image) into the crop of M (image -> crop)."""
    M = M_img_to_crop.copy()
    M[:, 2] += M[:, :2] @ origin
    if region.size == 0:
        return np.zeros((crop, crop, 3), np.uint8)
    return cv2.warpAffine(region, M, (crop, crop), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


OCCLUDED_WEIGHT = 0.3
"""A hidden keypoint's weight in the keypoint loss (a seen one's: 1), in [0, 1): it is still learnt
from the arc's shape, and the loss tells it from a seen one by the weight under 1
(``train.losses``' ``hidden_sigma``). The training configuration's ``train.occluded_weight``."""


def crop_sample(rec: ImageRecord, cfg: ModelConfig, aug: AugConfig | None, rng: np.random.Generator,
                negative: bool | None = None, occluded_weight: float = OCCLUDED_WEIGHT):
    """One stage-2 training sample: (crop uint8 HxWx3, kp_cells (5,2), kp_weight (5,),
    arc_cells (P,2) or None, presence 0/1). With ``aug`` None: the ground-truth box, no jitter."""
    c = cfg.crop
    s = cfg.out_stride
    if negative is None:
        negative = (not rec.has_needle) or (aug is not None and rng.random() < aug.neg_prob)
    if negative:
        src, org = (rec.neg, rec.neg_origin) if rec.neg.size else (rec.region, rec.origin)
        if src.size == 0:
            src, org = rec.small, np.zeros(2)
        hh, ww = src.shape[:2]
        side = float(np.clip(rng.uniform(cfg.crop_min, 300), 8, max(8, max(hh, ww))))
        cx, cy = org[0] + rng.uniform(0, ww), org[1] + rng.uniform(0, hh)
        M = crop_affine(cx, cy, side, c, rng.uniform(-np.pi, np.pi), bool(rng.random() < 0.5))
        img = crop_from(src, org, M, c)
        if aug is not None:
            img = photometric(img, aug, rng)
        return img, np.zeros((5, 2), np.float32), np.zeros(5, np.float32), None, 0.0
    cx, cy, bw, bh = rec.box
    side = crop_side(cfg, bw, bh)
    angle, flip = 0.0, False
    if aug is not None:
        side *= float(np.exp(rng.uniform(-aug.scale, aug.scale)))
        side = max(side, cfg.crop_min * 0.8)
        cx += rng.uniform(-aug.shift, aug.shift) * side
        cy += rng.uniform(-aug.shift, aug.shift) * side
        angle = rng.uniform(-np.pi, np.pi) if aug.rotate else 0.0
        flip = bool(rng.random() < aug.flip)
    M = crop_affine(cx, cy, side, c, angle, flip)
    img = crop_from(rec.region, rec.origin, M, c)
    if aug is not None:
        if aug.motion_blur > 0 and rng.random() < aug.motion_blur:
            img = motion_blur(img, rng.uniform(0, aug.motion_blur_px) * c / side, rng.uniform(0, np.pi))
        img = photometric(img, aug, rng)
    kp_c = apply_affine(M, np.nan_to_num(rec.kp, nan=-1e6))
    in_crop = np.isfinite(rec.kp).all(1) & (kp_c >= -0.5).all(1) & (kp_c <= c - 0.5).all(1)
    in_image = ((rec.kp[:, 0] >= -0.5) & (rec.kp[:, 0] <= rec.image_size[0] - 0.5)
                & (rec.kp[:, 1] >= -0.5) & (rec.kp[:, 1] <= rec.image_size[1] - 0.5))
    # occluded points are still learnt (from the arc's shape), with a lower weight
    valid = np.where(rec.vis, 1.0, np.where(in_image, occluded_weight, 0.0)) * in_crop
    kp_cells = (kp_c - (s - 1) / 2.0) / s
    good = np.isfinite(rec.arc).all(1)
    arc_cells = None
    if good.sum() >= 2:
        # the unseen samples stay NaN: the centreline target breaks there (centreline_target)
        arc_cells = (apply_affine(M, np.nan_to_num(rec.arc, nan=0.0)) - (s - 1) / 2.0) / s
        arc_cells[~good] = np.nan
    in_crop_arc = good.copy()
    if arc_cells is not None:
        in_crop_arc &= (arc_cells >= -0.5).all(1) & (arc_cells <= c / s - 0.5).all(1)
    presence = 1.0 if (valid >= 1.0).sum() >= 2 or _arc_present(in_crop_arc) else 0.0
    return img, kp_cells.astype(np.float32), valid.astype(np.float32), arc_cells, presence


def global_input(small: np.ndarray) -> np.ndarray:
    """Pad a downscaled image (replicating its border) so that both sides are multiples of 8."""
    h, w = small.shape[:2]
    ph, pw = (-h) % 8, (-w) % 8
    if ph or pw:
        small = cv2.copyMakeBorder(small, 0, ph, 0, pw, cv2.BORDER_REPLICATE)
    return small


def _global_window(img: np.ndarray, box: np.ndarray, ds: int, aug: AugConfig, rng):
    """A random ``aug.global_window`` of the downscaled image and the box (cx, cy, w, h in
    full-image pixels) in that window's full-resolution pixels; NaN if its centre falls outside."""
    ww, wh = (int(v) for v in aug.global_window)
    h, w = img.shape[:2]
    if ww <= 0 or wh <= 0 or (ww >= w and wh >= h):
        return img, box
    ww, wh = min(ww, w), min(wh, h)
    if np.isfinite(box).all() and rng.random() < aug.window_needle:
        c = box[:2] / ds   # the window holds the centre, anywhere but its outer 8 px
        x0 = int(np.clip(rng.uniform(c[0] - ww + 8, c[0] - 8), 0, w - ww))
        y0 = int(np.clip(rng.uniform(c[1] - wh + 8, c[1] - 8), 0, h - wh))
    else:
        x0, y0 = int(rng.integers(0, w - ww + 1)), int(rng.integers(0, h - wh + 1))
    box = box.copy()
    box[:2] -= (x0 * ds, y0 * ds)
    if np.isfinite(box).all() and not (0 <= box[0] < ww * ds and 0 <= box[1] < wh * ds):
        box[:] = np.nan
    return img[y0:y0 + wh, x0:x0 + ww], box


def global_sample(rec: ImageRecord, cfg: ModelConfig, aug: AugConfig | None, rng: np.random.Generator):
    """One stage-1 sample: (padded small image uint8, heat target (hc, wc), reg target (4, hc, wc),
    reg mask (hc, wc)). Targets: CenterNet Gaussian at the box centre; log size; sub-cell offset."""
    img = rec.small
    box = rec.box.copy()
    W, H = rec.image_size
    _, _, ds, box_scale = global_size(cfg, W, H)
    if aug is not None:
        if rng.random() < 0.5:
            img = img[:, ::-1]
            box[0] = (W - 1) - box[0]
        if rng.random() < 0.5:
            img = img[::-1]
            box[1] = (H - 1) - box[1]
        img, box = _global_window(img, box, ds, aug, rng)
        img = photometric(np.ascontiguousarray(img), aug, rng)
    img = global_input(np.ascontiguousarray(img))
    hc, wc = img.shape[0] // GLOBAL_STRIDE, img.shape[1] // GLOBAL_STRIDE
    heat = np.zeros((hc, wc), np.float32)
    reg = np.zeros((4, hc, wc), np.float32)
    mask = np.zeros((hc, wc), np.float32)
    if np.isfinite(box).all():
        cell = GLOBAL_STRIDE * ds
        u = (box[0] - (cell - 1) / 2.0) / cell
        v = (box[1] - (cell - 1) / 2.0) / cell
        iu, iv = int(np.clip(round(u), 0, wc - 1)), int(np.clip(round(v), 0, hc - 1))
        sig = max(0.7, max(box[2], box[3]) / cell / 4.0)
        yy, xx = np.mgrid[0:hc, 0:wc]
        heat = np.exp(-((xx - iu) ** 2 + (yy - iv) ** 2) / (2 * sig * sig)).astype(np.float32)
        heat[iv, iu] = 1.0
        unit = BOX_UNIT * box_scale
        reg[:, iv, iu] = [np.log(max(box[2], 4) / unit), np.log(max(box[3], 4) / unit), u - iu, v - iv]
        mask[iv, iu] = 1.0
    return img, heat, reg, mask
