"""``needletrack adapt --data DIR [--data DIR ...] --out OUT``: fit the detector to a user's scene
from recordings without ground truth (docs/adapt.md).

1. the shipped pipeline over each folder (``adapt_run``: OUT/pipeline/);
2. pseudo-labels from the groups that geometry confirms (``pseudo_labels``: OUT/labels/train,
   OUT/labels/fit held out, OUT/labels/labels.json: what was kept and why the rest was dropped);
3. fine-tuning on them (``needletrack train --init MODEL --config CONFIG``: OUT/train/), with
   ``--rehearse N`` beside N frames of the built-in scene with their truth (OUT/rehearsal/);
4. the new weights' familiarity and end identity, fitted on the held-out groups without ground
   truth (``adapt_calibration``), beside OUT/model.pt.

Every step keeps what an earlier run finished: rerun the same command to resume. ``--truth``
scores the pseudo-labels against the same folders with their ground truth (read only for that).
Then: ``needletrack eval --dataset TEST --model OUT/model.pt``.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

from common.cli_options import add_quiet, vector3


REHEARSAL_FRAMES = 0
"""Stereo frames of the built-in scene rehearsed beside the pseudo-labels by default
(``--rehearse``; docs/adapt.md: 200 found more needles on the test split, not on the
development split, and posed fewer)."""
REHEARSAL_SEED = 8901
"""Their scenes' seed: none of the from-scratch training's folders (models/train_from_scratch.sh)."""


def _parser() -> argparse.ArgumentParser:
    from common.detector.weights import DEFAULT_WEIGHTS
    here = Path(__file__).resolve().parents[2]
    p = argparse.ArgumentParser(prog="needletrack adapt", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", action="append", required=True, metavar="DIR",
                   help="a dataset folder without ground truth (images, calibration, endoscope "
                        "joints or pose), e.g. from `needletrack dataset from-bag`; repeatable")
    p.add_argument("--out", required=True, help="output folder (OUT/model.pt and its calibration)")
    p.add_argument("--model", default=str(DEFAULT_WEIGHTS), help="the weights to start from (default: shipped)")
    p.add_argument("--config", default=str(here / "models" / "finetune.yaml"),
                   help="fine-tuning YAML (default models/finetune.yaml)")
    p.add_argument("--support-normal", metavar="X,Y,Z", type=vector3,
                   help="the refinement's resting prior (as `needletrack eval --support-normal`)")
    p.add_argument("--truth", action="append", default=[], metavar="DIR",
                   help="the --data folders with their ground truth, in the same order: only to "
                        "score the pseudo-labels (OUT/labels/score.json)")
    p.add_argument("--rehearse", type=int, default=REHEARSAL_FRAMES, metavar="N",
                   help=f"stereo frames of the built-in scene (train look, instruments holding and "
                        f"covering the needle; with their truth) rendered and trained on beside the "
                        f"labels, so that what the labels do not show is not forgotten, e.g. 200 "
                        f"(default {REHEARSAL_FRAMES}: none; docs/adapt.md)")
    p.add_argument("--labels-only", action="store_true", help="stop after the pseudo-labels")
    add_quiet(p)
    return p


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    from common.data.dataset import Dataset, DatasetError
    from common.adapt.adapt_run import record_pipeline
    from common.evaluation.recording import RecordingError, read_recording
    from common.adapt.pseudo_labels import score_against_truth, summary_lines, write_labels
    out = Path(args.out)
    if args.truth and len(args.truth) != len(args.data):
        print(f"needletrack adapt: --truth: give one per --data ({len(args.data)}), got {len(args.truth)}",
              file=sys.stderr)
        return 2
    try:
        for d in args.data:
            Dataset(d)
        out.mkdir(parents=True, exist_ok=True)
    except (DatasetError, OSError) as exc:
        print(f"needletrack adapt: {exc}", file=sys.stderr)
        return 2
    t0 = time.monotonic()
    stamp = lambda: f"[{time.monotonic() - t0:.0f} s]"
    report: dict = {"data": [str(Path(d).resolve()) for d in args.data], "model": args.model}
    try:
        sources = []
        for i, d in enumerate(args.data):
            rec = record_pipeline(d, out / "pipeline" / f"{i:02d}-{Path(d).resolve().name}.jsonl",
                                  model=args.model, support_normal=args.support_normal,
                                  progress=not args.quiet)
            sources.append((str(Path(d).resolve()), read_recording(rec)))
        print(f"{stamp()} pipeline run over {len(args.data)} folder(s): {out / 'pipeline'}")
    except RecordingError as exc:
        print(f"needletrack adapt: {exc}", file=sys.stderr)
        return 1
    labels = write_labels(sources, out / "labels", progress=not args.quiet)
    report["labels"] = {k: v for k, v in labels.items() if k not in ("verdicts", "labels")}
    print(stamp() + " " + "\n".join(summary_lines(labels)))
    if args.truth:
        score = score_against_truth(out / "labels", {str(Path(d).resolve()): t for d, t in zip(args.data, args.truth)})
        (out / "labels" / "score.json").write_text(json.dumps(score, indent=1) + "\n")
        report["labels_score"] = score
        k = score["keypoint_px"]
        print(f"pseudo-labels against the truth: {score['scored_frames']} frames, keypoints "
              f"{_f(k['mean'])} px mean ({_f(k['median'])} median, {_f(k['p90'])} p90), pose "
              f"{_f(score['pose']['position_mm_mean'])} mm mean, tip right in {_f(score['tip_right'], pct=True)} "
              f"of {score['groups']} groups")
    if args.labels_only:
        _write_report(out, report)
        return 0
    if not labels["train_frames"]:
        print("needletrack adapt: no group was confirmed: nothing to train on (see "
              f"{out / 'labels' / 'labels.json'}; record the needle at rest from several endoscope poses)",
              file=sys.stderr)
        _write_report(out, report)
        return 1
    if args.rehearse < 0:
        print(f"needletrack adapt: --rehearse must be >= 0, got {args.rehearse}", file=sys.stderr)
        return 2
    rehearsal = rehearsal_folder(out, args.rehearse, not args.quiet)
    if rehearsal is not None:
        report["rehearsal"] = {"folder": str(rehearsal), "frames": args.rehearse, "seed": REHEARSAL_SEED,
                               "randomise": "train"}
        print(f"{stamp()} rehearsal frames of the built-in scene: {rehearsal}")
    rc = _train(args, out, report, stamp, rehearsal)
    if rc:
        return rc
    from common.adapt.adapt_calibration import refit
    fit = out / "labels" / "fit"
    earlier = json.loads((out / "adapt.json").read_text()) if (out / "adapt.json").is_file() else {}
    if earlier.get("calibration") and (out / "end_identity.json").is_file():
        report["calibration"] = earlier["calibration"]          # a finished run's: kept
    else:
        report["calibration"] = refit(out / "model.pt", args.model, fit if fit.is_dir() else None,
                                      progress=not args.quiet)
        print(f"{stamp()} familiarity and end identity refitted beside {out / 'model.pt'}")
    _write_report(out, report)
    beside = ", ".join(n for n in ("end_identity.json", "familiarity.json", "adapt.json") if (out / n).is_file())
    print(f"wrote {out / 'model.pt'} (+ {beside}); score it with "
          f"needletrack eval --dataset TEST --model {out / 'model.pt'}")
    return 0


def rehearsal_folder(out: Path, frames: int, progress: bool) -> Path | None:
    """OUT/rehearsal: ``frames`` stereo frames of the built-in scene's train look (pairs of
    endoscope poses), rendered with their truth (resumed by ``generate``); None for 0. The
    labels show only the needles geometry confirmed (at rest, well seen); trained on alone, the
    network forgets the rest (held in the jaws, edge-on, far), which these frames show with
    exact labels (rehearsal, or experience replay)."""
    if frames <= 0:
        return None
    from common.sim.generate import GenerateConfig, generate
    folder = out / "rehearsal"
    generate(str(folder), GenerateConfig(sequences=max(1, frames // 2), steps=2, seed=REHEARSAL_SEED,
                                         randomise="train"), progress=progress)
    return folder


def _train(args, out: Path, report: dict, stamp, rehearsal: Path | None = None) -> int:
    """Fine-tune on OUT/labels/train (and the ``rehearsal`` folder) into OUT/train (resumable) and
    put the weights at OUT/model.pt."""
    from common.data.dataset import DatasetError
    teacher = out / "labels" / "teacher"
    data = [str(out / "labels" / "train")] + ([str(rehearsal)] if rehearsal is not None else [])
    try:
        report["train"] = fine_tune(out, data, args.config, args.model, not args.quiet,
                                    [str(teacher)] if teacher.is_dir() else None)
    except (DatasetError, ValueError, OSError) as exc:
        print(f"needletrack adapt: training: {exc}", file=sys.stderr)
        return 2
    print(f"{stamp()} fine-tuned: {out / 'model.pt'}")
    return 0


def fine_tune(out: Path, data: list, config, init, progress: bool = True, teacher_dirs=None) -> dict:
    """``common.detector.train.train`` from ``init`` on the ``data`` folders into OUT/train
    (resumed from its checkpoint; OUT/train/done.json once finished: then kept), the weights
    copied to OUT/model.pt; returns the last epoch's metrics. Raises what ``train`` raises."""
    from common.detector.train import train
    out = Path(out)
    done = out / "train" / "done.json"
    if not done.is_file():
        (out / "model.pt").unlink(missing_ok=True)
        last = train(data, out / "train", config, progress=progress, init=init, teacher_dirs=teacher_dirs)
        done.write_text(json.dumps(last or {}, indent=1) + "\n")
    if not (out / "model.pt").is_file():
        shutil.copy2(out / "train" / "model.pt", out / "model.pt")
    return json.loads(done.read_text())


def _write_report(out: Path, report: dict) -> None:
    (out / "adapt.json").write_text(json.dumps(report, indent=1, default=str) + "\n")


def _f(x, pct: bool = False) -> str:
    if x is None:
        return "n/a"
    return f"{100 * x:.1f}%" if pct else f"{x:.2f}"
