"""What the rendered ground truth's ``visible`` means (``docs/dataset.md``), for both renderers
(``common.sim.render``, ``common.sim.alt_render``).

A point of the needle's centreline (a keypoint, or a sample of ``arc_seen``) is seen by a camera
when the needle's surface at that body point is in the image:
- it projects inside the image, in front of the camera;
- it is not inside the tissue deeper than the wire's radius there (``buried``: a solid's surface
  lies between it and every camera);
- the pixel holding its projection shows the needle, or nothing nearer than the needle's own
  surface there: the keypoint's depth minus the wire's radius at that point (0 at the sharp tip A,
  which is thinner than a pixel, so its pixel may show what lies behind it) minus one pixel's
  footprint at that depth (the pixel's centre is up to half a pixel from the exact projection).
"""
from __future__ import annotations

import numpy as np


def seen_in_render(uv: np.ndarray, z: np.ndarray, radius_m: np.ndarray, inside: np.ndarray, buried: np.ndarray,
                   label: np.ndarray, needle_label: int, depth: np.ndarray, focal_px: float) -> np.ndarray:
    """(N,) bool: which centreline points are seen (see the module docstring).

    ``uv`` (N, 2) their projections (px, (0, 0) the centre of the top-left pixel), ``z`` (N,) their
    depths along the optical axis (m), ``radius_m`` (N,) the wire's radius there (m), ``inside``
    (N,) in the image and in front of the camera, ``buried`` (N,) inside the tissue deeper than
    that radius; ``label`` (h, w) the render's labels (``needle_label`` on the needle), ``depth``
    (h, w) its depth along the optical axis (m, inf where nothing), ``focal_px`` the focal length."""
    h, w = label.shape
    u = np.clip(np.round(np.nan_to_num(uv[:, 0])).astype(int), 0, w - 1)
    v = np.clip(np.round(np.nan_to_num(uv[:, 1])).astype(int), 0, h - 1)
    z = np.asarray(z, float)
    surface = z - np.asarray(radius_m, float) - np.abs(z) / float(focal_px)
    shown = (label[v, u] == needle_label) | (depth[v, u] >= surface)
    return np.asarray(inside, bool) & ~np.asarray(buried, bool) & shown
