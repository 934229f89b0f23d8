"""Sub-pixel centreline refinement in the image (common.detector.centreline_subpixel)."""
import numpy as np

from common.detector.centreline_subpixel import (
    TRIM,
    ellipse_residual,
    refine_centreline,
)

CENTRE, RADIUS, HALF_WIDTH = np.array([400.3, 300.7]), 120.4, 2.2
TISSUE, WIRE = np.array([120, 130, 215.0]), np.array([205, 205, 210.0])   # BGR


def wire_image(rng, shape=(600, 800)):
    """Tissue with noise and an anti-aliased wire of HALF_WIDTH px along a circle, off the grid."""
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    d = np.abs(np.hypot(xx - CENTRE[0], yy - CENTRE[1]) - RADIUS)
    cover = np.clip(HALF_WIDTH + 0.5 - d, 0.0, 1.0)[..., None]
    img = TISSUE * (1 - cover) + WIRE * cover + rng.normal(0, 3.0, shape + (3,))
    return np.clip(img, 0, 255).astype(np.uint8)


def arc(angles, offset=0.0):
    return CENTRE + np.asarray(RADIUS + offset, float)[..., None] * np.stack([np.cos(angles), np.sin(angles)], -1)


def distance_to_wire(p):
    return np.abs(np.linalg.norm(p - CENTRE, axis=1) - RADIUS)


def test_coarse_stations_move_onto_the_wire_centre():
    rng = np.random.default_rng(0)
    img = wire_image(rng)
    t = np.linspace(0.3, 2.2, 48)
    coarse = arc(t, 0.4 + 0.5 * np.sin(5 * t))         # off by up to 0.9 px, wobbling, as the
    # learned ridge is (0.6 px at its 90th percentile)
    w = np.ones(48)
    w[20] = 0.0                                         # a station the detector left out
    pts, w2 = refine_centreline(img, coarse, w)
    ok = w2 > 0
    assert not ok[:TRIM].any() and not ok[-TRIM:].any() and not ok[20]
    assert ok.sum() == 48 - 2 * TRIM - 1
    err = distance_to_wire(pts[ok])
    assert np.median(err) < 0.05 and err.max() < 0.2, np.round(err, 3)
    assert np.array_equal(pts[~ok], coarse[~ok])        # left-out stations are not moved


def test_an_instrument_over_the_wire_leaves_those_stations_out():
    rng = np.random.default_rng(1)
    img = wire_image(rng)
    t = np.linspace(0.3, 2.2, 48)
    jaw = arc(t[22:28])
    x0, y0 = np.floor(jaw.min(0)).astype(int) - 8
    x1, y1 = np.ceil(jaw.max(0)).astype(int) + 8
    img[y0:y1, x0:x1] = (225, 225, 228)                 # a bright jaw, much wider than the wire
    pts, w2 = refine_centreline(img, arc(t, 0.6), np.ones(48))
    assert not (w2[23:27] > 0).any()
    err = distance_to_wire(pts[w2 > 0])
    assert np.median(err) < 0.05 and err.max() < 0.25


def test_too_short_or_off_image_curves_do_not_fail():
    img = wire_image(np.random.default_rng(2), (200, 200))
    pts, w = refine_centreline(img, arc(np.linspace(0, 1, 5)), np.ones(5))
    assert pts.shape == (5, 2) and not w.any()
    far = np.stack([np.linspace(-500, -400, 20), np.full(20, -300.0)], 1)
    pts, w = refine_centreline(img, far, np.ones(20))
    assert pts.shape == (20, 2) and not w.any()
    pts, w = refine_centreline(img, np.full((20, 2), np.nan), np.ones(20))
    assert not w.any()
    assert ellipse_residual(np.full((20, 2), np.nan)) == (float("inf"), 0.0)


def ellipse_arc(t, centre=(300.0, 200.0), axes=(80.0, 35.0), angle=0.4):
    c, s = np.cos(angle), np.sin(angle)
    x, y = axes[0] * np.cos(t), axes[1] * np.sin(t)
    return np.stack([centre[0] + c * x - s * y, centre[1] + s * x + c * y], 1)


def test_a_projected_circle_is_an_ellipse_and_a_bent_thread_is_not():
    rng = np.random.default_rng(3)
    t = np.linspace(0.2, 2.3, 44)                       # a 120-degree arc seen obliquely
    arc = ellipse_arc(t) + rng.normal(0, 0.07, (44, 2))
    med, share = ellipse_residual(arc)
    assert med < 0.1 and share > 0.9
    # a jaw bends a fifth of the stations away (its width filter leaves few such): the rest still
    # make one ellipse
    jaw = arc.copy()
    jaw[:9] += np.linspace(0, 6, 9)[:, None] * np.array([0.0, 1.0])
    med, share = ellipse_residual(jaw)
    assert med < 0.1 and share >= 0.5
    # a thread bent at a corner (two nearly straight arms, as the test set's decoy)
    arm1 = np.stack([np.linspace(0, 25, 22), np.linspace(0, 2, 22) ** 2], 1)
    arm2 = arm1[-1] + np.stack([np.linspace(0, 3, 22) ** 2, np.linspace(0, 25, 22)], 1)
    med, share = ellipse_residual(np.vstack([arm1, arm2[1:]]) + rng.normal(0, 0.07, (43, 2)))
    assert med > 0.25 or share < 0.5
    assert ellipse_residual(arc[:5]) == (float("inf"), 0.0)
