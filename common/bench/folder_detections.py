"""The learned detector run cold over a dataset folder's images: the loop the end-identity and
familiarity benchmarks (and ``needletrack adapt``'s refit) share.

Cold: the detector is reset before each image, so each is read on its own, without tracking.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterator, Optional

import cv2

from common.frames import CAMERAS
from common.progress import progress_bar


def cold_detections(folder: str, detector, step: int = 1, only: Optional[Callable] = None,
                    look: Optional[Callable] = None, progress: bool = True) -> Iterator[tuple]:
    """``(frame, camera, keypoints)`` for each image of every ``step``-th frame of ``folder`` that
    OpenCV reads (an unreadable one is passed over), left then right, in the folder's order.

    ``look(frame)``, called once per frame in order (skipped frames included), returns the function
    each of that frame's images goes through before detection (BGR in, BGR out), or None (as read).
    ``only(frame)``: False passes over the frame without reading its images. ``detector``'s state
    after each detection (``last_descriptor``, ``last_evidence``) is that image's until the next
    item is asked for. ``progress``: a progress bar over the frames."""
    from common.data.dataset import Dataset
    ds = Dataset(folder)
    for fr in progress_bar(ds.frames[::step], desc=Path(folder).name, unit="frame", leave=False,
                   show=progress):
        change = look(fr) if look is not None else None
        if only is not None and not only(fr):
            continue
        for cam in CAMERAS:
            img = cv2.imread(str(Path(ds.path) / getattr(fr, cam)))
            if img is None:
                continue
            if change is not None:
                img = change(img)
            detector.reset()
            yield fr, cam, detector.detect(img, cam)
