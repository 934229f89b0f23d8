"""The second renderer's z-buffer rasteriser: triangles in camera coordinates (OpenCV pinhole,
pixel (0, 0) the centre of the top-left pixel) to per-sample depth, triangle and barycentrics."""
from __future__ import annotations

import numpy as np


NEAR_M = 0.004             # triangles with a vertex nearer than this are not drawn
_CHUNK = 1 << 20           # candidate samples per rasterisation batch


def rasterise(V_cam: np.ndarray, F: np.ndarray, K: np.ndarray, width: int, height: int,
              depth: np.ndarray | None = None):
    """Z-buffer rasterisation of triangles (camera-frame vertices, m) on the sample grid of
    ``K`` (sample (i, j) is the ray through pixel coordinates (i, j), i.e. K^-1 [i, j, 1]).

    ``depth`` (height, width), if given, is the depth already there (e.g. the tissue): only
    nearer samples win. Returns (face (h, w) int32, -1 where no triangle wins; depth (h, w)
    float32; barycentrics (h, w, 3) float32, perspective-correct, of the winning face).
    A sample exactly on a shared edge belongs to both triangles: harmless with a z-buffer.
    """
    zbuf = np.full(width * height, np.inf, np.float64) if depth is None else \
        depth.astype(np.float64).reshape(-1).copy()
    face = np.full(width * height, -1, np.int32)
    bary = np.zeros((width * height, 3), np.float32)
    z = V_cam[:, 2]
    fid = np.flatnonzero(np.all(z[F] > NEAR_M, axis=1))
    if len(fid):
        uv = (V_cam[:, :2] / z[:, None]) @ K[:2, :2].T + K[:2, 2]
        P = uv[F[fid]]                                           # (T, 3, 2)
        Z = z[F[fid]]                                            # (T, 3)
        area = ((P[:, 1, 0] - P[:, 0, 0]) * (P[:, 2, 1] - P[:, 0, 1])
                - (P[:, 1, 1] - P[:, 0, 1]) * (P[:, 2, 0] - P[:, 0, 0]))
        x0 = np.maximum(np.ceil(P[..., 0].min(axis=1)), 0)
        x1 = np.minimum(np.floor(P[..., 0].max(axis=1)), width - 1)
        y0 = np.maximum(np.ceil(P[..., 1].min(axis=1)), 0)
        y1 = np.minimum(np.floor(P[..., 1].max(axis=1)), height - 1)
        keep = (np.abs(area) > 1e-12) & (x1 >= x0) & (y1 >= y0)
        fid, P, Z, area = fid[keep], P[keep], Z[keep], area[keep]
        x0, x1, y0, y1 = (a[keep].astype(np.int64) for a in (x0, x1, y0, y1))
        nx = x1 - x0 + 1
        cnt = nx * (y1 - y0 + 1)
        ends = np.cumsum(cnt)
        start = 0
        while start < len(fid):
            # a batch of triangles with at most _CHUNK candidate samples (at least one triangle)
            base = ends[start - 1] if start else 0
            stop = max(int(np.searchsorted(ends, base + _CHUNK, side="right")), start + 1)
            sl = slice(start, stop)
            c = cnt[sl]
            t = np.repeat(np.arange(stop - start), c)
            off = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
            px = x0[sl][t] + off % nx[sl][t]
            py = y0[sl][t] + off // nx[sl][t]
            Pt = P[sl][t]
            w0 = ((Pt[:, 2, 0] - Pt[:, 1, 0]) * (py - Pt[:, 1, 1])
                  - (Pt[:, 2, 1] - Pt[:, 1, 1]) * (px - Pt[:, 1, 0])) / area[sl][t]
            w1 = ((Pt[:, 0, 0] - Pt[:, 2, 0]) * (py - Pt[:, 2, 1])
                  - (Pt[:, 0, 1] - Pt[:, 2, 1]) * (px - Pt[:, 2, 0])) / area[sl][t]
            w2 = 1.0 - w0 - w1
            inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
            t, px, py, w = t[inside], px[inside], py[inside], np.stack([w0, w1, w2], -1)[inside]
            Zt = Z[sl][t]
            wz = w / Zt
            inv = wz.sum(axis=1)
            zz = 1.0 / inv
            pix = py * width + px
            front = zz < zbuf[pix]
            t, pix, zz, wz, inv = t[front], pix[front], zz[front], wz[front], inv[front]
            np.minimum.at(zbuf, pix, zz)
            win = zz <= zbuf[pix]
            face[pix[win]] = fid[sl][t[win]]
            bary[pix[win]] = wz[win] / inv[win, None]
            start = stop
    return face.reshape(height, width), zbuf.reshape(height, width).astype(np.float32), \
        bary.reshape(height, width, 3)
