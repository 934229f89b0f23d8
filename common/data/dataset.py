"""Reader, writer and checks of the needle dataset format, version 1 (``docs/dataset.md``).

``Dataset(path)`` loads any folder that follows the spec (PNG or JPEG, optional fields missing or
null, no ``ecm`` section) and raises ``DatasetError`` naming the file, line and field of the first
thing that breaks it. ``DatasetWriter`` writes folders; ``check_dataset`` runs the spec's
consistency checks (ground-truth projection, FK of the joints, image files).
Images are returned as (h, w, 3) uint8 BGR arrays, whatever the file holds.
"""
from __future__ import annotations

import json
import math
import os
import shutil
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np
import yaml

from common.errors import NeedletrackError
from common.frames import CAMERAS
from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import EcmArm
from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T, pose_error, transform_points
from common.data.instruments import T_jaw_needle, instruments_json, parse_instruments
from common.data.values import _Bad, _bools, _int, _matrix, _num, _rigid, _vector  # noqa: F401
from common.runtime.limits import (
    InputLimitError,
    compose_yaml,
    describe_path,
    inside,
    load_yaml,
    read_image_file,
)

FORMAT = "needle-dataset"
VERSION = 1
META_FILE = "dataset.yaml"
FRAMES_FILE = "frames.jsonl"
MAX_META_BYTES = 1 << 20           # dataset.yaml is a few KB
IMAGE_EXTS = (".png", ".jpg", ".jpeg")
_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)


class DatasetError(NeedletrackError, ValueError):
    """A folder that breaks the dataset spec; the message names file, line and field."""


def _where(file: str, line: Optional[int], fieldname: str) -> str:
    return f"{file}:{line}: {fieldname}" if line is not None else f"{file}: {fieldname}"


# ---------------------------------------------------------------- dataset.yaml

@dataclass
class DatasetMeta:
    """What is constant over a folder (dataset.yaml)."""

    image_size: tuple            # (width, height) px
    rig: StereoRig
    needle: NeedleModel
    arm: Optional[EcmArm] = None
    source: Optional[str] = None

    def to_dict(self) -> dict:
        d = {"format": FORMAT, "version": VERSION, "image_size": [int(self.image_size[0]), int(self.image_size[1])],
             "cameras": self.rig.to_dict(), "needle": self.needle.to_dict()}
        if self.arm is not None:
            d["ecm"] = self.arm.to_dict()
        if self.source is not None:
            d["source"] = self.source
        return d


def _yaml_lines(text: str) -> dict:
    """Map key paths (tuples) of a YAML document to their 1-based line numbers."""
    lines = {}
    try:
        root = compose_yaml(text)         # parse_meta has checked the alias budget
    except (yaml.YAMLError, InputLimitError):
        return lines
    seen = set()

    def walk(node, path):
        if id(node) in seen:              # an alias: its place is that of its anchor
            return
        seen.add(id(node))
        lines[path] = node.start_mark.line + 1
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                walk(v, path + (str(k.value),))
                lines[path + (str(k.value),)] = k.start_mark.line + 1
        elif isinstance(node, yaml.SequenceNode):
            for i, v in enumerate(node.value):
                walk(v, path + (i,))

    if root is not None:
        walk(root, ())
    return lines


def parse_meta(text: str, file: str = META_FILE) -> DatasetMeta:
    """Parse and validate dataset.yaml text."""
    try:
        d = load_yaml(text, file)
    except InputLimitError as exc:
        raise DatasetError(str(exc)) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise DatasetError(_where(file, line, f"not valid YAML ({getattr(exc, 'problem', exc)})")) from None
    lines = _yaml_lines(text)

    def fail(path: tuple, msg: str):
        line = None
        for k in range(len(path), -1, -1):
            if path[:k] in lines:
                line = lines[path[:k]]
                break
        name = ".".join(str(p) for p in path) or "(document)"
        raise DatasetError(_where(file, line, f"{name}: {msg}"))

    def get(mapping: dict, path: tuple, required: bool = True):
        key = path[-1]
        if not isinstance(mapping, dict):
            fail(path[:-1], "expected a mapping")
        if key not in mapping or mapping[key] is None:
            if required:
                fail(path, "required field missing")
            return None
        return mapping[key]

    def parse(path, value, fn, *args):
        try:
            return fn(value, *args)
        except _Bad as exc:
            fail(path, str(exc))

    if not isinstance(d, dict):
        fail((), "expected a mapping at the top level")
    if get(d, ("format",)) != FORMAT:
        fail(("format",), f"must be {FORMAT!r}, got {d.get('format')!r}")
    version = get(d, ("version",))
    if isinstance(version, bool) or version != VERSION:
        fail(("version",), f"unknown version {version!r} (this reader knows version {VERSION})")
    size = parse(("image_size",), get(d, ("image_size",)), _vector, 2)
    if np.any(size <= 0) or np.any(size != np.round(size)):
        fail(("image_size",), f"must be two positive integers [width, height], got {size.tolist()}")
    w, h = int(size[0]), int(size[1])
    cams = get(d, ("cameras",))
    parsed = {}
    for c in CAMERAS:
        cd = get(cams, ("cameras", c))
        K = parse(("cameras", c, "K"), get(cd, ("cameras", c, "K")), _matrix, 3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            fail(("cameras", c, "K"), f"not a camera matrix [[fx,s,cx],[0,fy,cy],[0,0,1]]: {K.tolist()}")
        dist = get(cd, ("cameras", c, "dist"), required=False)
        dist = np.zeros(5) if dist is None else parse(("cameras", c, "dist"), dist, _vector, None)
        if len(dist) not in _DIST_LENGTHS:
            fail(("cameras", c, "dist"), f"OpenCV distortion needs 4, 5, 8, 12 or 14 numbers, got {len(dist)}")
        if len(dist) == 0:
            dist = np.zeros(5)
        T = parse(("cameras", c, "T_ecm_cam"), get(cd, ("cameras", c, "T_ecm_cam")), _rigid)
        parsed[c] = {"K": K, "dist": dist, "T_ecm_cam": T}
    rig = StereoRig.from_dict(parsed, (w, h))
    nd = get(d, ("needle",))
    radius = parse(("needle", "radius_m"), get(nd, ("needle", "radius_m")), _num)
    angles = parse(("needle", "keypoint_angles_deg"), get(nd, ("needle", "keypoint_angles_deg")), _vector, 5)
    if radius <= 0:
        fail(("needle", "radius_m"), f"must be positive, got {radius}")
    extra = {}
    if isinstance(nd, dict) and nd.get("wire_diameter_m") is not None:
        extra["wire_diameter_m"] = parse(("needle", "wire_diameter_m"), nd["wire_diameter_m"], _num)
    needle = NeedleModel(radius_m=radius, keypoint_angles_deg=tuple(angles), **extra)
    arm = None
    ed = get(d, ("ecm",), required=False)
    if ed is not None:
        Tb = parse(("ecm", "T_world_base"), get(ed, ("ecm", "T_world_base")), _rigid)
        lr = ed.get("L_rcc") if isinstance(ed, dict) else None
        ls = ed.get("L_scopelen") if isinstance(ed, dict) else None
        arm = EcmArm(Tb, 0.0 if lr is None else parse(("ecm", "L_rcc"), lr, _num),
                     0.0 if ls is None else parse(("ecm", "L_scopelen"), ls, _num))
    source = d.get("source")
    if source is not None and not isinstance(source, str):
        source = str(source)
    return DatasetMeta((w, h), rig, needle, arm, source)


# ---------------------------------------------------------------- frames.jsonl

@dataclass
class Frame:
    """One stereo frame (a line of frames.jsonl). Image paths are relative to the folder.

    ``keypoints[c]`` (5, 2) px, ``visible[c]`` (5,) bool, ``bbox[c]`` [x0, y0, x1, y1] or None,
    ``instruments`` {name: ``common.data.instruments.InstrumentPose``}, ``needle_at_rest`` False
    when the needle moves during its sequence (then the sequence is a take, not a multi-view
    group: ``multiview_group``). Optional fields are None when the file leaves them out or null.
    """

    index: int
    stamp_ns: int
    left: str
    right: str
    sequence: Optional[int] = None
    step: Optional[int] = None
    ecm_joints: Optional[np.ndarray] = None
    T_world_ecm: Optional[np.ndarray] = None
    T_world_needle: Optional[np.ndarray] = None
    keypoints: Optional[dict] = None
    visible: Optional[dict] = None
    bbox: Optional[dict] = None
    needle_at_rest: Optional[bool] = None
    instruments: Optional[dict] = None
    line: Optional[int] = field(default=None, compare=False)

    def image(self, camera: str) -> str:
        return {"left": self.left, "right": self.right}[camera]

    @property
    def at_rest(self) -> bool:
        """The needle at rest over its sequence (``needle_at_rest`` absent means true)."""
        return self.needle_at_rest is not False

    @property
    def multiview_group(self) -> Optional[int]:
        """The multi-view group of this frame: its ``sequence`` when the needle is at rest, else
        None (a frame of a moving take is a view of its own)."""
        return self.sequence if self.at_rest else None

    @property
    def T_ecm_needle(self) -> Optional[np.ndarray]:
        if self.T_world_ecm is None or self.T_world_needle is None:
            return None
        return inv_T(self.T_world_ecm) @ self.T_world_needle

    def to_json(self) -> dict:
        d = {"index": int(self.index), "stamp_ns": int(self.stamp_ns), "left": self.left, "right": self.right}
        if self.sequence is not None:
            d["sequence"] = int(self.sequence)
        if self.step is not None:
            d["step"] = int(self.step)
        for k in ("ecm_joints", "T_world_ecm", "T_world_needle"):
            v = getattr(self, k)
            if v is not None:
                d[k] = np.asarray(v, dtype=float).tolist()
        if self.keypoints is not None:
            d["keypoints"] = {c: np.asarray(self.keypoints[c], dtype=float).tolist() for c in CAMERAS}
        if self.visible is not None:
            d["visible"] = {c: [bool(b) for b in self.visible[c]] for c in CAMERAS}
        if self.bbox is not None:
            d["bbox"] = {c: (None if self.bbox.get(c) is None else [float(x) for x in self.bbox[c]])
                         for c in CAMERAS}
        if self.needle_at_rest is not None:
            d["needle_at_rest"] = bool(self.needle_at_rest)
        if self.instruments is not None:
            d["instruments"] = instruments_json(self.instruments)
        return d


_FRAME_FIELDS = {"index", "stamp_ns", "left", "right", "sequence", "step", "ecm_joints", "T_world_ecm",
                 "T_world_needle", "keypoints", "visible", "bbox", "needle_at_rest", "instruments"}


def _relpath(v) -> str:
    if not isinstance(v, str) or not v:
        raise _Bad(f"expected an image path string, got {v!r}"[:120])
    if os.path.isabs(v) or v.startswith(("/", "\\")):
        raise _Bad(f"must be relative to the folder, got {v!r}")
    if ".." in v.replace("\\", "/").split("/"):
        raise _Bad(f"must stay inside the folder, got {v!r}")
    if not v.lower().endswith(IMAGE_EXTS):
        raise _Bad(f"must be a PNG or JPEG file (.png, .jpg, .jpeg), got {v!r}")
    return v


def _per_camera(v, fn, *args, nullable: bool = False) -> dict:
    if not isinstance(v, dict):
        raise _Bad(f"expected {{\"left\": ..., \"right\": ...}}, got {type(v).__name__}")
    extra = set(v) - set(CAMERAS)
    if extra:
        raise _Bad(f"unknown camera {sorted(extra)[0]!r} (expected left and right)")
    out = {}
    for c in CAMERAS:
        if c not in v:
            raise _Bad(f"{c}: missing")
        if v[c] is None and nullable:
            out[c] = None
            continue
        try:
            out[c] = fn(v[c], *args)
        except _Bad as exc:
            raise _Bad(f"{c}: {exc}") from None
    return out


def _bbox(v) -> list:
    b = _vector(v, 4)
    if b[2] < b[0] or b[3] < b[1]:
        raise _Bad(f"expected [x0, y0, x1, y1] with x0 <= x1 and y0 <= y1, got {b.tolist()}")
    return b.tolist()


def _flag(v) -> bool:
    if not isinstance(v, bool):
        raise _Bad(f"expected true or false, got {v!r}"[:120])
    return v


def parse_frame(obj, line: Optional[int] = None, file: str = FRAMES_FILE) -> Frame:
    """Validate one decoded frames.jsonl object."""
    def fail(name, msg):
        raise DatasetError(_where(file, line, f"{name}: {msg}"))

    if not isinstance(obj, dict):
        fail("(line)", f"expected a JSON object, got {type(obj).__name__}")
    for k in ("index", "stamp_ns", "left", "right"):
        if k not in obj or obj[k] is None:
            fail(k, "required field missing")
    parsers = {"index": (_int,), "stamp_ns": (_int,), "left": (_relpath,), "right": (_relpath,),
               "sequence": (_int,), "step": (_int,), "ecm_joints": (_vector, 4),
               "T_world_ecm": (_rigid,), "T_world_needle": (_rigid,),
               "keypoints": (lambda v: _per_camera(v, _matrix, 5, 2),),
               "visible": (lambda v: _per_camera(v, _bools, 5),),
               "bbox": (lambda v: _per_camera(v, _bbox, nullable=True),),
               "needle_at_rest": (_flag,), "instruments": (parse_instruments,)}
    vals = {}
    for k, (fn, *args) in parsers.items():
        v = obj.get(k)
        if v is None:
            continue
        try:
            vals[k] = fn(v, *args)
        except _Bad as exc:
            fail(k if exc.sub is None else f"{k}.{exc.sub}", str(exc))
    if vals["index"] < 0:
        fail("index", f"must be >= 0, got {vals['index']}")
    if vals.get("step") is not None and vals["step"] < 0:
        fail("step", f"must be >= 0, got {vals['step']}")
    return Frame(line=line, **vals)


def read_frames(folder: str) -> list[Frame]:
    """Parse and validate frames.jsonl: JSON per line, fields, index order, time order."""
    path = os.path.join(folder, FRAMES_FILE)
    if not os.path.isfile(path):
        raise DatasetError(_where(FRAMES_FILE, None, f"file missing in {folder}"))
    frames = []
    with open(path, "r", encoding="utf-8-sig") as f:
        for lineno, text in enumerate(f, start=1):
            if not text.strip():
                continue
            try:
                obj = json.loads(text)
            except json.JSONDecodeError as exc:
                raise DatasetError(_where(FRAMES_FILE, lineno, f"(line): not valid JSON ({exc.msg} at column {exc.colno})")) from None
            fr = parse_frame(obj, lineno)
            if fr.index != len(frames):
                raise DatasetError(_where(FRAMES_FILE, lineno, f"index: expected {len(frames)} (file order), got {fr.index}"))
            if frames and fr.stamp_ns < frames[-1].stamp_ns:
                raise DatasetError(_where(FRAMES_FILE, lineno, f"stamp_ns: {fr.stamp_ns} is before the previous frame's "
                                          f"{frames[-1].stamp_ns} (frames must be in time order)"))
            frames.append(fr)
    return frames


# ---------------------------------------------------------------- the folder

class Dataset:
    """A dataset folder: ``meta`` (DatasetMeta), ``frames`` (list of Frame), ``image(i, camera)``."""

    def __init__(self, path: str, check_files: bool = True):
        self.path = os.fspath(path)
        if not os.path.isdir(self.path):
            raise DatasetError(f"{self.path}: not a folder")
        for name in (META_FILE, FRAMES_FILE):
            try:
                inside(self.path, name)
            except InputLimitError as exc:
                raise DatasetError(str(exc)) from None
        mpath = os.path.join(self.path, META_FILE)
        if not os.path.isfile(mpath):
            what = "missing" if not os.path.lexists(mpath) else describe_path(mpath)
            raise DatasetError(_where(META_FILE, None, f"file {what} in {self.path}"))
        if os.path.getsize(mpath) > MAX_META_BYTES:
            raise DatasetError(_where(META_FILE, None, f"{os.path.getsize(mpath)} bytes, over the limit of {MAX_META_BYTES}"))
        with open(mpath, "r", encoding="utf-8-sig") as f:
            self.meta = parse_meta(f.read())
        self.frames = read_frames(self.path)
        if check_files:
            for fr in self.frames:
                for c in CAMERAS:
                    try:
                        path = inside(self.path, fr.image(c))
                    except InputLimitError as exc:
                        raise DatasetError(_where(FRAMES_FILE, fr.line, f"{c}: {exc}")) from None
                    if not os.path.isfile(path):
                        raise DatasetError(_where(FRAMES_FILE, fr.line, f"{c}: image file {fr.image(c)!r} "
                                                  f"{describe_path(path)}"))

    @property
    def rig(self) -> StereoRig:
        return self.meta.rig

    @property
    def needle(self) -> NeedleModel:
        return self.meta.needle

    @property
    def arm(self) -> Optional[EcmArm]:
        return self.meta.arm

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> Frame:
        return self.frames[i]

    def __iter__(self):
        return iter(self.frames)

    def image(self, frame, camera: str) -> np.ndarray:
        """The (h, w, 3) uint8 BGR image of ``frame`` (a Frame or an index) for ``camera``."""
        fr = self.frames[frame] if isinstance(frame, (int, np.integer)) else frame
        rel = fr.image(camera)
        w, h = self.meta.image_size
        data = self.image_bytes(fr, camera)
        try:
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
        except cv2.error:
            img = None
        if img is None:
            raise DatasetError(f"{rel}: not a readable PNG/JPEG image ({len(data)} bytes; frames.jsonl:{fr.line})")
        w, h = self.meta.image_size
        if img.shape[:2] != (h, w):
            raise DatasetError(f"{rel}: image is {img.shape[1]}x{img.shape[0]}, dataset.yaml image_size says {w}x{h}")
        return img

    def image_bytes(self, frame, camera: str) -> bytes:
        """The PNG/JPEG file of ``frame``'s ``camera`` image, not decoded, after the checks of
        ``common.runtime.limits.read_image_file`` (inside the folder, a regular file, 1 byte to
        ``MAX_IMAGE_BYTES``, a header stating ``image_size``); DatasetError naming the file."""
        fr = self.frames[frame] if isinstance(frame, (int, np.integer)) else frame
        try:
            return read_image_file(self.path, fr.image(camera), tuple(self.meta.image_size))
        except InputLimitError as exc:
            raise DatasetError(_where(FRAMES_FILE, fr.line, f"{camera}: {exc}")) from None

    def sequences(self) -> dict:
        """Frames grouped by ``sequence`` (frames without one are left out), in file order: the
        takes, whether the needle rests (a multi-view group) or moves (see ``multiview_groups``)."""
        out: dict = {}
        for fr in self.frames:
            if fr.sequence is not None:
                out.setdefault(fr.sequence, []).append(fr)
        return out

    def multiview_groups(self) -> dict:
        """The sequences whose needle is at rest (``Frame.multiview_group``): the frames that
        show one needle pose from several endoscope poses."""
        return {s: frs for s, frs in self.sequences().items() if all(f.at_rest for f in frs)}


# ---------------------------------------------------------------- writer

class DatasetWriter:
    """Writes a folder: dataset.yaml at creation, then images and frames.jsonl lines as they come.

    ``resume=True`` keeps the frames already written (a torn last line is dropped) and continues
    after them; the existing dataset.yaml must describe the same rig and needle.
    """

    def __init__(self, path: str, meta: DatasetMeta, image_format: str = "jpg", jpeg_quality: int = 95,
                 resume: bool = False):
        if image_format not in ("jpg", "png"):
            raise ValueError(f"image_format must be 'jpg' or 'png', got {image_format!r}")
        self.path, self.meta = os.fspath(path), meta
        self.image_format, self.jpeg_quality = image_format, int(jpeg_quality)
        os.makedirs(os.path.join(self.path, "images", "left"), exist_ok=True)
        os.makedirs(os.path.join(self.path, "images", "right"), exist_ok=True)
        mpath = os.path.join(self.path, META_FILE)
        fpath = os.path.join(self.path, FRAMES_FILE)
        self.n_frames = 0
        if resume and os.path.isfile(mpath):
            with open(mpath, encoding="utf-8-sig") as f:
                old = parse_meta(f.read())
            if yaml.safe_dump(old.to_dict()) != yaml.safe_dump(meta.to_dict()):
                raise DatasetError(f"{mpath}: describes a different rig/needle/arm than this run; "
                                   f"use another --out or delete the folder")
            self.n_frames = truncate_torn_tail(fpath)
        else:
            with open(mpath, "w", encoding="utf-8") as f:
                yaml.safe_dump(meta.to_dict(), f, sort_keys=False, default_flow_style=None, width=200)
            open(fpath, "w").close()
        self._frames = open(fpath, "a", encoding="utf-8")

    def image_relpath(self, index: int, camera: str) -> str:
        return f"images/{camera}/{index:06d}.{self.image_format}"

    def write_images(self, index: int, images: dict) -> dict:
        """Encode and write both BGR images of frame ``index``; returns their relative paths."""
        return write_frame_images(self.path, index, images, self.image_format, self.jpeg_quality)

    def append(self, frame: Frame) -> None:
        if frame.index != self.n_frames:
            raise ValueError(f"frame index {frame.index} out of order (next is {self.n_frames})")
        self._frames.write(json.dumps(frame.to_json(), separators=(",", ":")) + "\n")
        self._frames.flush()
        self.n_frames += 1

    def close(self) -> None:
        if self._frames and not self._frames.closed:
            self._frames.flush()
            os.fsync(self._frames.fileno())
            self._frames.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


@contextmanager
def staged_folder(out: str):
    """Write a folder whole or not at all: yields a temporary folder beside ``out``
    (``.NAME.partial-PID``), renamed to ``out`` when the block ends normally and removed when it
    raises, so a failed conversion leaves nothing that looks like a dataset. ``out`` must not
    exist or be an empty folder (ValueError)."""
    out = os.path.normpath(os.fspath(out))
    if os.path.lexists(out) and not (os.path.isdir(out) and not os.path.islink(out) and not os.listdir(out)):
        raise ValueError(f"{out} exists" + (" and is not empty" if os.path.isdir(out) else "")
                         + "; use another --out")
    parent = os.path.dirname(out) or "."
    os.makedirs(parent, exist_ok=True)
    tmp = os.path.join(parent, f".{os.path.basename(out)}.partial-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    os.makedirs(tmp)
    try:
        yield tmp
        if os.path.isdir(out):
            os.rmdir(out)
        os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def link_or_copy(src: str, dst: str) -> None:
    """Put the file ``src`` at ``dst`` (folders made): a hard link when both lie on one file
    system, else a copy."""
    os.makedirs(os.path.dirname(os.fspath(dst)) or ".", exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


TRUTH_FIELDS = ("T_world_needle", "keypoints", "visible", "bbox")
"""The frame fields that come from the needle's true pose: a recording has none of them."""


def without_truth(src: str, out: str) -> int:
    """Copy the folder ``src`` to the new folder ``out`` without its ground truth
    (``TRUTH_FIELDS``): images (hard-linked when they share a file system), dataset.yaml, and
    each frame's stamps, sequence, endoscope joints and pose. Returns the frames written."""
    ds = Dataset(src)
    with staged_folder(out) as tmp:
        shutil.copy2(os.path.join(ds.path, META_FILE), os.path.join(tmp, META_FILE))
        with open(os.path.join(tmp, FRAMES_FILE), "w", encoding="utf-8") as f:
            for fr in ds.frames:
                for c in CAMERAS:
                    link_or_copy(os.path.join(ds.path, fr.image(c)), os.path.join(tmp, fr.image(c)))
                d = {k: v for k, v in fr.to_json().items() if k not in TRUTH_FIELDS}
                f.write(json.dumps(d, separators=(",", ":")) + "\n")
    return len(ds.frames)


def write_frame_images(folder: str, index: int, images: dict, image_format: str = "jpg",
                       jpeg_quality: int = 95) -> dict:
    """Write ``images`` ({camera: BGR}) of frame ``index`` under folder/images/<camera>/."""
    paths = {}
    for c in CAMERAS:
        rel = f"images/{c}/{index:06d}.{image_format}"
        params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if image_format == "jpg" else [cv2.IMWRITE_PNG_COMPRESSION, 3]
        ok, buf = cv2.imencode("." + image_format, images[c], params)
        if not ok:
            raise RuntimeError(f"could not encode {rel}")
        tmp = os.path.join(folder, rel + ".tmp")
        buf.tofile(tmp)
        os.replace(tmp, os.path.join(folder, rel))
        paths[c] = rel
    return paths


def truncate_torn_tail(fpath: str) -> int:
    """Drop an incomplete last line of frames.jsonl (an interrupted write); returns the line count."""
    if not os.path.isfile(fpath):
        open(fpath, "w").close()
        return 0
    with open(fpath, "rb") as f:
        data = f.read()
    keep = data[: data.rfind(b"\n") + 1] if not data.endswith(b"\n") else data
    lines = [ln for ln in keep.split(b"\n") if ln.strip()]
    good = 0
    for ln in lines:  # a line that is not valid JSON ends the usable prefix
        try:
            json.loads(ln)
        except ValueError:
            break
        good += 1
    keep = b"".join(ln + b"\n" for ln in lines[:good])
    if keep != data:
        with open(fpath, "wb") as f:
            f.write(keep)
    return good


# ---------------------------------------------------------------- consistency checks

@dataclass
class CheckReport:
    frames: int = 0
    with_truth: int = 0
    max_reproj_px: float = 0.0
    mean_reproj_px: float = 0.0
    max_fk_m: float = 0.0
    images_checked: int = 0
    errors: list = field(default_factory=list)
    warnings: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.errors


def project_keypoints(meta: DatasetMeta, T_world_ecm: np.ndarray, T_world_needle: np.ndarray) -> dict:
    """Ground-truth keypoints {camera: (5, 2) px} from the poses, as the spec defines them."""
    p_ecm = transform_points(inv_T(T_world_ecm) @ T_world_needle, meta.needle.keypoints())
    return {c: meta.rig[c].project_from_ecm(p_ecm) for c in CAMERAS}


def check_frame(meta: DatasetMeta, fr: Frame, tol_px: float = 0.1, tol_fk_m: float = 1e-5) -> tuple[list, float, float]:
    """Spec consistency of one frame: (errors, max reprojection px, FK position error m)."""
    errs, reproj, fk = [], float("nan"), float("nan")
    where = f"{FRAMES_FILE}:{fr.line}"
    w, h = meta.image_size
    if fr.keypoints is not None and fr.T_world_ecm is not None and fr.T_world_needle is not None:
        proj = project_keypoints(meta, fr.T_world_ecm, fr.T_world_needle)
        reproj = max(float(np.max(np.linalg.norm(proj[c] - fr.keypoints[c], axis=1))) for c in CAMERAS)
        if not reproj <= tol_px:
            errs.append(f"{where}: keypoints: differ from the projection of T_world_needle through "
                        f"T_world_ecm, T_ecm_cam and K by {reproj:.3f} px (tolerance {tol_px} px)")
    if fr.ecm_joints is not None and fr.T_world_ecm is not None and meta.arm is not None:
        T = meta.arm.T_world_ecm(fr.ecm_joints)
        fk = float(np.linalg.norm(T[:3, 3] - fr.T_world_ecm[:3, 3]))
        rot = float(np.linalg.norm(T[:3, :3] - fr.T_world_ecm[:3, :3]))
        if fk > tol_fk_m or rot > 1e-4:
            errs.append(f"{where}: T_world_ecm: differs from the ECM forward kinematics of ecm_joints "
                        f"by {fk * 1000:.3f} mm / {rot:.2e} (rotation)")
    if fr.visible is not None and fr.keypoints is not None:
        for c in CAMERAS:
            uv = fr.keypoints[c]
            inside = (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= h - 0.5)
            bad = np.flatnonzero(fr.visible[c] & ~inside)
            if len(bad):
                errs.append(f"{where}: visible.{c}: keypoint {'ABCDE'[bad[0]]} is marked visible "
                            f"but lies outside the image at {uv[bad[0]].round(1).tolist()}")
    if fr.bbox is not None:
        for c in CAMERAS:
            b = fr.bbox[c]
            if b is not None and (b[0] < -0.5 - 1e-6 or b[1] < -0.5 - 1e-6 or b[2] > w - 0.5 + 1e-6 or b[3] > h - 0.5 + 1e-6):
                errs.append(f"{where}: bbox.{c}: {b} lies outside the {w}x{h} image")
    return errs, reproj, fk


GRASP_TOL_M, GRASP_TOL_RAD = 1e-6, 1e-5
"""How far a held needle may move in the jaws between two frames (JSON keeps full precision)."""


def check_take(first: Frame, prev: Optional[Frame], fr: Frame) -> list:
    """A frame against its sequence: all of it at rest or all of it moving; at rest, the
    first frame's ``T_world_needle``; moving, the needle rigid in the jaws of an instrument that
    holds it in this frame and the one before (``holds_needle``)."""
    where = f"{FRAMES_FILE}:{fr.line}"
    if fr.at_rest != first.at_rest:
        return [f"{where}: needle_at_rest: {fr.needle_at_rest} in sequence {fr.sequence}, whose first frame "
                f"(line {first.line}) says {first.needle_at_rest}; a sequence rests or moves as a whole"]
    if fr.at_rest:
        if (fr.T_world_needle is not None and first.T_world_needle is not None
                and not np.allclose(fr.T_world_needle, first.T_world_needle, atol=1e-9)):
            return [f"{where}: T_world_needle: differs from the first frame of sequence {fr.sequence} "
                    f"(line {first.line}); the needle must be at rest (or the frames say needle_at_rest: false)"]
        return []
    errs = []
    if prev is None or fr.T_world_needle is None or prev.T_world_needle is None:
        return errs
    for name, inst in (fr.instruments or {}).items():
        before = (prev.instruments or {}).get(name)
        if not (inst.holds_needle and before is not None and before.holds_needle):
            continue
        dt, da = pose_error(T_jaw_needle(before, prev.T_world_needle), T_jaw_needle(inst, fr.T_world_needle))
        if dt > GRASP_TOL_M or da > GRASP_TOL_RAD:
            errs.append(f"{where}: instruments.{name}: holds_needle in this frame and the one before (line "
                        f"{prev.line}), but the needle moved {dt * 1000:.4f} mm / {np.rad2deg(da):.4f} deg in its jaws")
    return errs


def check_dataset(ds: Dataset, tol_px: float = 0.1, images: bool = True, progress: bool = False,
                  max_errors: int = 50) -> CheckReport:
    """The spec's consistency checks over a loaded folder (see ``check_frame``), plus: every
    image decodes at ``image_size``; frames of one ``sequence`` share one ``T_world_needle``
    (the needle at rest) or, in a moving take, keep the needle rigid in the jaws that hold it
    (``check_take``), and have increasing ``step``."""
    rep = CheckReport(frames=len(ds))
    errs = []
    reprojs = []
    it = ds.frames
    if progress:
        from tqdm import tqdm
        it = tqdm(it, desc="check", unit="frame")
    seq_first: dict = {}
    prev: dict = {}
    for fr in it:
        e, rp, fk = check_frame(ds.meta, fr, tol_px)
        errs += e
        if not math.isnan(rp):
            reprojs.append(rp)
        if not math.isnan(fk):
            rep.max_fk_m = max(rep.max_fk_m, fk)
        if fr.sequence is not None:
            first = seq_first.get(fr.sequence)
            if first is None:
                seq_first[fr.sequence] = fr
            else:
                errs += check_take(first, prev.get(fr.sequence), fr)
            prev[fr.sequence] = fr
        if images:
            for c in CAMERAS:
                try:
                    ds.image(fr, c)
                    rep.images_checked += 1
                except DatasetError as exc:
                    errs.append(str(exc))
        if len(errs) >= max_errors:
            errs.append(f"... stopped after {max_errors} errors")
            break
    for s, frs in ds.sequences().items():
        steps = [f.step for f in frs if f.step is not None]
        if steps and steps != sorted(set(steps)):
            rep.warnings.append(f"sequence {s}: steps {steps[:10]} are not strictly increasing")
    if not len(ds):
        errs.append(f"{FRAMES_FILE}: no frames (a dataset needs at least one)")
    rep.errors = errs
    rep.with_truth = len(reprojs)
    if reprojs:
        rep.max_reproj_px = float(np.max(reprojs))
        rep.mean_reproj_px = float(np.mean(reprojs))
    return rep


def truncate_frames(fpath: str, n: int) -> None:
    """Keep only the first ``n`` lines of frames.jsonl (used when resuming a generation)."""
    with open(fpath, "rb") as f:
        lines = [ln for ln in f.read().split(b"\n") if ln.strip()]
    with open(fpath, "wb") as f:
        f.write(b"".join(ln + b"\n" for ln in lines[:n]))


def resume_generation(folder: str, record_name: str, config: dict, sequences: int, steps: int,
                      command: str, overwrite: bool = False, defaults: dict | None = None,
                      lengths: list | None = None) -> tuple[bool, int]:
    """Prepare ``folder`` for a resumable, sequence-by-sequence generation of ``sequences`` of
    ``steps`` frames each (``lengths``: each sequence's own frame count instead).

    ``record_name`` (e.g. generate.json) holds the settings ``config`` that must match for a run to
    be resumed or extended (``defaults`` fill settings an older record lacks). A torn last line of
    frames.jsonl and any partial sequence are dropped. Returns (resume, sequences already done);
    raises ValueError when the folder holds other settings or a dataset ``command`` did not make."""
    if sequences < 1 or steps < 1:
        raise ValueError(f"{command}: --sequences and --steps must be >= 1")
    os.makedirs(folder, exist_ok=True)
    gpath = os.path.join(folder, record_name)
    fpath = os.path.join(folder, "frames.jsonl")
    config = json.loads(json.dumps(config))
    resume = False
    if os.path.isfile(gpath) and not overwrite:
        with open(gpath) as f:
            old = dict(json.load(f).get("config") or {})
        if {**(defaults or {}), **old} != config:
            raise ValueError(f"{folder} holds a `{command}` run with other settings {old}; "
                             f"use another --out or --overwrite")
        resume = True
    elif os.path.exists(fpath) and not overwrite:
        raise ValueError(f"{folder} already holds a dataset not made by `{command}`; "
                         f"use another --out or --overwrite")
    done = 0
    ends = np.cumsum(lengths if lengths is not None else [steps] * sequences)
    if resume:
        done = int(np.searchsorted(ends, truncate_torn_tail(fpath), side="right"))
        truncate_frames(fpath, int(ends[done - 1]) if done else 0)
        if done:  # the last kept line must be the end of sequence done-1
            with open(fpath) as f:
                fr = parse_frame(json.loads(f.read().splitlines()[-1]))
            if fr.sequence != done - 1 or fr.index != ends[done - 1] - 1:
                raise ValueError(f"{fpath}: cannot resume, the last frame is not the end of sequence {done - 1}")
    with open(gpath, "w") as f:
        json.dump({"config": config, "sequences": sequences}, f, indent=1)
    return resume, done
