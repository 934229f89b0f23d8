"""The classical needle detector (OpenCV only, no learning): the baseline that shows what the
learned detector buys.

1. Segment thin bright metal: white top-hat of a whiteness image, 2 min(B,G,R) - max(B,G,R)
   (the needle is grey or white on reddish tissue; the top-hat keeps structures thinner than its kernel, which
   removes instrument bodies), thresholded relative to the strongest response, at half size.
2. Fit each connected component's projection: the image of a circular arc under a (near)
   affine camera is an elliptical arc; fit an ellipse to its pixels (``cv2.fitEllipseDirect``),
   drop outlying pixels (e.g. an attached thread), refit.
3. Score each component as a needle: fraction of pixels on the ellipse, angular span, wire width,
   elongation; the best one above the threshold wins.
4. Place A..E: under an affine camera, points equally spaced in angle on the circle are equally
   spaced in the ellipse's eccentric anomaly, so A..E split the covered anomaly range into four
   equal parts (for an arc seen nearly edge-on, a line fit and equal arc length instead).
5. Tip or tail: the tip tapers (less wire per unit length near that end) and the thread leaves
   the tail (thin bright pixels continuing beyond that end).

The fitted arc is published as the centreline observation (``Keypoints.centreline``).
"""
from __future__ import annotations

import dataclasses
import logging

import cv2
import numpy as np

from common.detector.config import ClassicalConfig
from common.detector.end_identity import polyline_length
from common.runtime.messages import Keypoints

log = logging.getLogger("needletrack.classical_detector")


def _ellipse_frame(ell):
    (cx, cy), (d1, d2), ang = ell
    th = np.deg2rad(ang)
    u = np.array([np.cos(th), np.sin(th)]) * d1 / 2
    v = np.array([-np.sin(th), np.cos(th)]) * d2 / 2
    return np.array([cx, cy]), u, v


def _anomaly(pts, c, u, v):
    """Eccentric anomaly of points w.r.t. the ellipse c + u cos t + v sin t."""
    d = pts - c
    a = d @ u / max(u @ u, 1e-9)
    b = d @ v / max(v @ v, 1e-9)
    return np.arctan2(b, a)


def _covered_range(t):
    """(t0, t1) with t1 > t0: the smallest interval (mod 2 pi) covering the angles ``t``."""
    s = np.sort(np.mod(t, 2 * np.pi))
    gaps = np.diff(np.concatenate([s, [s[0] + 2 * np.pi]]))
    k = int(np.argmax(gaps))
    t0 = s[(k + 1) % len(s)]
    t1 = s[k]
    if t1 < t0:
        t1 += 2 * np.pi
    return t0, t1


class ClassicalDetector:
    """OpenCV-only needle detector: ``detect(image_bgr, camera, seq, stamp_ns) -> Keypoints``."""

    name = "classical"

    def __init__(self, config: ClassicalConfig | None = None, centreline_points: int = 48, **settings):
        """``config``: its settings, ``settings`` any of its fields set anew."""
        self.config = c = dataclasses.replace(config or ClassicalConfig(), **settings)
        self.threshold = float(c.threshold)
        self.scale = float(c.scale)
        self.min_tophat = float(c.min_tophat)
        self.n_line = int(centreline_points)

    # ------------------------------------------------------------ segmentation
    def segment(self, img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(binary mask, top-hat response) of thin bright structures at ``scale``."""
        small = cv2.resize(img, None, fx=self.scale, fy=self.scale, interpolation=cv2.INTER_AREA)
        lo = small.min(axis=2).astype(np.int16)
        hi = small.max(axis=2).astype(np.int16)
        g = np.clip(2 * lo - hi, 0, 255).astype(np.uint8)   # bright and unsaturated: metal
        k = max(5, int(round(22 * self.scale)) | 1)
        th = cv2.morphologyEx(g, cv2.MORPH_TOPHAT, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
        # the needle is the brightest thin thing: a threshold relative to the strongest response
        top = float(np.percentile(th, 99.97))
        mask = (th >= max(self.min_tophat, 0.45 * top)).astype(np.uint8)
        return mask, th

    # ------------------------------------------------------------ one component
    def _fit(self, pts: np.ndarray):
        """Ellipse fit with one round of outlier removal; None if degenerate."""
        if len(pts) < 8:
            return None
        try:
            ell = cv2.fitEllipseDirect(pts.astype(np.float32))
        except cv2.error:
            return None
        for _ in range(2):
            c, u, v = _ellipse_frame(ell)
            if not np.all(np.isfinite(np.concatenate([c, u, v]))) or min(np.linalg.norm(u), np.linalg.norm(v)) < 1e-3:
                return None
            t = _anomaly(pts, c, u, v)
            on = c + np.cos(t)[:, None] * u + np.sin(t)[:, None] * v
            r = np.linalg.norm(pts - on, axis=1)
            keep = r < max(1.5, 2.5 * np.median(r) + 0.5)
            if keep.sum() < 8:
                return None
            try:
                ell = cv2.fitEllipseDirect(pts[keep].astype(np.float32))
            except cv2.error:
                return None
        c, u, v = _ellipse_frame(ell)
        t = _anomaly(pts, c, u, v)
        on = c + np.cos(t)[:, None] * u + np.sin(t)[:, None] * v
        r = np.linalg.norm(pts - on, axis=1)
        return c, u, v, t, r

    def _candidate(self, pts: np.ndarray, th_vals: np.ndarray):
        fit = self._fit(pts)
        if fit is None:
            return None
        c, u, v, t, r = fit
        inl = r < max(1.6, 2.0 * float(np.median(r)) + 0.8)   # the wire band has a width
        if inl.sum() < 8:
            return None
        t0, t1 = _covered_range(t[inl])
        span = t1 - t0
        ts = np.linspace(t0, t1, 200)
        curve = c + np.cos(ts)[:, None] * u + np.sin(ts)[:, None] * v
        length = polyline_length(curve)
        if length < 10:
            return None
        width = inl.sum() / length
        frac = inl.mean()
        # plausibility of a projected 120-degree arc (foreshortening widens the anomaly range)
        # (a free ellipse fit to a 120-degree band often returns a wider anomaly range)
        s_span = np.clip(1 - max(0.0, abs(np.rad2deg(span) - 150) - 90) / 60, 0, 1)
        # wire 0.55-1.05 mm at 10-25 cm: about 1-4.5 px wide at half resolution
        s_width = np.clip(1 - max(0.0, 1.0 - width, width - 4.5) / 2.0, 0, 1)
        s_len = np.clip((length - 12) / 20, 0, 1)
        s_bright = np.clip(np.median(th_vals[inl]) / 60, 0, 1)
        score = float(frac * (0.3 + 0.7 * s_span) * s_width * s_len * (0.5 + 0.5 * s_bright))
        return {"score": score, "c": c, "u": u, "v": v, "t0": t0, "t1": t1, "t": t, "inl": inl,
                "length": length, "width": width}

    # ------------------------------------------------------------ public
    def detect(self, image, camera: str = "left", seq: int = 0, stamp_ns: int = 0) -> Keypoints:
        from common.detector.inference import as_bgr, image_problem
        problem = image_problem(image)
        if problem:
            log.warning("camera %s seq %d: bad image: %s", camera, seq, problem)
            return Keypoints.not_found(camera, seq, stamp_ns, self.name, f"bad image: {problem}")
        img = as_bgr(image)
        mask, th = self.segment(img)
        n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        best = None
        order = np.argsort(-stats[1:, cv2.CC_STAT_AREA])[:12] + 1
        for i in order:
            x, y, w, h, area = stats[i]
            if area < 12 or max(w, h) < 10 * self.scale * 2:
                continue
            ys, xs = np.nonzero(labels[y:y + h, x:x + w] == i)
            pts = np.stack([xs + x, ys + y], 1).astype(np.float64)
            cand = self._candidate(pts, th[pts[:, 1].astype(int), pts[:, 0].astype(int)].astype(float))
            if cand is not None and (best is None or cand["score"] > best["score"]):
                best = cand
                best["pts"] = pts
        if best is None or best["score"] < self.threshold:
            conf = 0.0 if best is None else best["score"]
            return Keypoints.not_found(camera, seq, stamp_ns, self.name,
                                       f"no needle: confidence {conf:.2f} < {self.threshold:.2f}", conf)
        c, u, v, t0, t1 = best["c"], best["u"], best["v"], best["t0"], best["t1"]
        ts = np.linspace(t0, t1, 5)
        kp = c + np.cos(ts)[:, None] * u + np.sin(ts)[:, None] * v
        tl = np.linspace(t0, t1, self.n_line)
        line = c + np.cos(tl)[:, None] * u + np.sin(tl)[:, None] * v
        if self._tip_is_last(best, th, mask):
            kp, line = kp[::-1], line[::-1]
        s = self.scale
        kp = (kp + 0.5) / s - 0.5          # half-res pixel centres -> full-res pixel centres
        line = (line + 0.5) / s - 0.5
        lo, hi = line.min(0), line.max(0)
        conf = float(min(1.0, best["score"]))
        return Keypoints(camera, seq, stamp_ns, True, kp, np.full(5, conf), conf,
                         np.array([lo[0], lo[1], hi[0], hi[1]]), self.name, None, line,
                         np.ones(len(line)), on_arc=np.array([False, True, True, True, False]))

    def _tip_is_last(self, b, th, mask) -> bool:
        """Which end is the tip: thinner end (taper) and no thread continuing beyond it."""
        t = np.mod(b["t"][b["inl"]] - b["t0"], 2 * np.pi)
        span = b["t1"] - b["t0"]
        q = span * 0.2
        n_start = float(np.sum(t < q))
        n_end = float(np.sum((t > span - q) & (t <= span)))
        taper = (n_end - n_start) / max(1.0, n_end + n_start)   # > 0: start is thinner -> tip first
        # thread: mask pixels just beyond each end, along the tangent
        c, u, v = b["c"], b["u"], b["v"]

        def beyond(tt, sign):
            p = c + np.cos(tt) * u + np.sin(tt) * v
            d = sign * (-np.sin(tt) * u + np.cos(tt) * v)
            d = d / max(np.linalg.norm(d), 1e-9)
            hits = 0
            for k in range(3, 12):
                q_ = np.round(p + k * d).astype(int)
                if 0 <= q_[1] < mask.shape[0] and 0 <= q_[0] < mask.shape[1]:
                    y0, y1 = max(0, q_[1] - 2), q_[1] + 3
                    x0, x1 = max(0, q_[0] - 2), q_[0] + 3
                    hits += int(mask[y0:y1, x0:x1].any())
            return hits / 9.0

        thread_start = beyond(b["t0"], -1.0)
        thread_end = beyond(b["t1"], +1.0)
        vote = taper + (thread_end - thread_start)   # > 0: tip at the start
        return vote < 0


# ---------------------------------------------------------------- detector-node backend

from common.detector.backends import BackendError, KeypointBackend  # noqa: E402
from common.runtime.params import config_from  # noqa: E402


class ClassicalBackend(KeypointBackend):
    """Backend ``classical`` of the detector node. Params: ``threshold`` (0.5), ``scale`` (0.5:
    the working resolution), ``min_tophat`` (18 grey levels)."""

    name = "classical"
    needs_image = True

    def __init__(self, params=None):
        super().__init__(params)
        p = self.p
        try:
            self.detector = ClassicalDetector(config_from(ClassicalConfig, p))
        except (TypeError, ValueError) as exc:
            raise BackendError(f"classical backend: bad params: {exc}") from exc

    def detect(self, image, camera, truth, calib, *, seq=0, stamp_ns=0) -> Keypoints:
        return self.detector.detect(image, camera, seq, stamp_ns)
