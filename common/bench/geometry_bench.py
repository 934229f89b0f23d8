"""Measure the geometry methods on the oracle: pose error against keypoint noise, and speed.

The paper's protocol with exact geometry: random needle poses 10-25 cm from the built-in
endoscope (``oracle.random_needle_pose``), oracle keypoints with Gaussian noise in each image,
errors in the ECM frame (position of the needle origin in mm, orientation in degrees).
Multi-view: the ECM moves its yaw joint by 0.05 rad between views (``common.geometry.ecm_kinematics``),
one estimate per view, the fused pose scored at the last view.

    needletrack bench geometry [--poses 200] [--noise 0 0.25 0.5 1 2] [--seed 0]

(or ``python -m common.bench.geometry_bench``) prints two Markdown tables: the CPU time per stereo frame
of each method (``--speed-only``: just that), then mean and median errors, frames without a
pose, and the median wall-clock time per frame (per fused frame for fusion, excluding the PnP it
fuses; wall-clock times suffer from other processes' load, the CPU times much less).
"""
from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field

import numpy as np

from common.geometry.camera import StereoRig
from common.geometry.ecm_kinematics import MULTIVIEW_STEP_RAD, EcmArm
from common.geometry.fusion import MultiViewFusion
from common.geometry.needle import NeedleModel
from common.geometry.observations import NoPose
from common.geometry.oracle import Oracle, random_needle_pose
from common.geometry.pnp import pnp_average, pnp_joint
from common.geometry.transforms import inv_T, pose_error
from common.geometry.triangulation import triangulation_pose

METHODS = {
    "pnp_average (raw EPnP, as published)": lambda uv, sc, rig, P: pnp_average(uv, rig, P, sc, refine=False),
    "pnp_average": lambda uv, sc, rig, P: pnp_average(uv, rig, P, sc),
    "pnp_joint": lambda uv, sc, rig, P: pnp_joint(uv, rig, P, sc),
    "triangulation": lambda uv, sc, rig, P: triangulation_pose(uv, rig, P, sc),
}


@dataclass
class Errors:
    """Per-trial errors of one method (NaN where it gave no pose) and time per call (s)."""

    pos_m: list = field(default_factory=list)
    rot_rad: list = field(default_factory=list)
    seconds: list = field(default_factory=list)

    def add(self, T_est, T_true, dt: float):
        if T_est is None:
            self.pos_m.append(np.nan)
            self.rot_rad.append(np.nan)
        else:
            e = pose_error(T_est, T_true)
            self.pos_m.append(e[0])
            self.rot_rad.append(e[1])
        self.seconds.append(dt)

    def summary(self) -> dict:
        p, r = np.array(self.pos_m) * 1e3, np.rad2deg(np.array(self.rot_rad))
        ok = np.isfinite(p)
        return {"mean_mm": float(np.mean(p[ok])) if ok.any() else np.nan,
                "median_mm": float(np.median(p[ok])) if ok.any() else np.nan,
                "mean_deg": float(np.mean(r[ok])) if ok.any() else np.nan,
                "median_deg": float(np.median(r[ok])) if ok.any() else np.nan,
                "failed": int((~ok).sum()), "n": len(p),
                "ms": float(np.median(self.seconds) * 1e3) if self.seconds else np.nan}


def _timed(f, *a):
    t0 = time.perf_counter()
    try:
        out = f(*a)
    except NoPose:
        out = None
    return out, time.perf_counter() - t0


def single_view(noise_px: float, n_poses: int, seed: int = 0, methods=None, rig=None,
                model=None, bar=None) -> dict[str, Errors]:
    """Errors of each single-frame method over ``n_poses`` random poses at ``noise_px``."""
    rig = rig or StereoRig.default()
    model = model or NeedleModel()
    P = model.keypoints()
    methods = METHODS if methods is None else methods
    rng = np.random.default_rng(seed)
    oracle = Oracle(noise_px=noise_px, seed=seed)
    out = {name: Errors() for name in methods}
    for i in range(n_poses):
        T = random_needle_pose(rng, rig, model)
        uv, sc = oracle.stereo(rig, T, model, seq=i)
        for name, f in methods.items():
            res, dt = _timed(f, uv, sc, rig, P)
            out[name].add(None if res is None else res.T_ecm_needle, T, dt)
        if bar is not None:
            bar.update(1)
    return out


def multiview_scenario(rng: np.random.Generator, rig: StereoRig, model: NeedleModel,
                       arm: EcmArm | None = None, q0=(0.0, 0.0, 0.05, 0.0), n_views: int = 5,
                       joint: int = 0, step_rad: float = MULTIVIEW_STEP_RAD):
    """A static needle seen from ``n_views`` ECM poses, joint ``joint`` stepping ``step_rad``
    (centred on ``q0``). Returns (T_world_needle, [T_world_ecm_k], [T_ecm_needle_k]); the
    needle is placed in view of the middle pose."""
    arm = arm or EcmArm()
    qs = []
    for k in range(n_views):
        q = np.array(q0, dtype=float)
        q[joint] += (k - (n_views - 1) / 2) * step_rad
        qs.append(q)
    T_world_ecm = [arm.T_world_ecm(q) for q in qs]
    T_mid = T_world_ecm[n_views // 2]
    T_world_needle = T_mid @ random_needle_pose(rng, rig, model, max_offaxis=0.2)
    return T_world_needle, T_world_ecm, [inv_T(T) @ T_world_needle for T in T_world_ecm]


def multi_view(noise_px: float, n_scenes: int, seed: int = 0, n_views: int = 5, rig=None,
               model=None, use_covariance: bool = True, bar=None) -> dict[str, Errors]:
    """Fusion of ``pnp_joint`` over ``n_views`` against ``pnp_joint`` on the last view alone."""
    rig = rig or StereoRig.default()
    model = model or NeedleModel()
    P = model.keypoints()
    rng = np.random.default_rng(10_000 + seed)
    oracle = Oracle(noise_px=noise_px, seed=seed + 1)
    out = {"pnp_joint (last view)": Errors(), f"multiview ({n_views} views)": Errors()}
    seq = 0
    for _ in range(n_scenes):
        _, T_wecm, T_true = multiview_scenario(rng, rig, model, n_views=n_views)
        fusion = MultiViewFusion(k=n_views, use_covariance=use_covariance)
        fused, last, t_fuse = None, None, 0.0
        for T_we, T in zip(T_wecm, T_true):
            uv, sc = oracle.stereo(rig, T, model, seq=seq)
            seq += 1
            res, dt = _timed(pnp_joint, uv, rig, P, sc)
            last = (res, dt)
            if res is not None:
                t0 = time.perf_counter()
                fused = fusion.add(res.T_ecm_needle, T_we, res.covariance)
                t_fuse = time.perf_counter() - t0
        out["pnp_joint (last view)"].add(None if last[0] is None else last[0].T_ecm_needle,
                                         T_true[-1], last[1])
        ok = fused is not None and last[0] is not None
        out[f"multiview ({n_views} views)"].add(fused.T_ecm_needle if ok else None, T_true[-1], t_fuse)
        if bar is not None:
            bar.update(1)
    return out


def speed(n_frames: int = 100, noise_px: float = 1.0, repeats: int = 3, seed: int = 0) -> dict:
    """CPU time per stereo frame (ms) of each method: the best of ``repeats`` passes over the
    same ``n_frames`` oracle frames (process time, so other processes' load counts little);
    ``multiview`` is one ``MultiViewFusion.add`` into a full queue of 5 with covariances."""
    rig, model = StereoRig.default(), NeedleModel()
    P = model.keypoints()
    rng = np.random.default_rng(seed)
    oracle = Oracle(noise_px=noise_px, seed=seed)
    frames = []
    for i in range(n_frames):
        T = random_needle_pose(rng, rig, model)
        frames.append(oracle.stereo(rig, T, model, seq=i))
    out = {}
    for name, f in METHODS.items():
        best = np.inf
        for _ in range(repeats):
            t0 = time.process_time()
            for uv, sc in frames:
                _timed(f, uv, sc, rig, P)
            best = min(best, (time.process_time() - t0) / n_frames)
        out[name] = best * 1e3
    joint = [pnp_joint(uv, rig, P, sc) for uv, sc in frames[:10]]
    arm = EcmArm()
    best = np.inf
    for _ in range(repeats):
        fusion = MultiViewFusion(k=5)
        t0 = time.process_time()
        for i in range(n_frames):
            r = joint[i % len(joint)]
            fusion.add(r.T_ecm_needle, arm.T_world_ecm([0.0, 0.0, 0.05, 0.0]), r.covariance)
        best = min(best, (time.process_time() - t0) / n_frames)
    out["multiview (fusion step)"] = best * 1e3
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="needletrack bench geometry", description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=200, help="random poses (and multi-view scenes) per noise level")
    ap.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.25, 0.5, 1.0, 2.0], help="pixel noise sigmas")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--speed-only", action="store_true", help="only the CPU time per frame")
    args = ap.parse_args(argv)
    sp = speed(seed=args.seed)
    print("\nCPU time per stereo frame at 1 px (best of 3 passes over 100 frames):\n")
    print("| method | ms/frame |\n| --- | --- |")
    for name, ms in sp.items():
        print(f"| {name} | {ms:.2f} |")
    if args.speed_only:
        return 0
    from common.progress import progress_bar
    rows = []
    with progress_bar(total=2 * args.poses * len(args.noise), desc="geometry eval", unit="pose") as bar:
        for s in args.noise:
            res = single_view(s, args.poses, args.seed, bar=bar)
            res.update(multi_view(s, args.poses, args.seed, bar=bar))
            rows += [(s, name, e.summary()) for name, e in res.items()]
    print(f"\n{args.poses} random poses per noise level, seed {args.seed}; errors in the ECM frame\n")
    print("| noise (px) | method | mean mm | median mm | mean deg | median deg | no pose | ms/frame |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for s, name, m in rows:
        print(f"| {s:g} | {name} | {m['mean_mm']:.3g} | {m['median_mm']:.3g} | {m['mean_deg']:.3g} | "
              f"{m['median_deg']:.3g} | {m['failed']} | {m['ms']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
