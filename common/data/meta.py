"""dataset.yaml of the needle dataset format (``docs/dataset.md``): its sections declared once
(``MetaYaml``: each field with its parser and constraints), read by ``parse_meta`` into
``DatasetMeta``; ``DatasetError`` names the file, line and field of what breaks it."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

import numpy as np
import yaml

from common.errors import NeedletrackError
from common.frames import CAMERAS
from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import EcmArm
from common.geometry.needle import NeedleModel
from common.data.values import BadValue, FileValue, parse_matrix, parse_number, parse_rigid, parse_vector
from common.runtime.limits import InputLimitError, compose_yaml, load_yaml
from common.runtime.schema import fields_of


FORMAT = "needle-dataset"
VERSION = 1
META_FILE = "dataset.yaml"
FRAMES_FILE = "frames.jsonl"
MAX_META_BYTES = 1 << 20           # dataset.yaml is a few KB
IMAGE_EXTS = (".png", ".jpg", ".jpeg")
_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)


class DatasetError(NeedletrackError, ValueError):
    """A folder that breaks the dataset spec; the message names file, line and field."""


def file_place(file: str, line: Optional[int], fieldname: str) -> str:
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


# dataset.yaml's sections: each field declared once, its type the parser of its value with the
# field's own constraints (``FileValue``); ``parse_meta`` refuses the first that fails, in this order

class _Format(FileValue):
    @staticmethod
    def parse(v):
        if v != FORMAT:
            raise BadValue(f"must be {FORMAT!r}, got {v!r}")
        return v


class _Version(FileValue):
    @staticmethod
    def parse(v):
        if isinstance(v, bool) or v != VERSION:
            raise BadValue(f"unknown version {v!r} (this reader knows version {VERSION})")
        return VERSION


class _ImageSize(FileValue):
    @staticmethod
    def parse(v):
        size = parse_vector(v, 2)
        if np.any(size <= 0) or np.any(size != np.round(size)):
            raise BadValue(f"must be two positive integers [width, height], got {size.tolist()}")
        return int(size[0]), int(size[1])


class _CameraMatrix(FileValue):
    @staticmethod
    def parse(v):
        K = parse_matrix(v, 3, 3)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise BadValue(f"not a camera matrix [[fx,s,cx],[0,fy,cy],[0,0,1]]: {K.tolist()}")
        return K


class _Distortion(FileValue):
    @staticmethod
    def parse(v):
        dist = parse_vector(v, None)
        if len(dist) not in _DIST_LENGTHS:
            raise BadValue(f"OpenCV distortion needs 4, 5, 8, 12 or 14 numbers, got {len(dist)}")
        return dist if len(dist) else np.zeros(5)


class _Rigid(FileValue):
    parse = staticmethod(parse_rigid)


class _Number(FileValue):
    parse = staticmethod(parse_number)


class _Radius(FileValue):
    @staticmethod
    def parse(v):
        r = parse_number(v)
        if r <= 0:
            raise BadValue(f"must be positive, got {r}")
        return r


class _Angles(FileValue):
    @staticmethod
    def parse(v):
        return tuple(parse_vector(v, 5))


@dataclass
class CameraYaml:
    """A camera of dataset.yaml (``cameras.left``, ``cameras.right``); no ``dist``: none."""
    K: _CameraMatrix
    dist: Optional[_Distortion]
    T_ecm_cam: _Rigid


@dataclass
class CamerasYaml:
    left: CameraYaml
    right: CameraYaml


@dataclass
class NeedleYaml:
    radius_m: _Radius
    keypoint_angles_deg: _Angles
    wire_diameter_m: Optional[_Number] = None


@dataclass
class EcmYaml:
    T_world_base: _Rigid
    L_rcc: Optional[_Number] = None
    L_scopelen: Optional[_Number] = None


@dataclass
class MetaYaml:
    """dataset.yaml (``docs/dataset.md``)."""
    format: _Format
    version: _Version
    image_size: _ImageSize
    cameras: CamerasYaml
    needle: NeedleYaml
    ecm: Optional[EcmYaml] = None


def parse_meta(text: str, file: str = META_FILE) -> DatasetMeta:
    """Parse and validate dataset.yaml text: the sections it declares (``MetaYaml``), the first
    field that fails named with its line."""
    try:
        d = load_yaml(text, file)
    except InputLimitError as exc:
        raise DatasetError(str(exc)) from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise DatasetError(file_place(file, line, f"not valid YAML ({getattr(exc, 'problem', exc)})")) from None
    lines = _yaml_lines(text)

    def fail(path: tuple, msg: str):
        line = None
        for k in range(len(path), -1, -1):
            if path[:k] in lines:
                line = lines[path[:k]]
                break
        name = ".".join(str(p) for p in path) or "(document)"
        raise DatasetError(file_place(file, line, f"{name}: {msg}"))

    def section(path: tuple, cls, mapping) -> dict:
        if not isinstance(mapping, dict):
            fail(path, "expected a mapping" if path else "expected a mapping at the top level")
        out = {}
        for f in fields_of(cls):
            v = mapping.get(f.key)
            if v is None:
                if not f.optional:
                    fail(path + (f.key,), "required field missing")
                out[f.name] = None
            elif dataclasses.is_dataclass(f.base):
                out[f.name] = section(path + (f.key,), f.base, v)
            else:
                try:
                    out[f.name] = f.base.check(v)
                except ValueError as exc:
                    fail(path + (f.key,), str(exc))
        return out

    m = section((), MetaYaml, d)
    w, h = m["image_size"]
    rig = StereoRig.from_dict({c: {"K": m["cameras"][c]["K"], "dist": np.zeros(5) if m["cameras"][c]["dist"] is None
                                   else m["cameras"][c]["dist"], "T_ecm_cam": m["cameras"][c]["T_ecm_cam"]}
                               for c in CAMERAS}, (w, h))
    nd = m["needle"]
    extra = {} if nd["wire_diameter_m"] is None else {"wire_diameter_m": nd["wire_diameter_m"]}
    needle = NeedleModel(radius_m=nd["radius_m"], keypoint_angles_deg=nd["keypoint_angles_deg"], **extra)
    ed = m["ecm"]
    arm = None if ed is None else EcmArm(ed["T_world_base"], ed["L_rcc"] or 0.0, ed["L_scopelen"] or 0.0)
    source = d.get("source")
    if source is not None and not isinstance(source, str):
        source = str(source)
    return DatasetMeta((w, h), rig, needle, arm, source)
