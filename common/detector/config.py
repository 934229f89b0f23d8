"""The detectors' configs, one per algorithm: ``DetectorConfig`` (the learned two-stage detector,
``common.detector.inference``) and ``ClassicalConfig`` (the image-processing baseline). Each
field is also a param of the detector node's backend of the same name (``backends``), so they
are declared here, importing neither torch nor OpenCV: a graph is checked without them.
"""
from __future__ import annotations

from dataclasses import dataclass

# The needle's smallest image extent in any view, its 5.1 mm sagitta seen from the side, is
# 10 px at 40 cm with this endoscope (f ~ 790 px): keypoints closer together are a collapse.
MIN_EXTENT_PX = 10.0
# The perspective image of the needle's circle is an ellipse: the sub-pixel centreline of a
# needle lies within 0.1 px of one (median; standard test set), a bent thread 0.3-2.7 px.
MAX_ELLIPSE_PX = 0.25
# A held needle's centreline lies 0.14 / 0.39 / 0.84 px (quartiles, read right) from its ellipse:
# the jaws beside the wire and motion blur pull it, and a jaw's edge can pass for a stretch of it.
# A detection within KEYPOINTS_ONLY_ELLIPSE_PX but not MAX_ELLIPSE_PX is stated with its
# keypoints only: no centreline (a fit would take the jaw's edge for the wire), and its crop is
# not tracked (the next frame is searched cold, so a wrong reading is not carried on). Held
# needles where 30% is seen: found 86.8 -> 95.8%; pale-thread decoys 33 -> 47 of 400 images.
KEYPOINTS_ONLY_ELLIPSE_PX = 1.5
RETRY_HUES_DEG = (120.0, 240.0)
"""The hue turns (degrees) of a cold frame searched again after no proposal passed stage 2 as
the image is: the whole circle in thirds. Of all the turns' proposals the one with the highest
presence is kept, if it reaches ``RETRY_PRESENCE``. Every third image of the silicone pads (held
out): found 68 -> 96 of 100; of the `wide` set: 92 -> 97."""


@dataclass(frozen=True)
class DetectorConfig:
    """The learned detector's settings (``KeypointDetector``); pixels of the full image."""
    # stage 2's presence: below it, no needle; null: the weights' fitted gate
    # (presence_gate.json beside them: common.detector.presence_gate), else 0.5
    threshold: float | None = None
    tracking: bool = True                         # the next frame searched in the last one's crop
    refine: bool = True
    centreline: bool = True
    subpixel: bool = True                         # the centreline refined in the full-resolution image
    min_extent_px: float = MIN_EXTENT_PX          # keypoints closer together are "no needle"
    max_ellipse_px: float = MAX_ELLIPSE_PX        # a sub-pixel centreline farther from one ellipse: "no needle"; 0: off
    keypoints_only_ellipse_px: float = KEYPOINTS_ONLY_ELLIPSE_PX   # beyond max_ellipse_px: keypoints, no centreline
    arc_bcd: bool = True
    along_arc: bool = False
    proposals: int = 3                            # stage-1 proposals tried
    proposal_threshold: float = 0.2
    ridge_ends: bool = True                       # A, E from the centreline's ends when they collapse
    # a cold frame where no proposal passes is searched again with its hues turned by these
    # (degrees); null: RETRY_HUES_DEG (120, 240), []: not searched again
    retry_hues: tuple[float, ...] | None = None


@dataclass(frozen=True)
class ClassicalConfig:
    """The image-processing baseline's settings (``common.detector.classical.ClassicalDetector``)."""
    threshold: float = 0.5
    scale: float = 0.5                            # the image scaled by this before segmenting
    min_tophat: float = 18.0
