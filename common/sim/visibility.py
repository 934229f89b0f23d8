"""What the rendered ground truth's ``visible`` means (``docs/dataset.md``), for both renderers
(``common.sim.render``, ``common.sim.alt_render``).

A point of the needle's centreline (a keypoint, or a sample of ``arc_seen``) is seen by a camera
when the needle's surface at that body point shows in the image:
- it projects inside the image, in front of the camera;
- it is not inside the tissue deeper than the wire's radius there (``buried``: a solid's surface
  lies between it and every camera);
- the pixel holding its projection shows the needle (or, on the swage, the thread leaving it),
  or nothing nearer than the needle's own surface there: the point's depth minus the wire's
  largest radius within a pixel's footprint along the arc (at the sharp tip A nearly 0: the tip
  is thinner than a pixel, so its pixel may show what lies behind it) minus that footprint (the
  pixel's centre is up to half a pixel from the exact projection);
- the stretch of the arc it lies on, unhidden, shows in the image: walking along the centreline
  (points ``ARC_STEP_PX`` apart) from the point, past points seen as above, a pixel within
  ``NEAR_PX`` of some point's shows the needle. A sliver of tip out of the tissue or past a jaw's
  edge, thinner than a pixel all the way to where it is hidden, is not seen; a long fine taper
  in clear view is seen up to its point.
"""
from __future__ import annotations

import numpy as np

ARC_STEP_PX = 0.5
"""Most image distance (px) between the centreline points that ``arc_angles`` samples."""
MAX_ARC_POINTS = 8192
"""Most centreline points ``arc_angles`` samples (an arc 4096 px long in the image)."""
NEAR_PX = 2
"""A stretch of the arc shows when a pixel this close (rows and columns) to one of its points shows
the needle (a swage seen end on shows around the thread leaving it, a pixel or two away)."""
LENGTH_SAMPLES = 49
"""Points equally spaced over the arc whose projections measure its length in the image."""


def arc_angles(arc_span_rad: tuple, coarse_uv: list, wanted_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angles (rad, ascending) over the arc's span, no more than ``ARC_STEP_PX`` apart
    in any camera, and the ``wanted_rad`` angles among them: (angles, index of each wanted angle).
    ``coarse_uv``: per camera, the projections (n, 2) px of n >= 2 points equally spaced over the
    arc (NaN where a point is behind the camera), which tell how long the arc is in the image."""
    longest = 0.0
    n = 2
    for uv in coarse_uv:
        uv = np.asarray(uv, float)
        n = len(uv)
        step = np.linalg.norm(np.diff(uv, axis=0), axis=1)
        step = step[np.isfinite(step)]
        longest = max(longest, float(step.sum()) if len(step) else 0.0)
    count = int(np.clip(np.ceil(longest / ARC_STEP_PX), n - 1, MAX_ARC_POINTS))
    a0, a1 = sorted(arc_span_rad)
    wanted = np.asarray(wanted_rad, float)
    angles = np.unique(np.concatenate([np.linspace(a0, a1, count + 1), wanted]))
    return angles, np.searchsorted(angles, wanted)


def seen_in_render(uv: np.ndarray, z: np.ndarray, arc_m: np.ndarray, radius_m: np.ndarray, inside: np.ndarray,
                   buried: np.ndarray, label: np.ndarray, needle_label: int, depth: np.ndarray, focal_px: float,
                   thread_label: int | None = None, at_thread: np.ndarray | None = None) -> tuple:
    """Which centreline points nothing hides (the first three conditions of the module docstring),
    and which of those have the needle within ``NEAR_PX`` of their pixel: ((N,) bool, (N,) bool).

    ``uv`` (N, 2) their projections (px, (0, 0) the centre of the top-left pixel), ``z`` (N,) their
    depths along the optical axis (m), ``arc_m`` (N,) their distances along the arc from one end
    (ascending, m), ``radius_m`` (N,) the wire's radius there (m), ``inside`` (N,) in the image
    and in front of the camera, ``buried`` (N,) inside the tissue deeper than that radius;
    ``label`` (h, w) the render's labels (``needle_label`` on the needle), ``depth`` (h, w) its
    depth along the optical axis (m, inf where nothing), ``focal_px`` the focal length.
    ``at_thread`` (N,): the points where the thread leaves the needle (the swage), which a pixel of
    the thread (``thread_label``) does not hide: the swage's end shows around the thread that
    comes out of it towards the camera."""
    h, w = label.shape
    u = np.clip(np.round(np.nan_to_num(uv[:, 0])).astype(int), 0, w - 1)
    v = np.clip(np.round(np.nan_to_num(uv[:, 1])).astype(int), 0, h - 1)
    z = np.asarray(z, float)
    footprint = np.abs(z) / float(focal_px)
    surface = z - window_max(np.asarray(arc_m, float), np.asarray(radius_m, float), footprint) - footprint
    on_needle = label[v, u] == needle_label
    shown = on_needle | (depth[v, u] >= surface)
    if thread_label is not None and at_thread is not None:
        shown |= np.asarray(at_thread, bool) & (label[v, u] == thread_label)
    unhidden = np.asarray(inside, bool) & ~np.asarray(buried, bool) & shown
    near_needle = on_needle.copy()
    for dv in range(-NEAR_PX, NEAR_PX + 1):
        for du in range(-NEAR_PX, NEAR_PX + 1):
            near_needle |= label[np.clip(v + dv, 0, h - 1), np.clip(u + du, 0, w - 1)] == needle_label
    return unhidden, unhidden & near_needle


def window_max(x: np.ndarray, values: np.ndarray, half_width: np.ndarray) -> np.ndarray:
    """(N,) the largest of ``values`` over the points whose ``x`` (ascending) lies within
    ``half_width`` (N,) of each point's."""
    lo = np.searchsorted(x, x - half_width, side="left")
    hi = np.searchsorted(x, x + half_width, side="right")
    padded = np.append(values, -np.inf)               # reduceat's ends must index the array
    return np.maximum.reduceat(padded, np.ravel(np.stack([lo, hi], 1)))[::2]


def shown_along_arc(unhidden: np.ndarray, on_needle: np.ndarray) -> np.ndarray:
    """(N,) bool: the points (in order along the arc, ``arc_angles``) that nothing hides and whose
    unhidden stretch of the arc holds a point next to the needle's pixels (``seen_in_render``)."""
    unhidden = np.asarray(unhidden, bool)
    run = np.cumsum(~unhidden)                       # points of one unhidden stretch share a number
    shows = np.bincount(run[unhidden & on_needle], minlength=run.max() + 1) > 0
    return unhidden & shows[run]


def visible_along_arc(uv: np.ndarray, z: np.ndarray, arc_m: np.ndarray, radius_m: np.ndarray, inside: np.ndarray,
                      buried: np.ndarray, label: np.ndarray, needle_label: int, depth: np.ndarray, focal_px: float,
                      thread_label: int | None = None, at_thread: np.ndarray | None = None) -> np.ndarray:
    """(N,) bool: which centreline points, in order along the arc no more than ``ARC_STEP_PX``
    apart (``arc_angles``), the render shows (the module docstring); arguments as
    ``seen_in_render``."""
    return shown_along_arc(*seen_in_render(uv, z, arc_m, radius_m, inside, buried, label, needle_label, depth,
                                           focal_px, thread_label, at_thread))
