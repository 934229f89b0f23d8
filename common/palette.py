"""The colours of every picture, page and figure, in one place: the truth, the detector's
keypoints, the needle's axes, the instruments, the cameras' plot lines, and each pose method's
(its ``colour`` in ``common.methods.REGISTRY``, read through ``method``).

Colours are ``"#rrggbb"`` strings, as matplotlib, CSS and the page take them; ``bgr`` and
``rgb`` turn one into OpenCV's (B, G, R) or Rerun's [R, G, B] 0-255 triples. The final method
(``tracked``, magenta) is kept far from the truth (green) and every other colour drawn beside it:
``tests/viewer/test_palette.py`` holds each pair to a minimum CIELAB distance. Imports only
``common.methods`` (a leaf).
"""
from __future__ import annotations

from common.methods import METHOD_COLOURS

TRUTH = "#3cc83c"                 # the ground truth's arc and keypoints (green)
DETECTION = "#ffdc00"             # the detector's keypoints (yellow circles)
AMBIGUOUS = "#ff8c00"             # the AMBIGUOUS label (orange)
HOLDER = "#c0ff00"                # the instrument that holds the needle: ring and label (chartreuse)
TEXT = "#ffffff"                  # captions, labels, the zoomed inset's frame
AXES = ("#e62828", "#3cc83c", "#2878e6")   # a frame's x, y, z axes (red, green, blue)
CAMERA_LINES = {"left": "#ffdc00", "right": "#e0e0e0"}   # per-camera plot lines (detector confidence)
UNKNOWN = "#ffffff"               # a method not in the registry
DISTINCT_FROM_METHODS = {"truth": TRUTH, "detection": DETECTION, "holder": HOLDER,
                         **{f"{c} camera": v for c, v in CAMERA_LINES.items()}}
"""What is drawn beside the methods' arcs on the same picture, or listed with them in the page's
legend, and must not be mistaken for one."""


def method(name: str) -> str:
    """A pose method's colour (``UNKNOWN`` for a name not in the registry)."""
    return METHOD_COLOURS.get(name, UNKNOWN)


def line(name: str) -> str:
    """A plot line's colour: a camera's (``CAMERA_LINES``) or a method's."""
    return CAMERA_LINES.get(name) or method(name)


def rgb(colour: str) -> tuple[int, int, int]:
    """``"#rrggbb"`` -> (R, G, B), 0-255. Raises ValueError on another form."""
    h = colour.lstrip("#")
    if len(h) != 6:
        raise ValueError(f"colour {colour!r}: expected '#rrggbb'")
    r, g, b = (int(h[i:i + 2], 16) for i in (0, 2, 4))
    return r, g, b


def bgr(colour: str) -> tuple[int, int, int]:
    """``"#rrggbb"`` -> OpenCV's (B, G, R), 0-255."""
    return rgb(colour)[::-1]


def page_colours() -> dict:
    """Every named colour the viewer's page draws with: the methods, the cameras' lines, the truth."""
    return {**METHOD_COLOURS, **CAMERA_LINES, "truth": TRUTH}
