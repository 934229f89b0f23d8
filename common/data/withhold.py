"""One camera's images withheld for a share of each take: a lens covered by an instrument, smoke,
a camera lost (issue 56's "one camera is enough"). The replay sends a black image of the frame's
size in its place (``withheld_frames``); the truth is left as it is.

Per take (the frames sharing a ``sequence``, in order; frames without one form one take) one
window of ``round(share * len)`` consecutive frames, its start drawn from ``seed`` and the take's
``sequence``: the same frames on every run.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from common.frames import CAMERAS


def withheld_frames(sequences: Sequence, share: float, seed: int = 0) -> np.ndarray:
    """A bool per frame (``sequences``: each frame's ``sequence`` label or None, in play order):
    True where the camera's image is withheld (module docstring). ``share`` in [0, 1]."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"the share of each take withheld must be in [0, 1], got {share!r}")
    labels = list(sequences)
    out = np.zeros(len(labels), bool)
    takes: dict = {}
    for i, s in enumerate(labels):
        takes.setdefault(s, []).append(i)
    for s, idx in takes.items():
        n = int(round(share * len(idx)))
        if n == 0:
            continue
        key = -1 if s is None else int(s)
        start = int(np.random.default_rng([int(seed), key + 1]).integers(0, len(idx) - n + 1))
        out[idx[start:start + n]] = True
    return out


def withhold_params(text: str | None) -> dict:
    """``CAMERA[:SHARE]`` (e.g. ``right:0.3``) as the replay's params (``withhold``,
    ``withhold_share``); None or empty: {}. ValueError naming what is wrong."""
    if not text:
        return {}
    camera, _, share = text.partition(":")
    if camera not in CAMERAS:
        raise ValueError(f"{text!r}: the camera is one of {', '.join(CAMERAS)}")
    try:
        value = float(share) if share else 0.3
    except ValueError:
        raise ValueError(f"{text!r}: the share is a number in [0, 1]") from None
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"{text!r}: the share is a number in [0, 1]")
    return {"withhold": camera, "withhold_share": value}
