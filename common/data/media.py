"""A user's own image and video files as a stream of camera images (``needletrack detect``).

A path is an image file (``IMAGE_FILE_EXTS``), a video file (``VIDEO_FILE_EXTS``, frames in
order as OpenCV's ``VideoCapture`` decodes them), a folder of images (sorted by name; not
recursive) or a dataset folder (docs/dataset.md: each frame's left and right images, with the
folder's calibration). ``open_sources`` checks every path before any work and raises
``MediaError`` naming the path (missing, unknown extension, empty folder, a video OpenCV cannot
open); an image that cannot be decoded later is an ``InputImage`` with ``error`` set, so that a
corrupt file among many is reported and the run goes on.

Images are BGR uint8, as OpenCV reads them (grey and 16-bit images converted). A side-by-side
stereo image or video (``split_stereo``) gives its left half as camera ``left`` and its right
half as ``right``.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional

import cv2
import numpy as np

from common.errors import NeedletrackError
from common.frames import CAMERAS
from common.runtime.checks import MAX_IMAGE_SIDE
from common.runtime.limits import MAX_IMAGE_BYTES, describe_path

IMAGE_FILE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
"""Image files read one by one (lower case; OpenCV decodes each)."""
VIDEO_FILE_EXTS = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv", ".mjpeg")
"""Video files read frame by frame with OpenCV's ``VideoCapture`` (lower case)."""


class MediaError(NeedletrackError, ValueError):
    """A path that is not an image, a video or a folder of them; the text names it."""


@dataclass
class InputImage:
    """One camera image of a user's files. ``source``: the file it came from; ``frame``: its
    index in a video or dataset folder (None for an image file); ``camera``: ``left`` /
    ``right`` for a half of a side-by-side image or a dataset folder's camera, else None;
    ``name``: a short name unique within the run (file-name safe, for its overlay);
    ``image``: BGR uint8, None when ``error`` says why it could not be read; ``calib``: the
    dataset folder's ``Calibration`` (None elsewhere); ``stream``: images of one stream
    (a video, a dataset folder's sequence) share it, in order."""

    source: str
    frame: Optional[int]
    camera: Optional[str]
    name: str
    image: Optional[np.ndarray]
    error: Optional[str] = None
    calib: object = None
    stream: Optional[str] = None


@dataclass
class Source:
    """One path given: ``kind`` is ``image``, ``video``, ``images`` (a folder) or ``dataset``;
    ``files`` the image files of an ``images`` folder, in order; ``frames`` how many images it
    will give at most (a video's is OpenCV's estimate), before ``every`` and stereo halves."""

    path: str
    kind: str
    files: tuple = ()
    frames: int = 1


def _ext(path: str) -> str:
    return os.path.splitext(path)[1].lower()


def _video_frame_count(path: str) -> int:
    cap = cv2.VideoCapture(path)
    try:
        if not cap.isOpened():
            raise MediaError(f"{path}: OpenCV cannot open this video (codec or container not supported, "
                             f"or not a video)")
        ok = cap.grab()
        if not ok:
            raise MediaError(f"{path}: a video without a readable frame")
        return max(1, int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 1))
    finally:
        cap.release()


def open_source(path: str) -> Source:
    """The ``Source`` a path is, checked (``MediaError`` naming the path otherwise)."""
    p = os.fspath(path)
    if os.path.isdir(p):
        from common.data.meta import FRAMES_FILE, META_FILE
        if os.path.exists(os.path.join(p, META_FILE)):
            from common.data.dataset import Dataset
            ds = Dataset(p)         # DatasetError (a ValueError) names the file and line
            if not len(ds):
                raise MediaError(f"{p}: a dataset folder without frames ({FRAMES_FILE} is empty)")
            return Source(p, "dataset", frames=len(ds) * len(CAMERAS))
        files = tuple(sorted(f for f in os.listdir(p)
                             if _ext(f) in IMAGE_FILE_EXTS and os.path.isfile(os.path.join(p, f))))
        if not files:
            videos = sorted(f for f in os.listdir(p) if _ext(f) in VIDEO_FILE_EXTS)
            hint = f" (it holds videos: give them as paths, e.g. {os.path.join(p, videos[0])})" if videos else ""
            raise MediaError(f"{p}: a folder without images ({', '.join(IMAGE_FILE_EXTS)}) and without "
                             f"dataset.yaml{hint}")
        return Source(p, "images", files, len(files))
    if not os.path.isfile(p):
        raise MediaError(f"{p}: {describe_path(p)}")
    ext = _ext(p)
    if ext in IMAGE_FILE_EXTS:
        return Source(p, "image")
    if ext in VIDEO_FILE_EXTS:
        return Source(p, "video", frames=_video_frame_count(p))
    raise MediaError(f"{p}: unknown file extension {ext or '(none)'!r}: images are "
                     f"{', '.join(IMAGE_FILE_EXTS)}; videos {', '.join(VIDEO_FILE_EXTS)}; or give a folder")


def open_sources(paths) -> list[Source]:
    """Every path checked before any image is read (``MediaError`` names the first bad one)."""
    if not paths:
        raise MediaError("no image, video or folder given")
    return [open_source(p) for p in paths]


def read_image(path: str) -> np.ndarray:
    """An image file as BGR uint8; ``MediaError`` saying why it cannot be read (too large for
    ``MAX_IMAGE_BYTES`` / ``MAX_IMAGE_SIDE``, not decodable)."""
    from common.runtime.checks import image_header_size
    try:
        size = os.path.getsize(path)
        if size == 0:
            raise MediaError(f"{path}: empty file (0 bytes)")
        if size > MAX_IMAGE_BYTES:
            raise MediaError(f"{path}: {size} bytes, over the limit of {MAX_IMAGE_BYTES} (NEEDLETRACK_MAX_IMAGE_BYTES)")
        data = Path(path).read_bytes()
    except OSError as exc:
        raise MediaError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    hs = image_header_size(data)          # PNG / JPEG: the size before decoding
    if hs is not None and max(hs) > MAX_IMAGE_SIDE:
        raise MediaError(f"{path}: {hs[0]}x{hs[1]} px, over the limit of {MAX_IMAGE_SIDE} px a side")
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    except cv2.error:
        img = None
    if img is None or img.size == 0:
        raise MediaError(f"{path}: not a readable image ({size} bytes; OpenCV cannot decode it)")
    return img


def stereo_halves(img: np.ndarray) -> dict:
    """{camera: image} of a side-by-side stereo image: the left half and the right half (an odd
    width drops the middle column)."""
    w = img.shape[1] // 2
    return {"left": np.ascontiguousarray(img[:, :w]), "right": np.ascontiguousarray(img[:, img.shape[1] - w:])}


class _Names:
    """Unique, file-name safe names within a run."""

    def __init__(self):
        self.taken: set = set()

    def __call__(self, stem: str) -> str:
        stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in stem) or "image"
        name, k = stem, 2
        while name in self.taken:
            name, k = f"{stem}-{k}", k + 1
        self.taken.add(name)
        return name


def _images_of(img, error, source, frame, stem, names, split, stream=None) -> Iterator[InputImage]:
    if not split:
        yield InputImage(source, frame, None, names(stem), img, error, stream=stream)
        return
    halves = stereo_halves(img) if img is not None else dict.fromkeys(CAMERAS)
    for cam in CAMERAS:
        yield InputImage(source, frame, cam, names(f"{stem}_{cam}"), halves[cam], error, stream=stream)


def _video_images(src: Source, every: int, most: Optional[int], names, split: bool) -> Iterator[InputImage]:
    cap = cv2.VideoCapture(src.path)
    stem = Path(src.path).stem
    try:
        i = kept = 0
        while most is None or kept < most:
            if i % every:
                ok, img = cap.grab(), None
            else:
                ok, img = cap.read()
            if not ok or (img is None and not i % every):
                if i < src.frames - max(2, src.frames // 50):
                    # the container states more frames: a truncated or damaged file
                    yield InputImage(src.path, i, None, names(f"{stem}_{i:06d}"), None,
                                     f"{src.path}: frame {i} cannot be decoded (the video states "
                                     f"{src.frames} frames): truncated or damaged; its last frames are passed over")
                break
            if not i % every:
                yield from _images_of(img, None, src.path, i, f"{stem}_{i:06d}", names, split, stream=src.path)
                kept += 1
            i += 1
    finally:
        cap.release()


def _dataset_images(src: Source, every: int, most: Optional[int], names) -> Iterator[InputImage]:
    from common.data.dataset import Dataset
    from common.runtime.messages import Calibration
    ds = Dataset(src.path)
    meta = ds.meta
    calib = Calibration(stamp_ns=0, image_size=np.array(meta.image_size), cameras=meta.rig.to_dict(),
                        needle=meta.needle.to_dict(), source=f"dataset {ds.path}")
    stem = Path(src.path).resolve().name
    for fr in ds.frames[::every][:most]:
        for cam in CAMERAS:
            path = os.path.join(ds.path, fr.image(cam))
            try:
                img, error = ds.image(fr, cam), None
            except ValueError as exc:          # DatasetError: names the file and line
                img, error = None, str(exc)
            yield InputImage(path, fr.index, cam, names(f"{stem}_{fr.index:06d}_{cam}"), img, error, calib,
                             stream=f"{ds.path}#{fr.sequence}")


def input_images(sources: list, every: int = 1, max_frames: Optional[int] = None,
                 split_stereo: bool = False) -> Iterator[InputImage]:
    """The camera images of ``sources`` in order: each image file; every ``every``-th frame of
    each video and dataset folder (``every`` also thins a folder of images), at most
    ``max_frames`` of each (None: all); with ``split_stereo`` each image or video frame as its
    two halves."""
    if every < 1:
        raise MediaError(f"every must be at least 1, got {every}")
    if max_frames is not None and max_frames < 1:
        raise MediaError(f"max_frames must be at least 1, got {max_frames}")
    names = _Names()
    for src in sources:
        if src.kind == "video":
            yield from _video_images(src, every, max_frames, names, split_stereo)
        elif src.kind == "dataset":
            yield from _dataset_images(src, every, max_frames, names)
        else:
            files = [src.path] if src.kind == "image" else [os.path.join(src.path, f) for f in src.files[::every][:max_frames]]
            for path in files:
                try:
                    img, error = read_image(path), None
                except MediaError as exc:
                    img, error = None, str(exc)
                yield from _images_of(img, error, path, None, Path(path).stem, names, split_stereo)


def planned_images(sources: list, every: int = 1, max_frames: Optional[int] = None,
                   split_stereo: bool = False) -> int:
    """About how many images ``input_images`` gives (a video's frame count is OpenCV's estimate)."""
    n = 0
    for s in sources:
        if s.kind == "image":
            k = 1
        elif s.kind == "dataset":
            k = min(-(-(s.frames // len(CAMERAS)) // every), max_frames or s.frames) * len(CAMERAS)
        else:
            k = min(-(-s.frames // every), max_frames or s.frames)
        n += k * (2 if split_stereo and s.kind != "dataset" else 1)
    return n
