"""The presence gate fitted for a weights file: the stage-2 presence a needle must reach to be
reported, chosen on looks the weights never trained on (``presence_gate.json`` beside them;
``needletrack bench presence --fit``).

A network's presence is calibrated on its training looks only: on a look it never saw it can
read an instrument's jaws as a needle with presence 0.8-0.95, while the needles it reads right
score above 0.98 (``models/README.md``). The gate is the lowest threshold (at least
``DEFAULT_THRESHOLD``) at which, on the fitting folders, at most ``max_false`` of the needle-free
images report a needle and at most ``max_false`` of the images with a needle report one in the
wrong place (keypoints more than ``WRONG_PX`` from the truth, either end order). Without a gate
file the detector uses ``DEFAULT_THRESHOLD``.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from common.errors import NeedletrackError

DEFAULT_THRESHOLD = 0.5
"""Stage 2's presence below which no needle is reported, where the weights have no gate."""
WRONG_PX = 15.0
"""A detection whose keypoints' median distance to the truth (the nearer end order) exceeds this
(px) is in the wrong place: another object read as the needle."""
MAX_FALSE = 0.01
"""The default share of needle-free images (and of images read in the wrong place) the gate allows:
issue 54's figure for needle-free images."""


class PresenceGateError(NeedletrackError, ValueError):
    """A presence-gate file that is unreadable or out of range."""


@dataclass(frozen=True)
class PresenceGate:
    """``threshold``: stage 2's presence to report a needle; the rest: what it was fitted on and
    what it gave there (shares of images)."""
    threshold: float
    fitted_on: tuple[str, ...]
    needle_free_images: int
    images_with_needle: int
    false_share: float            # needle-free images reporting a needle at the threshold
    wrong_share: float            # images with a needle reporting one in the wrong place
    right_share: float            # images with a needle reporting it in the right place

    def to_dict(self) -> dict:
        d = asdict(self)
        d["fitted_on"] = list(self.fitted_on)
        return d


def presence_gate_path(weights) -> Path:
    """Where the presence gate of these weights is kept: beside them."""
    return Path(weights).with_name("presence_gate.json")


def load_presence_gate(weights) -> PresenceGate | None:
    """The gate fitted for these weights, or None (then ``DEFAULT_THRESHOLD``)."""
    path = presence_gate_path(weights)
    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text())
        gate = PresenceGate(float(d["threshold"]), tuple(d["fitted_on"]), int(d["needle_free_images"]),
                            int(d["images_with_needle"]), float(d["false_share"]), float(d["wrong_share"]),
                            float(d["right_share"]))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise PresenceGateError(f"{path}: not a presence-gate file ({type(exc).__name__}: {exc})") from None
    if not 0.0 <= gate.threshold < 1.0:
        raise PresenceGateError(f"{path}: threshold must be in [0, 1), got {gate.threshold}")
    return gate


def save_presence_gate(gate: PresenceGate, path) -> None:
    Path(path).write_text(json.dumps(gate.to_dict(), indent=1) + "\n")


def fit_presence_gate(needle_free: np.ndarray, right: np.ndarray, wrong: np.ndarray, images_with_needle: int,
                      fitted_on, max_false: float = MAX_FALSE) -> PresenceGate:
    """The gate from cold detections at ``DEFAULT_THRESHOLD``: ``needle_free`` the presence of each
    needle-free image (0 where none was reported), ``right`` / ``wrong`` the presence of each
    detection on an image with a needle, in the right / wrong place. The lowest threshold meeting
    both shares: ``DEFAULT_THRESHOLD`` or just above an observed false or wrong presence (at worst
    above them all, where it may report almost nothing: ``right_share`` says so)."""
    free = np.asarray(needle_free, float)
    right, wrong = np.asarray(right, float), np.asarray(wrong, float)
    if len(free) == 0 or images_with_needle <= 0:
        raise ValueError("fit_presence_gate: needs needle-free images and images with a needle")
    shares = lambda t: ((free >= t).mean(), (wrong >= t).sum() / images_with_needle,
                        (right >= t).sum() / images_with_needle)
    candidates = np.unique(np.concatenate([[DEFAULT_THRESHOLD], free, wrong]))
    candidates = candidates[candidates >= DEFAULT_THRESHOLD]
    # a threshold just above an observed false presence rejects it: the next representable float
    for t in np.concatenate([[DEFAULT_THRESHOLD], np.nextafter(candidates, 2.0)]):
        f, w, r = shares(t)
        if f <= max_false and w <= max_false:
            break
    t = float(min(t, np.nextafter(1.0, 0.0)))
    f, w, r = shares(t)
    return PresenceGate(t, tuple(fitted_on), len(free), int(images_with_needle), float(f), float(w), float(r))
