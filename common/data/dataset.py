"""Reader of the needle dataset format, version 1 (``docs/dataset.md``).

``Dataset(path)`` loads any folder that follows the spec (PNG or JPEG, optional fields missing or
null, no ``ecm`` section) and raises ``DatasetError`` naming the file, line and field of the first
thing that breaks it. ``common.data.writer.DatasetWriter`` writes folders;
``common.data.check.check_dataset`` runs the spec's consistency checks (ground-truth projection,
FK of the joints, the takes of a moving needle, image files).
Images are returned as (h, w, 3) uint8 BGR arrays, whatever the file holds.
"""
from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from typing import Optional

import cv2
import numpy as np

from common.frames import CAMERAS
from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import EcmArm
from common.geometry.needle import NeedleModel
from common.geometry.transforms import inv_T
from common.data.instruments import instruments_json, parse_instruments
from common.data.meta import (  # noqa: F401  (re-exported: the reader's API)
    FORMAT,
    FRAMES_FILE,
    IMAGE_EXTS,
    MAX_META_BYTES,
    META_FILE,
    VERSION,
    DatasetError,
    DatasetMeta,
    file_place,
    parse_meta,
)
from common.data.values import (
    BadValue,
    parse_bools,
    parse_int,
    parse_matrix,
    parse_number,
    parse_rigid,
    parse_vector,
)
from common.runtime.limits import InputLimitError, describe_path, inside, read_image_file


# ---------------------------------------------------------------- frames.jsonl

def _relpath(v) -> str:
    if not isinstance(v, str) or not v:
        raise BadValue(f"expected an image path string, got {v!r}"[:120])
    if os.path.isabs(v) or v.startswith(("/", "\\")):
        raise BadValue(f"must be relative to the folder, got {v!r}")
    if ".." in v.replace("\\", "/").split("/"):
        raise BadValue(f"must stay inside the folder, got {v!r}")
    if not v.lower().endswith(IMAGE_EXTS):
        raise BadValue(f"must be a PNG or JPEG file (.png, .jpg, .jpeg), got {v!r}")
    return v


def _per_camera(v, fn, *args, nullable: bool = False) -> dict:
    if not isinstance(v, dict):
        raise BadValue(f"expected {{\"left\": ..., \"right\": ...}}, got {type(v).__name__}")
    extra = set(v) - set(CAMERAS)
    if extra:
        raise BadValue(f"unknown camera {sorted(extra)[0]!r} (expected left and right)")
    out = {}
    for c in CAMERAS:
        if c not in v:
            raise BadValue(f"{c}: missing")
        if v[c] is None and nullable:
            out[c] = None
            continue
        try:
            out[c] = fn(v[c], *args)
        except BadValue as exc:
            raise BadValue(f"{c}: {exc}") from None
    return out


def _bbox(v) -> list:
    b = parse_vector(v, 4)
    if b[2] < b[0] or b[3] < b[1]:
        raise BadValue(f"expected [x0, y0, x1, y1] with x0 <= x1 and y0 <= y1, got {b.tolist()}")
    return b.tolist()


def _share(v) -> float:
    x = parse_number(v)
    if not 0.0 <= x <= 1.0:
        raise BadValue(f"expected a share in [0, 1], got {x:g}")
    return x


def _arc_samples(v) -> np.ndarray:
    if not isinstance(v, (list, tuple)) or len(v) < 2 or not all(isinstance(b, bool) for b in v):
        raise BadValue(f"expected a list of at least 2 booleans, got {v!r}"[:120])
    return np.array(v, dtype=bool)


def _flag(v) -> bool:
    if not isinstance(v, bool):
        raise BadValue(f"expected true or false, got {v!r}"[:120])
    return v


def _count(v) -> int:
    n = parse_int(v)
    if n < 0:
        raise BadValue(f"must be >= 0, got {n}")
    return n


def _hand_label(v) -> dict:
    """needletrack's ``label`` field (docs/datasets.md): the frame was labelled by hand."""
    if not isinstance(v, dict):
        raise BadValue(f"expected an object, got {type(v).__name__}")
    if not isinstance(v.get("no_needle"), bool):
        raise BadValue(f"no_needle: expected true or false, got {v.get('no_needle')!r}"[:120])
    for key, parse in (("T_ecm_needle", parse_rigid), ("covariance", lambda x: parse_matrix(x, 6, 6)),
                       ("keypoint_sigma_px", lambda x: _per_camera(x, parse_vector, 5))):
        if v.get(key) is not None:
            try:
                parse(v[key])
            except BadValue as exc:
                raise BadValue(f"{key}: {exc}") from None
    return dict(v)


_NO_DEFAULT = object()


def _line(parse, default=_NO_DEFAULT, extension: bool = False):
    """A field of a frames.jsonl line: ``parse`` its value's parser (``BadValue`` with the reason);
    no ``default``: required; ``extension``: needletrack's own field (``EXTENSION_FIELDS``)."""
    meta = {"parse": parse, "extension": extension}
    return field(metadata=meta) if default is _NO_DEFAULT else field(default=default, metadata=meta)


@dataclass
class Frame:
    """One stereo frame (a line of frames.jsonl). Image paths are relative to the folder.

    ``keypoints[c]`` (5, 2) px, ``visible[c]`` (5,) bool, ``bbox[c]`` [x0, y0, x1, y1] or None,
    ``instruments`` {name: ``common.data.instruments.InstrumentPose``}, ``arc_visible[c]`` the share
    of the arc seen and ``arc_seen[c]`` (N,) bool whether each of N points equally spaced along
    the arc from A to E is seen, ``label`` a hand label's record (needletrack's own fields,
    docs/datasets.md), ``needle_at_rest`` False
    when the needle moves during its sequence (then the sequence is a take, not a multi-view
    group: ``multiview_group``). Optional fields are None when the file leaves them out or null.
    Each field of the file is declared once, here, with the parser of its value (``_line``).
    """

    index: int = _line(_count)
    stamp_ns: int = _line(parse_int)
    left: str = _line(_relpath)
    right: str = _line(_relpath)
    sequence: Optional[int] = _line(parse_int, None)
    step: Optional[int] = _line(_count, None)
    ecm_joints: Optional[np.ndarray] = _line(lambda v: parse_vector(v, 4), None)
    T_world_ecm: Optional[np.ndarray] = _line(parse_rigid, None)
    T_world_needle: Optional[np.ndarray] = _line(parse_rigid, None)
    keypoints: Optional[dict] = _line(lambda v: _per_camera(v, parse_matrix, 5, 2), None)
    visible: Optional[dict] = _line(lambda v: _per_camera(v, parse_bools, 5), None)
    bbox: Optional[dict] = _line(lambda v: _per_camera(v, _bbox, nullable=True), None)
    needle_at_rest: Optional[bool] = _line(_flag, None)
    instruments: Optional[dict] = _line(parse_instruments, None)
    arc_visible: Optional[dict] = _line(lambda v: _per_camera(v, _share), None, extension=True)
    arc_seen: Optional[dict] = _line(lambda v: _per_camera(v, _arc_samples), None, extension=True)
    label: Optional[dict] = _line(_hand_label, None, extension=True)
    line: Optional[int] = field(default=None, compare=False)      # the line of frames.jsonl it was read from

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
        if self.arc_visible is not None:
            d["arc_visible"] = {c: float(self.arc_visible[c]) for c in CAMERAS}
        if self.arc_seen is not None:
            d["arc_seen"] = {c: [bool(b) for b in self.arc_seen[c]] for c in CAMERAS}
        if self.label is not None:
            d["label"] = self.label
        return d


def _file_fields(extension: bool) -> frozenset:
    return frozenset(f.name for f in dataclasses.fields(Frame) if "parse" in f.metadata
                     and f.metadata["extension"] == extension)


_FRAME_FIELDS = _file_fields(False)
"""The frame fields of docs/dataset.md (the shared spec)."""
EXTENSION_FIELDS = _file_fields(True)
"""needletrack's own frame fields (docs/datasets.md): other readers ignore them, as the spec says."""


def parse_frame(obj, line: Optional[int] = None, file: str = FRAMES_FILE) -> Frame:
    """Validate one decoded frames.jsonl object: the required fields first, then each field with
    its parser, in the order ``Frame`` declares them."""
    def fail(name, msg):
        raise DatasetError(file_place(file, line, f"{name}: {msg}"))

    if not isinstance(obj, dict):
        fail("(line)", f"expected a JSON object, got {type(obj).__name__}")
    declared = [f for f in dataclasses.fields(Frame) if "parse" in f.metadata]
    for f in declared:
        if f.default is dataclasses.MISSING and obj.get(f.name) is None:
            fail(f.name, "required field missing")
    vals = {}
    for f in declared:
        v = obj.get(f.name)
        if v is None:
            continue
        try:
            vals[f.name] = f.metadata["parse"](v)
        except BadValue as exc:
            fail(f.name if exc.sub is None else f"{f.name}.{exc.sub}", str(exc))
    return Frame(line=line, **vals)


def read_frames(folder: str) -> list[Frame]:
    """Parse and validate frames.jsonl: JSON per line, fields, index order, time order."""
    path = os.path.join(folder, FRAMES_FILE)
    if not os.path.isfile(path):
        raise DatasetError(file_place(FRAMES_FILE, None, f"file missing in {folder}"))
    frames = []
    with open(path, "r", encoding="utf-8-sig") as f:
        for lineno, text in enumerate(f, start=1):
            if not text.strip():
                continue
            try:
                obj = json.loads(text)
            except json.JSONDecodeError as exc:
                raise DatasetError(file_place(FRAMES_FILE, lineno, f"(line): not valid JSON ({exc.msg} at column {exc.colno})")) from None
            fr = parse_frame(obj, lineno)
            if fr.index != len(frames):
                raise DatasetError(file_place(FRAMES_FILE, lineno, f"index: expected {len(frames)} (file order), got {fr.index}"))
            if frames and fr.stamp_ns < frames[-1].stamp_ns:
                raise DatasetError(file_place(FRAMES_FILE, lineno, f"stamp_ns: {fr.stamp_ns} is before the previous frame's "
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
            raise DatasetError(file_place(META_FILE, None, f"file {what} in {self.path}"))
        if os.path.getsize(mpath) > MAX_META_BYTES:
            raise DatasetError(file_place(META_FILE, None, f"{os.path.getsize(mpath)} bytes, over the limit of {MAX_META_BYTES}"))
        with open(mpath, "r", encoding="utf-8-sig") as f:
            self.meta = parse_meta(f.read())
        self.frames = read_frames(self.path)
        if check_files:
            for fr in self.frames:
                for c in CAMERAS:
                    try:
                        path = inside(self.path, fr.image(c))
                    except InputLimitError as exc:
                        raise DatasetError(file_place(FRAMES_FILE, fr.line, f"{c}: {exc}")) from None
                    if not os.path.isfile(path):
                        raise DatasetError(file_place(FRAMES_FILE, fr.line, f"{c}: image file {fr.image(c)!r} "
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
            raise DatasetError(file_place(FRAMES_FILE, fr.line, f"{camera}: {exc}")) from None

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
