"""Writing needle dataset folders (``docs/dataset.md``): ``DatasetWriter``, a folder staged and
moved into place, a file replaced atomically, a copy without the ground truth, and resuming a
generation cut short."""
from __future__ import annotations

import json
import os
import shutil
from contextlib import contextmanager

import cv2
import numpy as np
import yaml

from common.frames import CAMERAS
from common.data.dataset import (
    Dataset,
    DatasetError,
    DatasetMeta,
    FRAMES_FILE,
    Frame,
    META_FILE,
    parse_frame,
    parse_meta,
)


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


def write_atomic(path: str, data: bytes) -> None:
    """Write the file ``path`` whole or not at all: a temporary file beside it (``.NAME.tmp-PID``),
    flushed to disk, then renamed over it, and the folder's entry flushed: a kill leaves the old
    file or the new one."""
    folder = os.path.dirname(os.path.abspath(path))
    tmp = os.path.join(folder, f".{os.path.basename(path)}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def link_or_copy(src: str, dst: str) -> None:
    """Put the file ``src`` at ``dst`` (folders made): a hard link when both lie on one file
    system, else a copy."""
    os.makedirs(os.path.dirname(os.fspath(dst)) or ".", exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


TRUTH_FIELDS = ("T_world_needle", "keypoints", "visible", "bbox", "arc_visible", "arc_seen", "label")
"""The frame fields that come from the needle's true pose, or a hand label's record of it
(``label``): a recording has none of them."""


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
