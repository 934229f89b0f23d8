"""``needletrack finetune --labels DIR [--labels DIR ...] --out OUT``: fit the detector to a
user's footage from frames labelled by hand (``needletrack label``; docs/adapt.md).

1. the labels (``common.label.targets``): only frames a person labelled count; "no needle"
   frames are negatives, keypoints marked hidden hidden targets; whole takes held out
   (``--hold-out``, OUT/labels/heldout-NN), the rest to train on (OUT/labels/train-NN);
2. rehearsal: ``--rehearse N`` stereo frames of the built-in scene with their truth
   (OUT/rehearsal, ``adapt.rehearsal_folder``), trained on beside the labels, and on which the
   init weights' outputs are kept (``train``'s teacher folders, ``distill_keypoints``: learning
   without forgetting), so that the standard set is not forgotten;
3. fine-tuning (``common.detector.train.train`` with ``--init``: OUT/train, OUT/model.pt) under
   ``--config`` (models/finetune.yaml) whose ``model`` section is the init weights' own, so any
   network the trainer builds (``ModelConfig``, a pretrained backbone's too) is fine-tuned as it is;
4. the calibrations beside OUT/model.pt (familiarity, end identity: ``adapt_calibration.refit``)
   fitted on the held-out labels;
5. the report (``finetune_report``): before and after on the held-out labels, the worst
   frames drawn, the frames to label next (OUT/report/report.md).

Every step keeps what an earlier run finished: rerun the same command after a kill to resume.
"""
from __future__ import annotations

import argparse
import hashlib
import os
import json
import sys
import time
from pathlib import Path

import yaml

from common.cli_options import add_quiet
HOLD_OUT = 0.25
"""Share of the labelled frames held out (whole takes) for the calibrations and the report."""
REHEARSAL_FRAMES = 40
"""Stereo frames of the built-in scene rehearsed beside the labels by default (``--rehearse``)."""
MINUTES = 8.0
"""Training time (minutes) by default: with the rendering, the fits and the report, a fine-tune
of 30 labelled stereo frames within 15 minutes on a 2-core CPU (docs/adapt.md)."""

CHECKPOINT_STEPS = 25
"""At most this many steps between checkpoints (an epoch): a kill loses at most these (about two
minutes on a loaded 2-core CPU)."""


def _parser() -> argparse.ArgumentParser:
    from common.detector.weights import DEFAULT_WEIGHTS
    here = Path(__file__).resolve().parents[2]
    p = argparse.ArgumentParser(prog="needletrack finetune", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--labels", action="append", required=True, metavar="DIR",
                   help="a dataset folder labelled with `needletrack label` (repeatable)")
    p.add_argument("--out", required=True, help="output folder (OUT/model.pt, its calibrations, OUT/report/)")
    p.add_argument("--init", default=str(DEFAULT_WEIGHTS), help="the weights to start from (default: shipped)")
    p.add_argument("--config", default=str(here / "models" / "finetune.yaml"),
                   help="fine-tuning YAML (default models/finetune.yaml); its model section is replaced "
                        "by the --init weights' own")
    p.add_argument("--minutes", type=float, default=MINUTES,
                   help=f"training time: the schedule ends there if its steps take longer (default {MINUTES:g})")
    p.add_argument("--hold-out", type=float, default=HOLD_OUT, metavar="SHARE",
                   help=f"share of the labelled frames (whole takes) held out for the calibrations and "
                        f"the report (default {HOLD_OUT:g})")
    p.add_argument("--rehearse", type=int, default=REHEARSAL_FRAMES, metavar="N",
                   help=f"stereo frames of the built-in scene rendered and trained on beside the labels "
                        f"(default {REHEARSAL_FRAMES}; 0: none)")
    p.add_argument("--seed", type=int, default=0, help="the held-out split's seed")
    p.add_argument("--threads", type=int, default=None,
                   help="CPU threads for training (default: the config's; 1 for two fine-tunes side by side)")
    add_quiet(p)
    return p


def _fingerprint(frames) -> str:
    """The labels a fine-tune started from: which frames, what each is, when each was saved."""
    return hashlib.sha1(json.dumps([[f.folder, f.index, f.kind, f.stamp] for f in frames]).encode()).hexdigest()[:16]


def prepare_labels(label_dirs: list[str], out: Path, hold_out: float, seed: int) -> dict:
    """OUT/labels/train-NN and heldout-NN (one per label folder that has frames on that side) and
    OUT/labels/split.json; kept when the labels are those of the earlier run (ValueError when
    they changed: use another --out)."""
    from common.label.targets import counts, read_labels, split_held_out, trainable, write_subset
    frames = trainable(label_dirs)
    lab = out / "labels"
    split_file = lab / "split.json"
    fp = _fingerprint(frames)
    if split_file.is_file():
        split = json.loads(split_file.read_text())
        if split.get("fingerprint") != fp:
            raise ValueError(f"{split_file}: the labels changed since this fine-tune started; use another --out "
                             f"(or delete {out})")
        return split
    train, held = split_held_out(frames, hold_out, seed)
    split = {"fingerprint": fp, "hold_out": hold_out, "seed": seed,
             "folders": {d: counts(read_labels(d)) for d in label_dirs}, "train": [], "heldout": []}
    for side, chosen in (("train", train), ("heldout", held)):
        for i, d in enumerate(label_dirs):
            mine = [f for f in chosen if f.folder == os.path.realpath(d)]
            if not mine:
                continue
            sub = lab / f"{side}-{i:02d}"
            if not sub.is_dir():
                write_subset(mine, str(sub))
            split[side].append({"folder": str(sub), "source": mine[0].folder,
                                "frames": [f.index for f in mine],
                                "kinds": {k: sum(f.kind == k for f in mine) for k in ("target", "no_needle")}})
    split_file.write_text(json.dumps(split, indent=1) + "\n")
    return split


def write_config(config: str, init: str, minutes: float, out: Path, keep_keypoints: bool = False,
                 threads: int | None = None) -> Path:
    """OUT/finetune.yaml: ``config`` with the ``init`` weights' model section, ``time_budget_min``
    ``minutes``, ``threads`` CPU threads (None: the config's), no validation split (the held-out labels are scored instead) and epochs of at
    most ``CHECKPOINT_STEPS`` steps (the same number of steps in all); ``keep_keypoints``: the
    init weights' keypoint heatmaps kept on the rehearsal frames too (``distill_keypoints``)."""
    import torch

    from common.detector.model import ModelConfig
    from common.detector.train import load_config
    from common.detector.weights import load_model
    load_model(init)                  # a clear ModelFileError for weights that are no detector's
    blob = torch.load(init, map_location="cpu", weights_only=True)
    cfg = load_config(config)
    cfg["model"] = ModelConfig.from_dict(dict(blob["config"])).to_dict()
    cfg["train"]["time_budget_min"] = float(minutes)
    cfg["train"]["val_fraction"] = 0.0
    if threads is not None:
        cfg["train"]["threads"] = int(threads)
    t = cfg["train"]
    if keep_keypoints:
        t["distill_keypoints"] = True
    if int(t["steps_per_epoch"]) > CHECKPOINT_STEPS:     # the same schedule, a checkpoint more often
        total = int(t["steps_per_epoch"]) * int(t["epochs"])
        t["steps_per_epoch"], t["epochs"] = CHECKPOINT_STEPS, -(-total // CHECKPOINT_STEPS)
    path = out / "finetune.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    from common.data.dataset import Dataset, DatasetError
    from common.detector.weights import ModelFileError
    from common.adapt.adapt import fine_tune, rehearsal_folder
    from common.adapt.adapt_calibration import refit
    from common.adapt.finetune_report import write_report
    from common.label.targets import LabelsError
    out = Path(args.out)
    err = lambda msg: print(f"needletrack finetune: {msg}", file=sys.stderr)
    t0 = time.monotonic()
    stamp = lambda: f"[{time.monotonic() - t0:.0f} s]"
    progress = not args.quiet
    if args.minutes <= 0 or args.rehearse < 0 or (args.threads is not None and args.threads < 1):
        err(f"--minutes must be > 0, --rehearse >= 0 and --threads >= 1, got {args.minutes:g}, {args.rehearse} "
            f"and {args.threads}")
        return 2
    try:
        for d in args.labels:
            Dataset(d)
        out.mkdir(parents=True, exist_ok=True)
        split = prepare_labels(args.labels, out, args.hold_out, args.seed)
        config = write_config(args.config, args.init, args.minutes, out, keep_keypoints=args.rehearse > 0,
                              threads=args.threads)
    except (LabelsError, DatasetError, ModelFileError, ValueError, OSError) as exc:
        err(str(exc))
        return 2
    n_train = sum(len(s["frames"]) for s in split["train"])
    n_held = sum(len(s["frames"]) for s in split["heldout"])
    print(f"{stamp()} labels: {n_train} frames to train on, {n_held} held out ({out / 'labels' / 'split.json'})")
    if not split["train"]:
        err("every labelled frame is held out: label more takes or lower --hold-out")
        return 2
    rehearsal = rehearsal_folder(out, args.rehearse, progress)
    if rehearsal is not None:
        print(f"{stamp()} rehearsal: {args.rehearse} stereo frames of the built-in scene in {rehearsal}")
    data = [s["folder"] for s in split["train"]] + ([str(rehearsal)] if rehearsal is not None else [])
    try:
        last = fine_tune(out, data, str(config), args.init, progress,
                         teacher_dirs=[str(rehearsal)] if rehearsal is not None else None)
    except (DatasetError, ValueError, OSError) as exc:
        err(f"training: {exc}")
        return 2
    except KeyboardInterrupt:
        err("interrupted; run the same command again to resume")
        return 130
    print(f"{stamp()} fine-tuned: {out / 'model.pt'} ({last.get('elapsed_s', 0) / 60:.1f} min of training)")
    held = [s["folder"] for s in split["heldout"]]
    summary = {"labels": [str(Path(d).resolve()) for d in args.labels], "init": str(args.init),
               "split": {k: split[k] for k in ("train", "heldout", "folders")}, "train": last}
    done = out / "calibration.json"
    if done.is_file() and (out / "end_identity.json").is_file():
        summary["calibration"] = json.loads(done.read_text())
    else:
        summary["calibration"] = refit(out / "model.pt", args.init, held, progress=progress,
                                       labels="hand labels: the labelled tip")
        done.write_text(json.dumps(summary["calibration"], indent=1) + "\n")
        print(f"{stamp()} familiarity and end identity refitted on the held-out labels beside {out / 'model.pt'}")
    if held:
        rep = write_report(out / "report", held, args.init, str(out / "model.pt"), args.labels, progress,
                           cache=out / "report" / "before-scores.json")
        summary["report"] = {k: rep[k] for k in ("before", "after", "held_out_frames", "held_out_images")}
        for name in ("before", "after"):
            s = rep[name]
            print(f"  {name:6s}: found {s['found']}/{s['images_with_needle']}, keypoints "
                  f"{_f(s['keypoint_px']['mean'])} px mean ({_f(s['keypoint_px']['median'])} median), tip right "
                  f"{_f(s['tip_right'], True)}, sure and right {_f(s['sure_right'], True)}, confident swaps "
                  f"{s['confident_swaps']}, false detections {s['false_detections']}/{s['images_without']}")
        print(f"{stamp()} report on {rep['held_out_frames']} held-out frames: {out / 'report' / 'report.md'}")
    else:
        print("warning: no frame held out (--hold-out 0): no report, calibrations kept from the start",
              file=sys.stderr)
    summary["seconds"] = round(time.monotonic() - t0, 1)
    (out / "finetune.json").write_text(json.dumps(summary, indent=1, default=str) + "\n")
    print(f"wrote {out / 'model.pt'}; use it as the detector's weights (docs/adapt.md): "
          f"needletrack detect --weights {out / 'model.pt'} ... or a graph's detector params weights: {out / 'model.pt'}")
    return 0


def _f(x, pct: bool = False) -> str:
    if x is None:
        return "n/a"
    return f"{100 * x:.1f}%" if pct else f"{x:.2f}"
