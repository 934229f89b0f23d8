"""The batched Levenberg-Marquardt both pose solvers run (common/geometry/lm.py), on a problem
of its own: a rigid pose fitted to 3-D point pairs (residuals ``R p + t - q``)."""
import numpy as np
import pytest

from common.geometry import lm
from common.geometry.transforms import rotvec_to_R, skew

rng = np.random.default_rng(4)
P = rng.normal(size=(8, 3)) * 0.05


def point_fit(Q, weights=None):
    """``linearise`` of the point-pair fit: r = R p + t - q, d r / d[w, v] = [-[R p]x, I]."""
    def linearise(R, t, prev=None):
        q = P @ np.swapaxes(R, 1, 2) + t[:, None, :]
        r = (q - Q).reshape(len(R), -1)
        J = np.concatenate([-np.stack([np.stack([skew(x) for x in qi]) for qi in q - t[:, None, :]]),
                            np.broadcast_to(np.eye(3), q.shape + (3,))], axis=3).reshape(len(R), -1, 6)
        w = None if weights is None else np.broadcast_to(np.repeat(weights, 3), r.shape).copy()
        cost = np.einsum("km,km->k", r, r if w is None else r * w)
        return r, J, w, cost, {"calls": np.zeros(len(R))}
    return linearise


def stop(dx, acc, pred, c1, c0, fits, act):
    return acc & (np.abs(dx).max(axis=1) < 1e-12) | (fits.rej[act] >= 8)


@pytest.mark.parametrize("damping", ["nielsen", "thirds"])
@pytest.mark.parametrize("scaled", [True, False])
def test_both_dampings_recover_the_pose_from_far_starts(damping, scaled):
    R_true, t_true = rotvec_to_R([0.3, -0.5, 0.8]), np.array([0.01, -0.02, 0.15])
    Q = P @ R_true.T + t_true
    lin = point_fit(Q, weights=np.linspace(0.5, 2.0, len(P)))
    R0 = np.stack([rotvec_to_R(rng.normal(size=3) * 0.8) for _ in range(5)])
    t0 = rng.normal(size=(5, 3)) * 0.05
    fits = lm.run(lm.Fits(R0, t0, lin(R0, t0)), lin, 100, stop, damping=damping, scaled=scaled)
    assert fits.converged.all() and (fits.iters > 0).all() and fits.rounds == fits.iters.max()
    assert np.abs(fits.R - R_true).max() < 1e-9 and np.abs(fits.t - t_true).max() < 1e-11
    assert (fits.cost < 1e-20).all()


def test_trust_region_settling_merging_and_taking_a_subset():
    R_true, t_true = np.eye(3), np.array([0.0, 0.0, 0.2])
    lin = point_fit(P @ R_true.T + t_true)
    R0 = np.stack([rotvec_to_R([0.5, 0, 0]), rotvec_to_R([0.7, 0, 0]), np.eye(3)])
    t0 = np.array([[0.0, 0.0, 0.3], [0.0, 0.0, 0.35], [0.0, 0.0, 0.2]])
    R0[2], t0[2] = R_true, t_true + 1e-4
    steps = []

    def watch(dx, acc, pred, c1, c0, fits, act):
        steps.append(np.abs(dx).max(axis=0))
        return stop(dx, acc, pred, c1, c0, fits, act)

    def merge(fits, act):          # fit 1 heads where fit 0 goes: it stops once fit 0 has converged
        go = np.ones(len(act), bool)
        if fits.converged[0]:
            go &= act != 1
            fits.merged[act[act == 1]] = 0
        return go
    fits = lm.Fits(R0, t0, lin(R0, t0))
    fits = lm.run(fits, lin, 200, watch, damping="thirds", max_step=(0.05, 0.01), settle_tol=1e-12,
                  dof=len(P) * 3 - 6, after=merge)
    assert max(s[:3].max() for s in steps) <= 0.05 + 1e-15 and max(s[3:].max() for s in steps) <= 0.01 + 1e-15
    assert fits.converged[[0, 2]].all() and fits.done.all()
    assert np.abs(fits.t[0] - t_true).max() < 1e-9 and np.abs(fits.t[2] - t_true).max() < 1e-9
    assert fits.merged[1] == 0 and not fits.converged[1] and fits.iters[1] == fits.iters[0]
    sub = fits.take([2, 0])
    assert len(sub) == 2 and np.array_equal(sub.R[1], fits.R[0]) and sub.extra["calls"].shape == (2,)
    assert sub.rounds == fits.rounds


def test_a_start_that_is_not_valid_is_done_before_it_starts():
    lin = point_fit(P)

    def behind(R, t, prev=None):          # a pose beyond 0.5 m is not valid (inf)
        r, J, w, cost, extra = lin(R, t, prev)
        return r, J, w, np.where(t[:, 2] > 0.5, np.inf, cost), extra
    R0, t0 = np.stack([np.eye(3)] * 2), np.array([[0.0, 0, 1.0], [0.0, 0, 0.01]])
    fits = lm.run(lm.Fits(R0, t0, behind(R0, t0)), behind, 50, stop)
    assert fits.iters[0] == 0 and not fits.converged[0] and np.array_equal(fits.t[0], t0[0])
    assert fits.converged[1] and np.abs(fits.t[1]).max() < 1e-11
