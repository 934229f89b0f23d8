"""The dense fit's residuals, precomputed per rig and needle: the projected model arc in both
cameras, each observed centreline point's foot on it (Newton steps along the exact projected
circle), the keypoint and curve residuals with their analytic Jacobians over ``[w, v]`` (a
rotation vector left-multiplied in the ECM frame, a translation in the ECM frame), and the
robust (Cauchy) loss. Pixels are undistorted first. The solver and its results:
``common.geometry.refine``.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Mapping

import numpy as np

from common.errors import NeedletrackError
from common.geometry.camera import StereoRig
from common.geometry.needle import NeedleModel
from common.geometry.transforms import rotvecs_to_Rs

if TYPE_CHECKING:
    from common.geometry.refine import ArcObservation, RefineConfig


class RefineError(NeedletrackError, ValueError):
    """The observations or candidates cannot give a pose; the text says why (a short reason
    first, e.g. ``no_candidates: ...``, usable as a counter name)."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


class ArcStatic:
    """What does not change between frames: cameras and needle model, shaped to broadcast over
    (P poses, C = 2 cameras, N points)."""

    def __init__(self, rig: StereoRig, needle: NeedleModel, cfg: RefineConfig):
        cams = rig.cameras
        self.cams, self.cfg, self.needle = cams, cfg, needle
        self.Rc = np.stack([c.T_cam_ecm[:3, :3] for c in cams])
        self.tc = np.stack([c.T_cam_ecm[:3, 3] for c in cams])
        Kp = np.stack([c.K[:2, :2] for c in cams])
        kc = np.stack([c.K[:2, 2] for c in cams])
        if np.any(Kp[:, 1, 0] != 0) or np.any(Kp[:, [0, 1], [0, 1]] <= 0) or not np.all(np.isfinite(Kp)):
            raise RefineError("bad_calibration",
                              "camera K must be upper triangular with positive focal lengths")
        self.cam_centres = np.stack([c.T_ecm_cam[:3, 3] for c in cams])
        self.radius = needle.radius_m
        a0, a1 = needle.arc_span_rad
        self.mid, self.half = 0.5 * (a0 + a1), 0.5 * (a1 - a0)
        self.arc_centroid = needle.sample_arc(64).mean(0)
        C, M = len(cams), cfg.max_curve_points
        self.C, self.M = C, M
        col = lambda a: np.asarray(a, float).reshape(1, C, 1)
        self._fx, self._sk, self._fy = col(Kp[:, 0, 0]), col(Kp[:, 0, 1]), col(Kp[:, 1, 1])
        self._cx, self._cy = col(kc[:, 0]), col(kc[:, 1])
        self._Rmid = rotvecs_to_Rs(np.array([[0.0, 0.0, self.mid]]))[0]
        # radius * [e1, e2, e2, -e1] of the needle axes turned so the arc's middle is on +x
        self._W = self.radius * np.stack([self._Rmid[:, 0], self._Rmid[:, 1], self._Rmid[:, 1],
                                          -self._Rmid[:, 0]], axis=1)
        self._cos_half, self._sin_half = np.cos(self.half), np.sin(self.half)
        kp_ang = needle.keypoint_angles_rad - self.mid               # A..E about the middle
        self._kp_cs = np.stack([np.cos(kp_ang), np.sin(kp_ang)], axis=1)   # (5, 2)
        self._end_cs = np.array([[np.cos(self.half), -np.sin(self.half)],
                                 [np.cos(self.half), np.sin(self.half)]])  # A, E
        self._perp = np.array([-1.0, 1.0])           # (cos, sin)[::-1] * perp = d/d angle
        # Jacobian rows (see ArcProblem.evaluate): for a point at W (camera frame, from the needle
        # origin) with pixel offset (du, dv) from the principal point and 1/depth iz,
        #   d u / d[dr_c, dt_c] = iz (Ku(W) - du m(W)),  d v / d[dr_c, dt_c] = iz (Kv(W) - dv m(W)),
        #   Ku = [-sk W2, fx W2, sk W0 - fx W1, fx, sk, 0], Kv = [-fy W2, 0, fy W0, 0, fy, 0],
        #   m = [W1, -W0, 0, 0, 0, 1]  (rotation part W x a, a = d(u, v)/d point).
        # All three are affine in W: [Ku, Kv, m] = W @ L + L1, with the camera -> ECM map of the
        # increments (block diag(Rc, Rc)) folded in.
        L = np.zeros((C, 3, 18))
        L1 = np.zeros((C, 18))
        fx, sk, fy = Kp[:, 0, 0], Kp[:, 0, 1], Kp[:, 1, 1]
        L[:, 0, 2], L[:, 1, 2], L[:, 2, 0], L[:, 2, 1] = sk, -fx, -sk, fx          # Ku
        L1[:, 3], L1[:, 4] = fx, sk
        L[:, 0, 8], L[:, 2, 6] = fy, -fy                                          # Kv
        L1[:, 10] = fy
        L[:, 0, 13], L[:, 1, 12] = -1.0, 1.0                                      # m
        L1[:, 17] = 1.0
        Bc = np.zeros((C, 6, 6))                                                  # camera -> ECM
        Bc[:, :3, :3] = self.Rc
        Bc[:, 3:, 3:] = self.Rc
        for k in range(3):
            L[:, :, 6 * k:6 * k + 6] = L[:, :, 6 * k:6 * k + 6] @ Bc
            L1[:, 6 * k:6 * k + 6] = (L1[:, None, 6 * k:6 * k + 6] @ Bc)[:, 0]
        self._L, self._L1 = L[None], L1[None, :, None]
        self._out = np.array([-1.0, 1.0])                       # outward along the arc at A, E
        self._cos_end_zone = np.cos(self.half - np.deg2rad(1.0))  # feet within 1 deg of an end
        ang = np.linspace(-self.half, self.half, cfg.n_samples)
        self._samples = np.stack([np.cos(ang), np.sin(ang)], axis=1)       # (S, 2)
        self.is_kp = np.concatenate([np.ones((C, 10), bool), np.zeros((C, 2 * M), bool)], axis=1).ravel()


class ArcProblem:
    """Observations of one stereo frame, arranged for batched evaluation: per camera 5 keypoints
    and M centreline points (zero weight where absent or left out)."""

    def __init__(self, st: ArcStatic, obs: Mapping[str, ArcObservation]):
        self.__dict__.update(st.__dict__)
        cfg, C, M = st.cfg, st.C, st.M
        U, wU = np.zeros((C, 5, 2)), np.zeros((C, 5))
        O, wO = np.zeros((C, M, 2)), np.zeros((C, M))
        corr = np.ones(C)                 # per camera: centreline points per independent error
        for i, cam in enumerate(st.cams):
            o = obs.get(cam.name)
            if o is None:
                continue
            if o.uv is not None:
                uv = np.asarray(o.uv, float)
                sc = np.ones(5) if o.scores is None else np.asarray(o.scores, float)
                if uv.shape != (5, 2) or sc.shape != (5,):
                    raise RefineError("bad_keypoints", f"{cam.name}: need uv (5, 2) and scores (5,), "
                                      f"got {uv.shape} and {sc.shape}")
                sig = cfg.sigma_kp_px if o.keypoint_sigma_px is None else float(o.keypoint_sigma_px)
                if not (np.isfinite(sig) and sig > 0):
                    raise RefineError("bad_keypoints", f"{cam.name}: keypoint_sigma_px must be positive, got {sig}")
                ok = np.all(np.isfinite(uv), axis=1) & np.isfinite(sc) & (sc >= cfg.min_score)
                U[i, ok] = _undistort(cam, uv[ok])
                wU[i, ok] = np.minimum(sc[ok], 1.0) / sig ** 2
            if o.centreline is not None and len(o.centreline):
                pts, w = _select_curve(cam.name, o.centreline, o.centreline_w, M, cfg.min_centreline_w)
                O[i, :len(pts)] = _undistort(cam, pts)
                sig = cfg.sigma_curve_px if o.centreline_sigma_px is None else float(o.centreline_sigma_px)
                if not (np.isfinite(sig) and sig > 0):
                    raise RefineError("bad_centreline", f"{cam.name}: centreline_sigma_px must be positive, got {sig}")
                wO[i, :len(pts)] = w / sig ** 2
                if o.centreline_corr_points is not None:
                    corr[i] = float(o.centreline_corr_points)
                    if not (np.isfinite(corr[i]) and corr[i] >= 1):
                        raise RefineError("bad_centreline", f"{cam.name}: centreline_corr_points must be "
                                          f"at least 1, got {o.centreline_corr_points}")
                if o.on_arc is not None and np.count_nonzero(w) >= 3:
                    # keypoints a detector placed on its own fitted arc count the curve twice,
                    # with that arc's (weak-perspective) bias along it, which tips the mirror
                    # choice of small, far needles: the curve stands for them
                    on_arc = np.asarray(o.on_arc)
                    if on_arc.shape != (5,):
                        raise RefineError("bad_keypoints", f"{cam.name}: need on_arc (5,), got {on_arc.shape}")
                    wU[i, on_arc.astype(bool)] = 0.0
        self.U, self.wU, self.O, self.wO = U, wU, O, wO
        self.n_kp = int(np.count_nonzero(wU))
        self.n_curve = int(np.count_nonzero(wO))
        self.n_res = 2 * self.n_kp + self.n_curve
        if self.n_res < 6:
            raise RefineError("too_few_points", f"{self.n_kp} keypoints and {self.n_curve} centreline "
                              "points cannot fix 6 pose parameters")
        seen = [cam.name for i, cam in enumerate(st.cams) if wU[i].any() or wO[i].any()]
        if len(seen) < cfg.min_cameras:
            raise RefineError("too_few_cameras", f"the needle is seen by {len(seen)} camera(s) ({', '.join(seen)}), "
                              f"min_cameras is {cfg.min_cameras}")
        # Residual weights in evaluation order, per camera: keypoint u (5), keypoint v (5),
        # curve normal distance (M), curve overshoot beyond the arc's ends (M).
        self.wp = np.concatenate([wU, wU, wO, wO], axis=1).ravel()
        self.used_kp, self.used_curve = (self.wp > 0) & st.is_kp, (self.wp > 0) & ~st.is_kp
        # the weight of each residual in the covariance relative to the fit's
        self.cov_scale = np.concatenate([np.ones((C, 10)), np.repeat(1.0 / corr[:, None], 2 * M, axis=1)],
                                        axis=1).ravel()
        # Cauchy scales (squared, in sigmas) per residual: the overshoot past an arc end has its
        # own, so that a spur past the needle's end (thread, glare) cannot drag the arc along
        c_end = cfg.cauchy_scale_end ** 2
        self._c2 = np.concatenate([np.full((C, 10 + M), cfg.cauchy_scale ** 2), np.full((C, M), c_end)],
                                  axis=1).ravel()
        self._Uu, self._Uv = U[None, :, :, 0], U[None, :, :, 1]
        self._Ou, self._Ov = O[None, :, :, 0], O[None, :, :, 1]
        # the same padded in front with the keypoints, for the feet's Newton steps (which
        # leave the keypoints' angles alone)
        self._Opu = np.concatenate([U[None, :, :, 0], self._Ou], axis=2)
        self._Opv = np.concatenate([U[None, :, :, 1], self._Ov], axis=2)

    def _axes(self, R, t):
        """Needle pose in each camera (P, C, ...): translation, and E (P, C, 2, 6) with rows
        radius * [e1 e2] and radius * [e2 -e1] (needle axes turned so that the arc's middle is
        on +x): [cos, sin] @ E gives an arc point (less the origin) and its tangent."""
        tcam = (self.Rc[None] @ t[:, None, :, None])[..., 0] + self.tc     # (P, C, 3)
        # camera-frame columns [e1, e2, e2, -e1] (times radius); transposed and reshaped: the
        # rows [e1 e2] and [e2 -e1]
        E = np.swapaxes(self.Rc[None] @ (R @ self._W)[:, None], 2, 3).reshape(len(R), self.C, 2, 6)
        return tcam, E

    def _project_arc(self, cs, E, t4, full: bool = False):
        """Pixels (u, v) of arc points (P, C, N) at angles given as (cos, sin) ``cs`` (P, C, N, 2)
        and their derivatives (du, dv) along the arc (per radian); ``t4`` the camera-frame
        origin (P, C, 1, 3). With ``full`` also the depth z, 1/z, normalised x, y and the
        points less the origin."""
        XT = cs @ E
        W = XT[..., :3]
        z = W[..., 2] + t4[..., 2]
        iz = 1.0 / np.maximum(z, 1e-9)
        x, y = (W[..., 0] + t4[..., 0]) * iz, (W[..., 1] + t4[..., 1]) * iz
        dx, dy = (XT[..., 3] - x * XT[..., 5]) * iz, (XT[..., 4] - y * XT[..., 5]) * iz
        out = (self._fx * x + self._sk * y + self._cx, self._fy * y + self._cy,
               self._fx * dx + self._sk * dy, self._fy * dy)
        return out + (z, iz, x, y, W) if full else out

    def nearest_samples(self, E, t4):
        """Starts (P, C, 5 + M, 2) of the feet: (cos, sin) of the angle from the arc's middle of
        the keypoints A..E, then for each observed point the nearest of ``n_samples`` projected
        arc points."""
        X = self._samples @ E[..., :3] + t4                                # (P, C, S, 3)
        iz = 1.0 / np.maximum(X[..., 2], 1e-9)
        x, y = X[..., 0] * iz, X[..., 1] * iz
        u = (self._fx * x + self._sk * y + self._cx)[:, :, None, :]
        v = (self._fy * y + self._cy)[:, :, None, :]
        k = ((u - self._Ou[..., None]) ** 2 + (v - self._Ov[..., None]) ** 2).argmin(axis=3)
        cs = np.empty(k.shape[:2] + (5 + self.M, 2))
        cs[:, :, :5] = self._kp_cs
        cs[:, :, 5:] = self._samples[k]
        return cs

    def _newton(self, cs, E, t4, steps):
        """``steps`` Newton steps of the feet ``cs`` (the part after the 5 keypoints) along the
        projected arc towards the observed points, clamped to the arc."""
        if steps < 1:
            return cs
        c = cs[:, :, 5:]
        for _ in range(steps):
            u, v, tu, tv = self._project_arc(c, E, t4)
            du, dv = u - self._Ou, v - self._Ov
            step = -(tu * du + tv * dv) / np.maximum(tu * tu + tv * tv, 1e-300)
            step = np.minimum(np.maximum(step, -0.5), 0.5)[..., None]
            c = (c + step * c[..., ::-1] * self._perp) / np.sqrt(1.0 + step * step)
            c = np.where(c[..., :1] < self._cos_half, np.where(c[..., 1:] > 0, self._end_cs[1], self._end_cs[0]), c)
        out = np.empty_like(cs)
        out[:, :, :5] = self._kp_cs
        out[:, :, 5:] = c
        return out

    def feet(self, R, t, start=None, axes=None):
        """Feet (K, C, 5 + M, 2) for poses (R, t): (cos, sin) of the arc angles (from the arc's
        middle) of the keypoints and of each observed point's nearest arc point. From
        ``start`` (the feet at a nearby pose: ``warm_steps`` Newton steps) or else from the
        nearest of ``n_samples`` projected arc points (``foot_steps`` Newton steps)."""
        tcam, E = self._axes(R, t) if axes is None else axes
        t4 = tcam[:, :, None, :]
        cs = self.nearest_samples(E, t4) if start is None else start
        return self._newton(cs, E, t4, self.cfg.foot_steps if start is None else self.cfg.warm_steps)

    def evaluate(self, R, t, feet, jacobian: bool = True, axes=None):
        """Residuals (P, n) in px of P poses ``(R (P,3,3), t (P,3))`` with the ``feet`` (P, C,
        5 + M, 2) (see ``feet``) held fixed, their Jacobians (P, n, 6) w.r.t. the
        ECM increment [dr, dt] (None unless ``jacobian``), and whether each pose keeps the
        keypoints and the needle's centre in front of both cameras.

        Per camera: keypoint u (5) and v (5) errors; for each observed point the signed
        distance to the arc's tangent at its foot, and its overshoot past the nearer end of the
        arc along the outward tangent there (a hinge, kept only where the foot is at that end:
        elsewhere the projected arc may curve back past an end's tangent). Together they are
        the point's distance to the arc. The distance's derivative at a foot needs no foot
        derivative (envelope theorem); the overshoot's leaves out the turn of the end's tangent.
        """
        P = len(R)
        tcam, E = self._axes(R, t) if axes is None else axes
        t4 = tcam[:, :, None, :]
        co, si = feet[:, :, 5:, 0], feet[:, :, 5:, 1]
        u, v, tu, tv, z, iz, x, y, W = self._project_arc(feet, E, t4, full=True)
        zc = tcam[..., 2]
        valid = ((z[..., :5].min(axis=(1, 2)) > self.cfg.min_depth_m) & (zc.min(axis=1) > self.cfg.min_depth_m)
                 & (zc.max(axis=1) < self.cfg.max_depth_m))
        ru, rv = u[..., :5] - self._Uu, v[..., :5] - self._Uv
        du, dv = u[..., 5:] - self._Ou, v[..., 5:] - self._Ov
        itn = 1.0 / np.maximum(np.sqrt(tu * tu + tv * tv), 1e-300)
        nx, ny = -tv[..., 5:] * itn[..., 5:], tu[..., 5:] * itn[..., 5:]
        r_n = nx * du + ny * dv
        # outward unit tangents at A (index 0, towards -angle) and E (index 4)
        ox = tu[..., 0:5:4] * itn[..., 0:5:4] * self._out
        oy = tv[..., 0:5:4] * itn[..., 0:5:4] * self._out
        at_e = si > 0
        ex = np.where(at_e, ox[..., 1:], ox[..., :1])
        ey = np.where(at_e, oy[..., 1:], oy[..., :1])
        ov = np.where(at_e,
                      (self._Ou - u[..., 4:5]) * ox[..., 1:] + (self._Ov - v[..., 4:5]) * oy[..., 1:],
                      (self._Ou - u[..., 0:1]) * ox[..., :1] + (self._Ov - v[..., 0:1]) * oy[..., :1])
        at_end = co < self._cos_end_zone
        active = at_end & (ov > 0.0)
        r_t = np.where(at_end, np.maximum(ov, 0.0), 0.0)
        r = np.concatenate([ru, rv, r_n, r_t], axis=2).reshape(P, -1)
        if not jacobian:
            return r, None, valid

        # d(u, v)/d[dr, dt] of every point (see ArcStatic: Ku, Kv, m), in the ECM frame
        Q = W @ self._L + self._L1                                          # (P, C, N, 18)
        izc = iz[..., None]
        Gu = (Q[..., :6] - (u - self._cx)[..., None] * Q[..., 12:]) * izc
        Gv = (Q[..., 6:12] - (v - self._cy)[..., None] * Q[..., 12:]) * izc
        # curve rows: along the normal at the foot; overshoot rows: minus the outward tangent at
        # the end's point (A or E), where active
        rows_n = nx[..., None] * Gu[..., 5:, :] + ny[..., None] * Gv[..., 5:, :]
        cu, cv = np.where(active, -ex, 0.0)[..., None], np.where(active, -ey, 0.0)[..., None]
        at_e4 = at_e[..., None]
        rows_t = (cu * np.where(at_e4, Gu[..., 4:5, :], Gu[..., 0:1, :])
                  + cv * np.where(at_e4, Gv[..., 4:5, :], Gv[..., 0:1, :]))
        J = np.concatenate([Gu[..., :5, :], Gv[..., :5, :], rows_n, rows_t], axis=2).reshape(P, -1, 6)
        return r, J, valid

    def linearise(self, R, t, start=None):
        """Residuals (K, n), Jacobians (K, n, 6) w.r.t. the ECM increment [dr, dt], the observed
        points' feet (a start for nearby poses) and validity of K poses. ``start``: see ``feet``."""
        axes = self._axes(R, t)
        cs = self.feet(R, t, start, axes)
        r, J, valid = self.evaluate(R, t, cs, axes=axes)
        return r, J, cs, valid

    def robust(self, r):
        """Per-residual Cauchy cost and IRLS weight (prior weights included)."""
        c2 = self._c2
        s2 = self.wp * r ** 2
        return c2 * np.log1p(s2 / c2), self.wp / (1.0 + s2 / c2)


def _undistort(cam, uv):
    from common.geometry.camera import undistort_pixels
    return undistort_pixels(cam.K, cam.dist, uv)


def _select_curve(name: str, pts, w, m: int, w_min: float):
    """At most m of the observed centreline points, evenly spaced in arc length. Points are
    picked, not interpolated, so that an exact observation stays exact."""
    pts = np.asarray(pts, float)
    w = np.ones(len(pts)) if w is None else np.asarray(w, float)
    if pts.ndim != 2 or pts.shape[1] != 2 or w.shape != (len(pts),):
        raise RefineError("bad_centreline", f"{name}: need centreline (N, 2) and centreline_w (N,), "
                          f"got {pts.shape} and {w.shape}")
    if not (np.isfinite(pts.sum() + w.sum()) and w.min(initial=1.0) >= w_min):
        ok = np.isfinite(pts).all(axis=1) & np.isfinite(w) & (w >= w_min)
        pts, w = pts[ok], w[ok]
    w = np.minimum(w, 1.0)
    if len(pts) <= m:
        return pts, w
    dp = np.diff(pts, axis=0)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(dp[:, 0], dp[:, 1]))])
    idx = np.minimum(np.searchsorted(s, s[-1] * np.arange(m) / (m - 1)), len(pts) - 1)
    idx = idx[np.concatenate([[True], idx[1:] > idx[:-1]])]
    return pts[idx], w[idx]
