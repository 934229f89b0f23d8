"""``needletrack eval --dataset DIR [--detector learned|classical|oracle] [--out OUTDIR]``

Checks the folder against the dataset spec (exit 2 with file, line and field when it breaks
it, or when it has no ground truth to compare with), then runs the real graph on it: replay ->
detector -> epnp (average, joint) -> triangulate -> ecm -> fusion (-> refine -> fusion) ->
evaluator, on a free loopback port; on a folder of moving takes (``needle_at_rest: false``) also
the tracker (method ``tracked``, its in-hand poses scored: docs/tracking.md#evaluation). Every node queues all its inputs (none keeps only the
newest, as in a live graph), so every frame is scored whatever the load. The evaluator writes
OUTDIR (results.json, report.md, error_vs_distance.png, per_frame.csv, overlays/; for moving takes
tracking.png and tracking.mp4, the longest take's errors and its video); this command
prints the summary. The graph's log is OUTDIR/graph.log and the graph itself OUTDIR/graph.yaml.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import yaml

from common.cli_options import add_dataset, add_quiet, add_weights, vector3
from common.data.withhold import withhold_params
from common.frames import CAMERAS
from common.evaluation.replay_progress import wait_with_progress

DETECTORS = ("learned", "classical", "oracle")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="needletrack eval", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_dataset(p)
    p.add_argument("--detector", default="learned", choices=DETECTORS, help="keypoint backend (default learned)")
    p.add_argument("--out", default="results", help="output folder (default results/)")
    p.add_argument("--noise-px", type=float, default=0.0,
                   help="oracle only: Gaussian keypoint noise per coordinate (px)")
    p.add_argument("--seed", type=int, default=0, help="oracle only: noise seed")
    add_weights(p, "--model", learned_only=True)
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="a detector parameter (repeatable), e.g. --param tracking=false")
    p.add_argument("--refine-param", action="append", default=[], metavar="KEY=VALUE",
                   help="a refinement parameter (repeatable), e.g. --refine-param one_camera=false")
    p.add_argument("--tracker-param", action="append", default=[], metavar="KEY=VALUE",
                   help="a tracker parameter on moving takes (repeatable), e.g. --tracker-param arm_correction=true")
    p.add_argument("--rate", default=None,
                   help="replay rate in Hz, or 'max' (default: 30 for the oracle, 10 otherwise). Every "
                        "frame is scored whatever the rate (the nodes queue their inputs here); "
                        "`needletrack bench` measures speed")
    p.add_argument("--no-refine", action="store_true", help="leave out the refinement node")
    p.add_argument("--withhold", metavar="CAMERA[:SHARE]",
                   help="send CAMERA's (left or right) images black for SHARE (default 0.3) of each take, "
                        "one window per take: a lens an instrument covers (common/data/withhold.py)")
    p.add_argument("--cameras", choices=["left", "right"], default=None,
                   help="a monocular endoscope: only this camera's images, the refinement on them alone "
                        "and the tracker (tracked only; docs/tracking.md#one-camera)")
    p.add_argument("--support-normal", metavar="X,Y,Z", type=vector3,
                   help="the refinement's prior that the needle may rest on a surface with this "
                        "normal (world frame), e.g. 0,0,1 for the simulator's phantom (common/geometry/rest_prior.py; "
                        "default: no prior)")
    p.add_argument("--timeout", type=float, default=None, help="give up after this many seconds")
    p.add_argument("--bench", type=float, default=0.0, metavar="SECONDS",
                   help="then also measure the live graph's speed for this long (`needletrack bench`) "
                        "and add it to results.json (key `bench`) and report.md")
    p.add_argument("--rrd", metavar="FILE",
                   help="also write the frames (Fig. 1 pictures), every method's pose and the errors "
                        "as a Rerun recording, to scrub frame by frame: `needletrack view FILE` "
                        "(needs the viewer extra)")
    p.add_argument("--record", metavar="FILE",
                   help="also write each refined pose and each camera's keypoints as JSON lines (the "
                        "`recorder` node's file, as `needletrack adapt` reads it): the tracker replayed "
                        "on them offline (`needletrack bench tracker --replay`) needs no detector run")
    add_quiet(p)
    return p


def check_folder(path: str, progress: bool = True):
    """The loaded Dataset, or raise DatasetError naming the file, line and field at fault.

    Beyond the spec, evaluation needs ground truth: ``T_world_needle`` and the endoscope pose
    (``T_world_ecm``, or ``ecm_joints`` with the ``ecm`` arm) on every frame.
    """
    from common.data.check import check_dataset
    from common.data.dataset import Dataset, DatasetError
    ds = Dataset(path)
    if len(ds) == 0:
        raise DatasetError(f"{path}/frames.jsonl: no frames")
    rep = check_dataset(ds, images=True, progress=progress)
    if rep.errors:
        more = f" (and {len(rep.errors) - 1} more)" if len(rep.errors) > 1 else ""
        raise DatasetError(rep.errors[0] + more)
    for fr in ds.frames:
        where = f"frames.jsonl:{fr.line}"
        if fr.T_world_needle is None:
            raise DatasetError(f"{where}: T_world_needle: missing; evaluation needs the ground-truth "
                               f"needle pose on every frame")
        if fr.T_world_ecm is None and (fr.ecm_joints is None or ds.arm is None):
            raise DatasetError(f"{where}: T_world_ecm: missing (and no ecm_joints with an ecm arm in "
                               f"dataset.yaml); evaluation needs the endoscope pose")
    return ds


def print_summary(res: dict, out=sys.stdout) -> None:
    k2 = res["keypoints_2d_px"]["all"]
    k3 = res["keypoints_3d_mm"]["all"]
    f = lambda x, nd=2: "n/a" if x is None else f"{x:.{nd}f}"
    print(f"dataset {res['dataset']}: {res['frames']} frames, detector {res['detector']}", file=out)
    dr = res["detection_rate"]
    print(f"needle found in {f(None if dr is None else 100 * dr, 1)}% of the images; keypoints "
          f"2D {f(k2['mean'])} +- {f(k2['std'])} px (paper 5.58), 3D {f(k3['mean'])} +- {f(k3['std'])} mm",
          file=out)
    print(f"{'method':<18} {'n':>9} {'pos mean':>9} {'median':>7} {'rot mean':>9} {'median':>7} "
          f"{'turned':>7} {'sure':>5}   paper", file=out)
    paper = res.get("paper", {}).get("pose", {})
    for m, d in res["pose"].items():
        p, o = d["position_mm"], d["orientation_deg"]
        pp = paper.get(m)
        ps = f"{pp['position_mm']:.2f} mm / {pp['orientation_deg']:.2f} deg" if pp else "-"
        sw = d.get("end_for_end") or {}
        turned = " ".join(f"{100 * sw[k]:>4.0f}%" if k in sw else "    -" for k in ("share", "confident_share"))
        print(f"{m:<18} {d['n']:>4}/{d.get('expected', d['n']):<4} {f(p['mean']):>6} mm {f(p['median']):>7} "
              f"{f(o['mean']):>5} deg {f(o['median']):>7}  {turned}   {ps}", file=out)
    for m, d in res["pose"].items():
        s = d.get("sure")
        if s and 0 < s["n"] < d["n"]:
            print(f"{m}: the {s['n']} poses not flagged ambiguous: {f(s['position_mm']['mean'])} mm / "
                  f"{f(s['orientation_deg']['mean'])} deg mean", file=out)
    t = res["timing"]
    for node, c in res.get("node_counters", {}).items():
        errs = {k: v for k, v in c.items() if v and k in ("handler_errors", "decode_errors")}
        if errs:
            print(f"warning: node {node}: {errs} (see graph.log)", file=out)
    print(f"throughput {f(t['throughput_hz'], 1)} frames/s at the replay's pace; latency p50 "
          f"{f(t['latency_ms']['p50'], 1)} ms, p99 {f(t['latency_ms']['p99'], 1)} ms", file=out)


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    from common.data.dataset import DatasetError
    from common.evaluation.pipeline_graph import (
        LOSSLESS_TRACKER_WAIT,
        GraphRun,
        GraphRunError,
        keypoint_sources,
        pipeline_graph,
        pose_inputs,
        recorder_node,
    )

    if args.rrd:
        try:
            import rerun  # noqa: F401
        except ImportError:
            print("needletrack eval: --rrd needs rerun-sdk: pip install -e '.[viewer]'", file=sys.stderr)
            return 2
        from common.viewer.recording import rrd_target_problem
        problem = rrd_target_problem(args.rrd)
        if problem:
            print(f"needletrack eval: --rrd {problem}", file=sys.stderr)
            return 2
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        print(f"needletrack eval: --out {out} exists and is not a folder", file=sys.stderr)
        return 2
    dataset = str(Path(args.dataset))
    try:
        ds = check_folder(dataset, progress=not args.quiet)
    except DatasetError as exc:
        print(f"needletrack eval: {dataset} is not a usable dataset folder: {exc}", file=sys.stderr)
        return 2
    if args.noise_px and args.detector != "oracle":
        print("needletrack eval: --noise-px applies to the oracle detector only", file=sys.stderr)
        return 2

    try:
        _clear_outputs(out)
    except OSError as exc:
        print(f"needletrack eval: --out {out}: cannot write {exc.filename or out}: {exc.strerror}", file=sys.stderr)
        return 2

    det_params = {}
    if args.detector == "oracle":
        det_params = {"noise_px": args.noise_px, "seed": args.seed}
    elif args.model:
        det_params = {"weights": str(Path(args.model).resolve())}
    split = args.detector != "oracle"   # one process per camera: images detected in parallel
    from common.runtime.graph import parse_param
    try:
        det_params.update(dict(parse_param(p) for p in args.param))
        tracker_params = dict(parse_param(p) for p in args.tracker_param) or None
        refine_params = dict(parse_param(p) for p in args.refine_param)
    except ValueError as exc:
        print(f"needletrack eval: {exc}", file=sys.stderr)
        return 2
    try:
        replay_params = withhold_params(args.withhold)
    except ValueError as exc:
        print(f"needletrack eval: --withhold: {exc}", file=sys.stderr)
        return 2
    cameras = (args.cameras,) if args.cameras else CAMERAS
    rate = args.rate or (30 if args.detector == "oracle" else 10)
    rate = rate if str(rate) == "max" else float(rate)
    # moving takes: the graph as deployed, the refinement warm from frame to frame (what the tracker
    # gets live); views of a needle at rest: the refinement a single-frame method, each view on its own
    moving_takes = any(fr.needle_at_rest is False for fr in ds.frames)
    doc = pipeline_graph(dataset, detector=args.detector, detector_params=det_params, rate=rate,
                         refine=False if args.no_refine else None, lossless=True,
                         split_detector=split, refine_tracking=moving_takes,
                         refine_params={**refine_params, **({"support_normal_world": args.support_normal}
                                                            if args.support_normal else {})} or None,
                         tracker=moving_takes,
                         tracker_params=tracker_params, replay_params=replay_params, cameras=cameras)
    evaluator = {"id": "evaluator", "module": "evaluator",
                 "params": {"out": str(out.resolve()), "dataset": str(Path(dataset).resolve()),
                            "drain_s": EVAL_DRAIN_S,
                            "detector": args.detector, "noise_px": args.noise_px,
                            "support_normal_world": args.support_normal,
                            "rrd": str(Path(args.rrd).resolve()) if args.rrd else None},
                 "inputs": {"truth": "replay/truth", "calib": "replay/calib", "eos": "replay/eos",
                            **{c: src for c, src in keypoint_sources(split or len(cameras) == 1).items()
                               if c in cameras},
                            **({"points3d": "triangulate/points"}
                               if any(n["id"] == "triangulate" for n in doc["nodes"]) else {}),
                            **{m: src for m, src in pose_inputs(doc).items()
                               if len(cameras) == 2 or m == "tracked"},   # monocular: refine/pose is empty
                            **({"instruments": "replay/instruments", "in_hand": "tracker/in_hand",
                                "arm_correction": "tracker/arm_correction"}
                               if any(n["id"] == "tracker" for n in doc["nodes"]) else {})},
                 "restart": "never"}
    doc["nodes"].append(evaluator)
    if args.record:
        doc["nodes"].append(recorder_node(doc, args.record, split or len(cameras) == 1, cameras))
    log_path = out / "graph.log"
    try:
        (out / "graph.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
        log = open(log_path, "w")
        if args.rrd:
            Path(args.rrd).unlink(missing_ok=True)     # a recording (rrd_target_problem): replaced
    except OSError as exc:
        print(f"needletrack eval: cannot write {exc.filename}: {exc.strerror}", file=sys.stderr)
        return 2

    n = len(ds)
    timeout = args.timeout or (180 + n / (rate if rate != "max" else 5) * 3)
    t0 = time.monotonic()
    with log:
        try:
            with GraphRun(doc, log) as run:
                run.start()
                wait_with_progress(run, n, timeout, show=not args.quiet,
                                   until=("evaluator", "recorder") if args.record else ("evaluator",))
        except GraphRunError as exc:
            log.flush()
            print(f"needletrack eval: the graph failed: {exc}", file=sys.stderr)
            text = log_path.read_text().splitlines()
            errors = [l for l in text if " ERROR " in l]
            if errors:
                print("first errors:\n" + "\n".join(errors[:5]), file=sys.stderr)
            print(f"last lines of {log_path}:\n" + "\n".join(text[-15:]), file=sys.stderr)
            return 1
    res_path = out / "results.json"
    if not res_path.is_file():
        print(f"needletrack eval: the evaluator wrote no {res_path}; see {log_path}", file=sys.stderr)
        return 1
    res = json.loads(res_path.read_text())
    if args.bench > 0:
        rc = _bench(args, dataset, out, res)
        if rc:
            return rc
    print_summary(res)
    short = unanswered(res)
    if short:
        warning = ("needletrack eval: warning: the run ended before the graph answered every frame ("
                   + ", ".join(f"{n} {k} of {res['frames']}" for n, k in short.items())
                   + f"; a node fell further behind than the lossless graph waits, {LOSSLESS_TRACKER_WAIT} frames, "
                   f"or the evaluator's {EVAL_DRAIN_S:.0f} s of silence after the source's end): "
                   "the figures are of the frames answered; rerun on a less loaded machine")
        print(warning, file=sys.stderr)
        with open(out / "report.md", "a") as f:
            f.write(f"\n**Incomplete run.** {warning.split('warning: ', 1)[1]}.\n")
    if replay_params:
        _withheld(ds, out, res, replay_params)
    moving = ", tracking.png, tracking.mp4" if (out / "tracking.mp4").is_file() else ""
    print(f"wrote {out}/results.json, report.md, error_vs_distance.png, per_frame.csv, overlays/{moving} "
          f"({time.monotonic() - t0:.0f} s)")
    if args.rrd:
        if not Path(args.rrd).is_file():
            print(f"needletrack eval: the evaluator wrote no {args.rrd}; see {log_path}", file=sys.stderr)
            return 1
        print(f"wrote {args.rrd}: needletrack view {args.rrd}")
    return 0


def unanswered(res: dict) -> dict:
    """{node: frames answered} of the frame-by-frame pose nodes (a pose or a notice that there is
    none, per frame) that answered fewer than the run's frames: a run cut short."""
    out = {}
    for node, c in (res.get("node_counters") or {}).items():
        if node in ("refine", "tracker", "triangulate") or node.startswith("epnp"):
            answered = int(c.get("out.pose", 0)) + int(c.get("out.no_pose", 0))
            if 0 < answered < int(res.get("frames") or 0):
                out[node] = answered
    return out


EVAL_DRAIN_S = 20.0
"""How long the evaluator waits for the outputs still in flight after the source's end, without a
message (it ends at once when every method has answered every frame). The lossless graph's
refinement can lag the source by tens of seconds on a loaded machine and go quiet for seconds on
one slow frame: with 3 s a run on a machine shared with the tests stopped two takes early."""


def _withheld(ds, out: Path, res: dict, replay_params: dict) -> None:
    """The tracked pose on the frames one camera was withheld from, against the others: printed,
    in results.json (``withheld``) and report.md (``common.evaluation.withheld``)."""
    from common.evaluation.withheld import withheld_markdown, withheld_summary
    methods = [m for m in ("refined", "tracked") if m in res.get("pose", {})]
    table = withheld_summary(ds, out / "per_frame.csv", replay_params["withhold_share"], methods=methods or ("tracked",))
    res["withheld"] = {"camera": replay_params["withhold"], "share": replay_params["withhold_share"], **table}
    (out / "results.json").write_text(json.dumps(res, indent=2, allow_nan=False) + "\n")
    lines = withheld_markdown(table)
    with open(out / "report.md", "a") as f:
        f.write(f"\n## The {replay_params['withhold']} camera withheld for {replay_params['withhold_share']:.0%} "
                f"of each take (`--withhold`)\n\n" + "\n".join(lines) + "\n")
    print(f"{replay_params['withhold']} camera withheld:\n" + "\n".join(lines))


def _clear_outputs(out: Path) -> None:
    """Make the folder ``out`` and remove the outputs an earlier run of this command left there."""
    out.mkdir(parents=True, exist_ok=True)
    for stale in ("results.json", "report.md", "error_vs_distance.png"):
        (out / stale).unlink(missing_ok=True)
    for png in (out / "overlays").glob("*.png") if (out / "overlays").is_dir() else []:
        png.unlink()


def _bench(args, dataset: str, out: Path, res: dict) -> int:
    """Measure the live graph (``common.evaluation.graph_speed``) and add it to results.json/report.md."""
    from common.evaluation.graph_speed import measure, report
    from common.evaluation.pipeline_graph import GraphRunError
    from common.evaluation.results import to_jsonable
    bargs = argparse.Namespace(detector=args.detector, model=args.model, rate="30",
                               duration=args.bench, warmup=4.0, one_detector=False,
                               no_refine=args.no_refine)
    log_path = out / "bench.log"
    try:
        with open(log_path, "w") as log:
            r = measure(bargs, dataset, log)
    except (GraphRunError, RuntimeError) as exc:
        print(f"needletrack eval --bench: {exc}; see {log_path}", file=sys.stderr)
        return 1
    text = report(r)
    res["bench"] = to_jsonable(r)
    (out / "results.json").write_text(json.dumps(res, indent=2, allow_nan=False) + "\n")
    with open(out / "report.md", "a") as f:
        f.write("\n## Live graph speed (`needletrack bench`)\n\n```\n" + text + "\n```\n")
    print(text)
    return 0
