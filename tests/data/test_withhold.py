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


def test_the_evaluation_splits_the_withheld_frames_from_the_others(tmp_path):
    from types import SimpleNamespace

    from common.evaluation.withheld import withheld_markdown, withheld_summary
    frames = [SimpleNamespace(index=i, sequence=0, arc_visible={"left": 0.8, "right": 0.8 if i % 5 else 0.1})
              for i in range(20)]
    mask = withheld_frames([f.sequence for f in frames], 0.3, seed=1)
    rows = ["seq,tracked_mm,tracked_deg,tracked_nees"]
    rows += [f"{i},{2.0 if mask[i] else 1.0},{3.0 if mask[i] else 1.0},{'' if i == 0 else 4.0}" for i in range(20)]
    rows[1 + 3] = "3,,,"                                   # frame 3 not posed
    (tmp_path / "per_frame.csv").write_text("\n".join(rows) + "\n")
    t = withheld_summary(SimpleNamespace(frames=frames), tmp_path / "per_frame.csv", 0.3, seed=1)["tracked"]
    held = [i for i in range(20) if mask[i] and i % 5]
    w = t["withheld, >= 30% seen"]
    assert w["n"] == len(held) and w["position_mm"]["mean"] == pytest.approx(2.0)
    assert w["orientation_deg"]["median"] == pytest.approx(3.0)
    both = t["both_cameras, >= 30% seen"]
    assert both["position_mm"]["mean"] == pytest.approx(1.0) and both["posed_share"] < 1.0 and both["nees_median"] == 4.0
    assert sum(s["n"] for s in t.values()) == 20
    assert len(withheld_markdown({"tracked": t})) == 2 + 4
