"""``needletrack bench tracker``: the needle tracker (``common.geometry.needle_tracker``) alone, on
the motion scripts' exact takes, no rendering.

    needletrack bench tracker [--takes 20] [--seed 100] [--arm-error dvrk [--arm-correction]] [--json OUT.json]

Takes play pickup, handover, throw and suture in turn (``common.sim.motion.script_take``, the
scripts of the moving test set). Each frame's measurement is the true pose moved by an error
drawn from a stated covariance (``--pos-mm`` and ``--rot-deg``: 1 sigma along three random axes
per take, the last of each the larger, as a stereo fit's depth and turn about the arc's axis).
Two runs: every frame measured, and ``hidden``: no measurement while an instrument holds the
needle after its 5th held frame (the jaws hide the arc, the refine node poses nothing). Per run:
frames, mean position and orientation error, NEES median (chi-square(6): 5.35), poses turned end
for end (``swaps``), and ``T_jaw_needle`` from the 10th held frame on (mean errors, frames whose
holder the tracker names wrongly). ``--arm-error SPEC`` (``common.sim.arm_error``): the jaws as an
arm with that error reports them (``T_jaw_needle`` scored in the true jaw frame); with
``--arm-correction`` the tracker estimates each arm's error (``TrackerConfig.arm_correction``),
and the corrected jaws are scored against the true ones where the needle is held, from 3 s after
it is first held (``correction``).

    needletrack bench tracker --replay RECORDING --dataset DIR [--tracker-param KEY=VALUE ...]

The tracker replayed on a run's refined poses (``needletrack eval --record RECORDING``, on the
same folder; ``common.evaluation.tracker_replay``): the moving takes' table of ``needletrack
eval`` for ``tracked`` in seconds, with the tracker's params as given (default: the node's). For changing the tracker; the
documented figures come from ``needletrack eval``.
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from common.evaluation.metrics import SWAP_DEG, pose_nees
from common.geometry.needle import NeedleModel
from common.geometry.needle_tracker import Jaw, Measurement, NeedleTracker, TrackerConfig, retract
from common.geometry.transforms import inv_T, pose_error
from common.sim.arm_error import arm_error_config, draw_arm_errors
from common.sim.motion import FPS, MOTIONS, script_take


def stated_covariance(rng, pos_mm=(0.2, 0.2, 0.8), rot_deg=(0.5, 0.5, 2.0)) -> np.ndarray:
    """A 6x6 [w, v] covariance with these 1-sigma errors along three random orthogonal axes."""
    Q = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    C = np.zeros((6, 6))
    C[:3, :3] = Q @ np.diag(np.radians(rot_deg) ** 2) @ Q.T
    C[3:, 3:] = Q @ np.diag((np.asarray(pos_mm) * 1e-3) ** 2) @ Q.T
    return C


def run_take(frames, rng, C, needle: NeedleModel, hidden: bool, arm_errors: dict | None = None,
             config: TrackerConfig = TrackerConfig()) -> list:
    """Per frame of a take: (position m, orientation rad, nees, true holder, held run index,
    tracker's holder, T_jaw_needle errors or None, the holder's corrected jaws' errors from 3 s
    after the needle is first held, or None) for the frames the tracker posed. ``arm_errors``:
    {name: ArmError} of the arms that report the jaws (none: exact)."""
    tr, rows, run, prev, first = NeedleTracker(needle, config), [], 0, None, None
    dt_ns = int(round(1e9 / FPS))
    for k, fr in enumerate(frames):
        holder = next((n for n, (_, _, h) in sorted(fr.instruments.items()) if h), None)
        run = run + 1 if holder is not None and holder == prev else 0
        prev = holder
        first = k if first is None and holder is not None else first
        m = None
        if not (hidden and holder is not None and run >= 5):
            m = Measurement(retract(fr.T_world_needle, rng.multivariate_normal(np.zeros(6), C)), C)
        jaws = {n: Jaw(*(arm_errors[n].report(T, jaw, k) if arm_errors else (T, jaw)))
                for n, (T, jaw, _) in fr.instruments.items()}
        o = tr.step(k * dt_ns, jaws, m)
        if o is None:
            continue
        dt, dr = pose_error(o.T_world_needle, fr.T_world_needle)
        in_hand = correction = None
        if holder is not None and o.holder == holder:
            in_hand = pose_error(o.T_jaw_needle, inv_T(fr.instruments[holder][0]) @ fr.T_world_needle)
        if holder is not None and o.corrections and holder in o.corrections and k >= first + 3 * FPS:
            correction = pose_error(o.corrections[holder][0] @ jaws[holder].T_world_jaw, fr.instruments[holder][0])
        rows.append((dt, dr, pose_nees(o.T_world_needle, o.covariance, fr.T_world_needle), holder, run,
                     o.holder, in_hand, correction))
    return rows


def summarise(rows: list) -> dict:
    pos, rot, nees = (np.array([r[i] for r in rows]) for i in range(3))
    late = [r for r in rows if r[3] is not None and r[4] >= 9]
    good = np.array([r[6] for r in late if r[6] is not None]).reshape(-1, 2)
    corr = np.array([r[7] for r in rows if r[7] is not None]).reshape(-1, 2)
    out = {"frames": len(rows), "position_mm": float(pos.mean() * 1e3), "orientation_deg": float(np.degrees(rot.mean())),
           "nees_median": float(np.median(nees)), "swaps": int((np.degrees(rot) > SWAP_DEG).sum()),
           "in_hand": {"frames": len(late), "wrong_holder": sum(r[5] != r[3] for r in late),
                       "position_mm": float(good[:, 0].mean() * 1e3) if len(good) else None,
                       "orientation_deg": float(np.degrees(good[:, 1].mean())) if len(good) else None}}
    if len(corr):
        out["correction"] = {"frames": len(corr), "position_mm": float(corr[:, 0].mean() * 1e3),
                             "orientation_deg": float(np.degrees(corr[:, 1].mean())),
                             "within_1mm_1deg": float(((corr[:, 0] <= 1e-3) & (corr[:, 1] <= np.radians(1))).mean())}
    return out


def _replay(args) -> int:
    """``--replay``: the tracker on a recording (module docstring)."""
    from common.evaluation.recording import RecordingError
    from common.data.dataset import Dataset, DatasetError
    from common.evaluation.moving import moving_markdown
    from common.evaluation.tracker_replay import replay_summary, replay_tracker
    from common.runtime.graph import parse_param
    from common.runtime.params import parse_params
    if not (args.replay and args.dataset):
        print("needletrack bench tracker: --replay and --dataset go together", file=sys.stderr)
        return 2
    try:
        raw = dict(parse_param(p) for p in args.tracker_param)
        config = parse_params(TrackerConfig, raw, "--tracker-param")
        ds = Dataset(args.dataset, check_files=False)
        col = replay_tracker(ds, args.replay, config)
    except (ValueError, RecordingError, DatasetError, OSError) as exc:
        print(f"needletrack bench tracker: {exc}", file=sys.stderr)
        return 2
    summary = replay_summary(ds, col)
    if summary is None:
        print(f"needletrack bench tracker: {args.dataset} has no moving take", file=sys.stderr)
        return 2
    print("\n".join(moving_markdown(summary)))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(summary, f, indent=2, default=float)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="needletrack bench tracker", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--takes", type=int, default=20)
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--pos-mm", type=float, nargs=3, default=(0.2, 0.2, 0.8))
    ap.add_argument("--rot-deg", type=float, nargs=3, default=(0.5, 0.5, 2.0))
    ap.add_argument("--arm-error", default=None, help="the jaws as an arm with this error reports them "
                    "(common.sim.arm_error: exact, dvrk, dvrk:field=value,...)")
    ap.add_argument("--arm-correction", action="store_true", help="the tracker estimates each arm's error")
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument("--replay", metavar="RECORDING", help="a recording of a run's refined poses "
                    "(needletrack eval --record): the tracker replayed on them (needs --dataset)")
    ap.add_argument("--dataset", metavar="DIR", help="with --replay: the folder the run was on")
    ap.add_argument("--tracker-param", action="append", default=[], metavar="KEY=VALUE",
                    help="with --replay: a tracker param (repeatable), e.g. arm_correction=true")
    args = ap.parse_args(argv)
    if args.replay or args.dataset or args.tracker_param:
        return _replay(args)
    if args.takes < 1 or min(args.pos_mm) <= 0 or min(args.rot_deg) <= 0:
        print("needletrack bench tracker: --takes must be >= 1 and the sigmas positive", file=sys.stderr)
        return 2
    try:
        arm_error = arm_error_config(args.arm_error)
    except ValueError as exc:
        print(f"needletrack bench tracker: --arm-error: {exc}", file=sys.stderr)
        return 2
    config = TrackerConfig(arm_correction=args.arm_correction)
    needle = NeedleModel()
    out = {}
    for hidden in (False, True):
        rows = []
        for i in range(args.takes):
            frames = script_take(MOTIONS[i % len(MOTIONS)], np.random.default_rng(args.seed + i), needle,
                                 needle.wire_diameter_m / 2).frames
            rng = np.random.default_rng(args.seed + 10_000 + i)
            errors = draw_arm_errors(arm_error, (args.seed, i), {n: T for n, (T, _, _) in frames[0].instruments.items()})
            rows += run_take(frames, rng, stated_covariance(rng, args.pos_mm, args.rot_deg), needle, hidden,
                             errors, config)
        r = out["hidden" if hidden else "seen"] = summarise(rows)
        h = r["in_hand"]
        line = (f"{'hidden in the jaws' if hidden else 'every frame seen'}: {r['frames']} frames, "
                f"{r['position_mm']:.3f} mm / {r['orientation_deg']:.3f} deg mean, NEES median {r['nees_median']:.2f}, "
                f"{r['swaps']} swaps; T_jaw_needle from the 10th held frame: {h['frames']} frames, "
                f"{h['position_mm']:.3f} mm / {h['orientation_deg']:.3f} deg, {h['wrong_holder']} wrong holder")
        if "correction" in r:
            cr = r["correction"]
            line += (f"; corrected jaws from 3 s after first held: {cr['frames']} frames, {cr['position_mm']:.3f} mm / "
                     f"{cr['orientation_deg']:.3f} deg, {100 * cr['within_1mm_1deg']:.0f}% within 1 mm and 1 deg")
        print(line)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=2)
    return 0
