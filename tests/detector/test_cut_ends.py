"""End keypoints where something covers the wire (common.detector.cut_ends)."""
import numpy as np

from common.detector.cut_ends import beyond_end_covered, cut_end_scores

CENTRE, RADIUS, HALF_WIDTH = np.array([300.3, 300.7]), 120.4, 2.2
TISSUE, WIRE = np.array([120, 130, 215.0]), np.array([205, 205, 210.0])   # BGR
JAW, THREAD = np.array([150, 150, 150.0]), np.array([140, 40, 110.0])
A0, A1 = np.deg2rad(30.0), np.deg2rad(150.0)                              # the arc: A at A0, E at A1


def scene(rng, jaw=False, thread=False):
    """Tissue with noise and a wire along the arc from A0 to A1; a grey jaw over the circle past
    E, or a thin thread leaving E along its tangent."""
    yy, xx = np.mgrid[0:600, 0:600].astype(float)
    ang = np.arctan2(yy - CENTRE[1], xx - CENTRE[0])
    on = (ang >= A0) & (ang <= A1)
    d = np.where(on, np.abs(np.hypot(xx - CENTRE[0], yy - CENTRE[1]) - RADIUS), 99.0)
    img = TISSUE + rng.normal(0, 3.0, (600, 600, 3))
    cover = np.clip(HALF_WIDTH + 0.5 - d, 0.0, 1.0)[..., None]
    img = img * (1 - cover) + WIRE * cover
    e = CENTRE + RADIUS * np.array([np.cos(A1), np.sin(A1)])
    t = np.array([-np.sin(A1), np.cos(A1)])                                # out of the wire at E
    if jaw:
        c = e + 14.0 * t
        img[(np.abs(xx - c[0]) < 14) & (np.abs(yy - c[1]) < 14)] = JAW
    if thread:
        s = (xx - e[0]) * t[0] + (yy - e[1]) * t[1]
        off = np.abs(-(xx - e[0]) * t[1] + (yy - e[1]) * t[0])
        img[(s > 0) & (s < 60) & (off < 0.8)] = THREAD
    return np.clip(img, 0, 255).astype(np.uint8), e


def centreline():
    a = np.linspace(A0, A1, 60)
    return CENTRE + RADIUS * np.stack([np.cos(a), np.sin(a)], 1)


def test_an_end_on_tissue_is_not_covered_and_one_under_a_jaw_is():
    rng = np.random.default_rng(0)
    img, e = scene(rng)
    assert beyond_end_covered(img, e, centreline()) < 0.2
    img, e = scene(rng, jaw=True)
    assert beyond_end_covered(img, e, centreline()) > 0.8


def test_an_end_in_the_jaws_is_covered_though_the_jaws_lie_beside_it_too():
    """A grasp: the jaws lie over the wire from a cut on, and beside the wire just before the cut,
    so the image beside the end is no tissue; the tissue is then the one beside the whole wire."""
    rng = np.random.default_rng(4)
    img, _ = scene(rng)
    cut = A1 - 0.3                                                       # the cut, 36 px before E
    c = CENTRE + RADIUS * np.array([np.cos(cut), np.sin(cut)])
    t = np.array([-np.sin(cut), np.cos(cut)])                            # out of the seen wire
    yy, xx = np.mgrid[0:600, 0:600].astype(float)
    s = (xx - c[0]) * t[0] + (yy - c[1]) * t[1]
    off = -(xx - c[0]) * t[1] + (yy - c[1]) * t[0]
    img[(s > -14) & (s < 30) & (np.abs(off) < 20)] = JAW.astype(np.uint8)
    a = np.linspace(A0, cut, 50)
    seen = CENTRE + RADIUS * np.stack([np.cos(a), np.sin(a)], 1)
    assert beyond_end_covered(img, c, seen) > 0.8


def test_a_thread_leaving_the_tail_does_not_cover_it():
    img, e = scene(np.random.default_rng(1), thread=True)
    assert beyond_end_covered(img, e, centreline()) < 0.5


def test_a_cut_end_and_the_points_placed_through_it_lose_their_score():
    img, e = scene(np.random.default_rng(2), jaw=True)
    cl = centreline()
    a = CENTRE + RADIUS * np.array([np.cos(A0), np.sin(A0)])
    uv = np.array([a, cl[15], cl[30], cl[45], e])
    scores = np.array([0.9, 0.7, 0.7, 0.7, 0.7])
    out = cut_end_scores(img, uv, scores, cl, on_arc=[False, True, True, True, False])
    assert out[0] == 0.9 and out[4] < 0.2 and np.all(out[1:4] <= out[4])
    assert np.array_equal(cut_end_scores(img, uv, scores, None), scores)
    free, _ = scene(np.random.default_rng(3))                            # both ends on tissue
    assert np.array_equal(cut_end_scores(free, uv, scores, cl, on_arc=[False, True, True, True, False]), scores)
    assert np.isnan(beyond_end_covered(img, e, cl[:4]))                  # too short to judge


def test_a_lone_sure_tip_that_does_not_taper_is_not_sure():
    from common.detector.cut_ends import TIP_RISE_PX, blunt_tip_scores
    lone = np.array([0.8, 0.3, 0.2, 0.2, 0.4])
    out = blunt_tip_scores(lone, 1.0)                                    # full width within 1 px
    assert out[0] < 0.5 and np.array_equal(out[1:], lone[1:])
    assert np.array_equal(blunt_tip_scores(lone, TIP_RISE_PX + 1.0), lone)   # it narrows: a tip
    assert np.array_equal(blunt_tip_scores(lone, float("nan")), lone)        # not measured
    confirmed = np.array([0.8, 0.7, 0.2, 0.2, 0.4])                      # another sure point
    assert np.array_equal(blunt_tip_scores(confirmed, 1.0), confirmed)
