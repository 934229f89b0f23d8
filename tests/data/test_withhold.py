"""One camera's images withheld for a share of each take (common/data/withhold.py) and the replay
that sends them black."""
import numpy as np
import pytest

from common.data.withhold import withheld_frames, withhold_params


def test_one_window_of_the_share_per_take_the_same_on_every_run():
    labels = [0] * 100 + [1] * 50 + [None] * 10
    w = withheld_frames(labels, 0.3, seed=5)
    assert w[:100].sum() == 30 and w[100:150].sum() == 15 and w[150:].sum() == 3
    for a, b in ((0, 100), (100, 150), (150, 160)):           # one window of consecutive frames
        idx = np.flatnonzero(w[a:b])
        assert np.all(np.diff(idx) == 1)
    assert np.array_equal(w, withheld_frames(labels, 0.3, seed=5))
    assert not np.array_equal(w, withheld_frames(labels, 0.3, seed=6))
    assert not withheld_frames(labels, 0.0).any() and withheld_frames(labels, 1.0).all()
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        withheld_frames(labels, 1.5)


def test_the_command_line_s_camera_and_share():
    assert withhold_params("right:0.25") == {"withhold": "right", "withhold_share": 0.25}
    assert withhold_params("left") == {"withhold": "left", "withhold_share": 0.3}
    assert withhold_params(None) == {}
    for bad in ("middle:0.3", "left:x", "left:2"):
        with pytest.raises(ValueError):
            withhold_params(bad)
