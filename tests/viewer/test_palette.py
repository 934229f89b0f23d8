"""The palette (common/palette.py): every colour drawn beside another on a picture can be told
from it; one home for the colours the pictures, the page and Rerun use."""
import itertools

import cv2
import numpy as np
import pytest

from common import palette
from common.methods import FINAL_ORDER, POSE_METHODS

MIN_DELTA_E = 35.0
"""CIE76 distance in CIELAB below which two thin lines on an endoscope image read as one colour
(the truth's green and the former ``tracked`` green #2ca02c were 18 apart; matplotlib's blue and
purple, ``pnp_average`` and ``triangulation``, 38)."""


def delta_e(a: str, b: str) -> float:
    lab = cv2.cvtColor(np.array([[palette.rgb(a), palette.rgb(b)]], np.float32) / 255.0, cv2.COLOR_RGB2Lab)[0]
    return float(np.linalg.norm(lab[0] - lab[1]))


def test_every_method_can_be_told_from_the_truth_the_detections_the_holder_and_the_others():
    named = {m: palette.method(m) for m in POSE_METHODS} | palette.DISTINCT_FROM_METHODS
    close = [(a, b, round(delta_e(named[a], named[b]), 1)) for a, b in itertools.combinations(named, 2)
             if (a in POSE_METHODS or b in POSE_METHODS) and delta_e(named[a], named[b]) < MIN_DELTA_E]
    assert not close, close


def test_the_final_method_stands_apart_from_everything_drawn_with_it():
    final = palette.method(FINAL_ORDER[0])
    others = [palette.method(m) for m in FINAL_ORDER[1:]] + [
        palette.TRUTH, palette.DETECTION, palette.HOLDER, palette.AMBIGUOUS, palette.TEXT, *palette.AXES]
    assert min(delta_e(final, c) for c in others) >= 60.0


def test_delta_e_sees_the_former_clash():
    """The check can fail: the former ``tracked`` green against the truth."""
    assert delta_e("#2ca02c", palette.TRUTH) < MIN_DELTA_E <= delta_e("#ff00ff", palette.TRUTH)


def test_conversions_and_lookups():
    assert palette.rgb("#ff8000") == (255, 128, 0) and palette.bgr("#ff8000") == (0, 128, 255)
    with pytest.raises(ValueError, match="rrggbb"):
        palette.rgb("#fff")
    assert palette.method("no such method") == palette.UNKNOWN
    assert palette.line("left") == palette.CAMERA_LINES["left"]
    assert palette.line("tracked") == palette.method("tracked")
    assert set(POSE_METHODS) | {"left", "right", "truth"} <= set(palette.page_colours())


def test_colours_are_defined_only_in_the_palette_and_the_registry():
    """No module of the viewer or the overlays writes a colour of its own (a BGR triple or a hex;
    the page's greys, its background and grid, aside)."""
    import re
    from pathlib import Path
    repo = Path(__file__).resolve().parents[2]
    found = []
    for path in [*repo.glob("common/viewer/*.py"), repo / "common/evaluation/overlays.py"]:
        for i, text in enumerate(path.read_text().splitlines(), 1):
            hexes = [h for h in re.findall(r"#([0-9a-fA-F]{6})\b", text) if len({h[0:2], h[2:4], h[4:6]}) > 1]
            if hexes or re.search(r"_BGR\s*=\s*\(\s*\d", text):
                found.append(f"{path.relative_to(repo)}:{i}: {text.strip()}")
    assert not found, found
