"""Batched Levenberg-Marquardt over rigid poses: the one loop of the PnP's reprojection fit
(``reprojection``) and the dense arc fit (``refine``).

K fits run at once (vectorised numpy). A fit's pose is ``(R, t)``; a step ``dx = [dw, dv]``
(rad, m) moves it as ``R <- exp([dw]x) R``, ``t <- t + dv``. The problem linearises poses: its
``linearise(R, t, prev)`` returns ``(r, J, w, cost, extra)``: residuals ``r`` (k, m), their
Jacobian ``J`` (k, m, 6) w.r.t. ``dx``, per-residual weights ``w`` (k, m) or None (all 1), the
cost (k,) (inf for a pose that is not valid, e.g. behind a camera) and per-fit arrays the
problem carries from a pose to the next (``extra``, a dict; ``prev`` is its rows for the poses
stepped from, or None after a large step: see ``relinearise``).

Each iteration solves the damped normal equations ``(H + lam diag(H)) dx = -g`` (``H = J^T W
J``, ``g = J^T W r``) in their Jacobi-scaled form (rotation and translation columns differ by
~1e2), limits the step (``max_step``), takes it where the cost does not rise and updates the
damping (``damping``). The problem's ``stop`` rule says which fits are done; ``settle_tol``
and ``after`` are the two solvers' other ways to stop (see ``run``).
"""
from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from common.geometry.transforms import rotvecs_to_Rs

_I6 = np.eye(6)


class Fits:
    """The state of K fits: poses ``R`` (K, 3, 3), ``t`` (K, 3); at them ``r``, ``J``, ``w``,
    ``cost`` and the problem's ``extra``; damping ``lam`` (and Nielsen's ``nu``), rejected steps
    in a row ``rej``, iterations per fit ``iters`` and ``rounds`` in all, ``done``,
    ``converged`` (stopped by the stop rule or ``settle_tol``) and ``merged`` (the index of the
    fit it stopped at, -1: none)."""

    def __init__(self, R, t, linearised, lam0: float = 1e-3):
        r, J, w, cost, extra = linearised
        K = len(R)
        self.R, self.t, self.r, self.J, self.w, self.cost, self.extra = R, t, r, J, w, cost, dict(extra)
        self.lam, self.nu = np.full(K, lam0), np.full(K, 2.0)
        self.rej = np.zeros(K, int)
        self.iters = np.zeros(K, int)
        self.rounds = 0
        self.done = ~np.isfinite(cost)
        self.converged = np.zeros(K, bool)
        self.merged = np.full(K, -1)

    _ARRAYS = ("R", "t", "r", "J", "w", "cost", "lam", "nu", "rej", "iters", "done", "converged", "merged")

    def take(self, idx) -> "Fits":
        """The fits ``idx`` alone (``merged`` indices refer to the old numbering)."""
        out = object.__new__(Fits)
        for k in self._ARRAYS:
            v = getattr(self, k)
            setattr(out, k, None if v is None else v[idx])
        out.extra = {k: v[idx] for k, v in self.extra.items()}
        out.rounds = self.rounds
        return out

    def __len__(self) -> int:
        return len(self.R)


def damped_step(H: np.ndarray, g: np.ndarray, lam: np.ndarray, scaled: bool = True) -> np.ndarray:
    """``dx`` (k, 6) solving ``(H + lam diag(H)) dx = -g`` per fit: Jacobi-scaled (least squares
    where the system is singular), or with ``scaled`` False as written (the PnP's form, kept so
    that its figures stay as measured; None where singular)."""
    if not scaled:
        D = np.einsum("kii->ki", H) + 1e-30
        try:
            return -np.linalg.solve(H + (lam[:, None] * D)[:, :, None] * _I6, g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            return None
    dg = np.maximum(np.diagonal(H, axis1=1, axis2=2), 1e-300)
    sc = 1.0 / np.sqrt(dg)
    A = H * sc[:, :, None] * sc[:, None, :] + lam[:, None, None] * _I6
    try:
        return -sc * np.linalg.solve(A, (g * sc)[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return -sc * np.stack([np.linalg.lstsq(a, b * c, rcond=None)[0] for a, b, c in zip(A, g, sc)])


def run(fits: Fits, linearise: Callable, max_iter: int, stop: Callable, *,
        damping: str = "nielsen", max_step: Optional[tuple] = None, settle_tol: Optional[float] = None,
        dof: int = 1, relinearise: Optional[tuple] = None, after: Optional[Callable] = None,
        scaled: bool = True) -> Fits:
    """Up to ``max_iter`` iterations of the fits not yet done; returns ``fits`` (updated).

    ``stop(dx, accepted, pred, cost_new, cost_old, fits, act)`` -> (len(act),) bool: which of the
    fits ``act`` just stepped (``dx``; ``accepted`` where the cost did not rise; ``pred`` the
    decrease the linear model predicted) are done; they count as converged.
    ``damping``: ``"nielsen"`` (an accepted step scales ``lam`` by ``max(1/3, 1 - (2 rho - 1)^3)``
    with ``rho`` the actual over the predicted decrease, a rejected one by ``nu``, which doubles)
    or ``"thirds"`` (``lam / 3``, at least 1e-9, after an accepted step; ``lam * 4`` after a
    rejected one). ``max_step``: ``(rad, m)``, a step turns and moves no component more (a trust
    region). ``settle_tol``: a step within the trust region whose cost change ``dx' H dx`` is
    below ``settle_tol`` residual variances (cost / ``dof``, at most 1) is taken unevaluated and
    the fit is done. ``relinearise``: ``(rad, m)``; after a larger step the problem gets no
    ``prev`` (None: always ``prev``). ``after(fits, act)`` -> (len(act),) bool, which of the fits
    ``act`` still running go on (another stop rule, run after each iteration: the PnP's merge of
    fits heading to one minimum).
    """
    s = fits
    K = len(s)
    act = np.flatnonzero(~s.done)
    nielsen = damping == "nielsen"
    for _ in range(max_iter):
        if len(act) == 0:
            break
        s.rounds += 1
        s.iters[act] += 1
        r, J, lam = s.r[act], s.J[act], s.lam[act]
        JtW = np.swapaxes(J if s.w is None else J * s.w[act][..., None], 1, 2)
        H = JtW @ J
        g = (JtW @ r[..., None])[..., 0] if scaled else np.einsum("kmi,km->ki", J, r)
        dx = damped_step(H, g, lam, scaled)
        if dx is None:                         # singular: a rejected step for every fit
            s.lam[act] *= s.nu[act]
            s.nu[act] *= 2.0
            continue
        rot = tra = shrink = None
        if max_step is not None or relinearise is not None:
            adx = np.abs(dx)
            rot, tra = adx[:, :3].max(axis=1), adx[:, 3:].max(axis=1)
        if max_step is not None:
            shrink = np.minimum(1.0, np.minimum(max_step[0] / np.maximum(rot, 1e-300),
                                                max_step[1] / np.maximum(tra, 1e-300)))
            dx = dx * shrink[:, None]
            rot, tra = rot * shrink, tra * shrink
        if settle_tol is not None:
            quad = (dx[:, None, :] @ H @ dx[..., None])[:, 0, 0]
            # (residuals in sigmas: a variance above 1 is outliers' doing, not a looser bound)
            within = quad < settle_tol * np.minimum(s.cost[act] / dof, 1.0)
            if shrink is not None:
                within &= shrink == 1.0
            if within.any():
                iw = act[within]
                s.R[iw] = rotvecs_to_Rs(dx[within, :3]) @ s.R[iw]
                s.t[iw] = s.t[iw] + dx[within, 3:]
                s.done[iw] = True
                s.converged[iw] = True
                go = ~within
                if not go.any():
                    break
                act, dx, lam, g, H = act[go], dx[go], lam[go], g[go], H[go]
                if rot is not None:
                    rot, tra = rot[go], tra[go]
        # the decrease the linear model predicts: dx^T (lam D dx - g)
        D = np.maximum(np.diagonal(H, axis1=1, axis2=2), 1e-300) if scaled else np.einsum("kii->ki", H) + 1e-30
        pred = np.einsum("ki,ki->k", dx, lam[:, None] * D * dx - g)
        Rn = rotvecs_to_Rs(dx[:, :3]) @ s.R[act]
        tn = s.t[act] + dx[:, 3:]
        big = relinearise is not None and (rot.max() > relinearise[0] or tra.max() > relinearise[1])
        prev = None if big else {k: v[act] for k, v in s.extra.items()}
        rn, Jn, wn, cost_n, extra_n = linearise(Rn, tn, prev)
        old = s.cost[act]
        acc = cost_n <= old
        ia = act[acc]
        new = [("R", Rn), ("t", tn), ("r", rn), ("J", Jn), ("cost", cost_n)] + ([] if wn is None else [("w", wn)])
        if len(ia) == K:                       # every fit active and accepted: take them all
            for key, val in new:
                setattr(s, key, val)
            s.extra.update(extra_n)
        else:
            for key, val in new:
                getattr(s, key)[ia] = val[acc]
            for key, val in extra_n.items():
                s.extra[key][ia] = val[acc]
        if nielsen:
            nu = s.nu[act]
            with np.errstate(invalid="ignore", over="ignore"):
                rho = (old - cost_n) / np.maximum(pred, 1e-300)
                scale = np.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            s.lam[act] = np.where(acc, lam * scale, lam * nu)
            s.nu[act] = np.where(acc, 2.0, nu * 2.0)
        else:
            s.lam[act] = np.where(acc, np.maximum(lam / 3.0, 1e-9), lam * 4.0)
        s.rej[act] = np.where(acc, 0, s.rej[act] + 1)
        done = stop(dx, acc, pred, cost_n, old, s, act)
        if done.any():
            ad = act[done]
            s.done[ad] = True
            s.converged[ad] = True
            act = act[~done]
        if after is not None and len(act):
            go_on = after(s, act)
            s.done[act[~go_on]] = True
            act = act[go_on]
    return s
