"""``needletrack train``: train the learned keypoint detector on a needle dataset, on the CPU.

    needletrack train --data DIR [--data DIR2 ...] [--config models/train.yaml] --out models/NAME

Writes into ``--out`` (a folder): ``model.pt`` (the best weights by validation keypoint error,
what the detector loads), ``checkpoint.pt`` (everything needed to resume: the same command
continues where it stopped), ``train.yaml`` (the configuration used), ``metrics.jsonl`` (one line
per epoch) and ``curves.png``. Seeded: the same data, config and seed give the same model.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import yaml

from common.detector.batches import crop_batch, global_batch, mine_hard_negatives
from common.detector.data import (
    OCCLUDED_WEIGHT,
    AugConfig,
    DatasetError,
    crop_from,
    global_input,
    load_cached,
    load_records,
    save_records,
)
from common.detector.model import (
    KeypointModel,
    ModelConfig,
    apply_affine,
    crop_affine,
    crop_side,
    decode_global,
    decode_heatmaps,
    focal_heatmap_loss,
    gaussian_targets,
    global_size,
    invert_affine,
    keypoint_loss,
    visibility_logits,
)
from common.detector.weights import MODEL_FORMAT, MODEL_VERSION

DEFAULT_TRAIN = {
    "epochs": 20,
    "batch": 32,              # stage-2 crops per step
    "global_batch": 16,       # stage-1 images per step
    "optimizer": "adamw",     # adamw | sgd (the paper's: lr 0.01, momentum 0.9, wd 0.0005)
    "lr": 0.002,
    "momentum": 0.9,
    "weight_decay": 0.0005,
    "warmup_steps": 100,
    "steps_per_epoch": 0,     # 0: one crop per training image per epoch
    "val_fraction": 0.1,
    "val_every": 1,           # validate (and keep the best weights) every this many epochs, and at the end
    "threads": 2,
    "time_budget_min": 0,     # the cosine schedule ends at this training time if it comes first; 0 = none
    "loss_weights": {"kp": 1.0, "line": 4.0, "presence": 0.3, "global": 1.0, "box": 1.0,
                     "global_presence": 1.0, "visibility": 0.5},
    "backbone_lr": 1.0,       # the pretrained trunks' learning rate, as a fraction of lr (model.backbone)
    "stages": ["global", "crop"],   # which networks to train (the other keeps its weights)
    "hard_negatives": 0,      # >0: mine up to this many stage-1 false proposals per image
                              # (instrument jaws, thread...) with the weights of that moment
    "hard_mining_at": 0.0,    # when to mine: fraction(s) of the schedule (0 = before the first step)
    "hard_mining_images": 0,  # mine on at most this many images (a seeded random subset); 0 = all
    "hard_prob": 0.2,         # fraction of stage-2 samples drawn from the mined hard negatives
    "jaw_negatives": 0.0,     # share of the images' needle-free regions centred on an instrument's jaws
    "occluded_weight": OCCLUDED_WEIGHT,   # a hidden keypoint's weight in the keypoint loss, in [0, 1)
    "hidden_sigma": 0.0,      # >0: a hidden keypoint's target is a Gaussian this wide (cells), so that
                              # its heatmap is diffuse and its score (peak mass) stays under the gate;
                              # 0: as wide as a seen one's (model.kp_sigma)
    "distill_weight": 1.0,    # with teacher folders (train(teacher_dirs=...)): the weight of keeping the
                              # --init weights' presence and proposals there (learning without forgetting)
    "distill_batch": 8,       # teacher crops and images per step
    "distill_keypoints": False,   # also keep the --init weights' keypoint and centreline heatmaps on
                              # the teacher folders: only where those weights are right (folders of
                              # the looks they were trained on), so that new data does not wear
                              # their precision away
}


def load_config(path: str | None) -> dict:
    """Training configuration: defaults overridden by the YAML file (sections seed, model,
    augment, train); raises ValueError naming the file and field."""
    cfg = {"seed": 0, "model": {}, "augment": {}, "train": dict(DEFAULT_TRAIN)}
    if path:
        try:
            user = yaml.safe_load(Path(path).read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise ValueError(f"{path}: cannot read config: {exc}") from None
        if not isinstance(user, dict):
            raise ValueError(f"{path}: expected a mapping at the top level")
        unknown = set(user) - set(cfg)
        if unknown:
            raise ValueError(f"{path}: unknown section(s) {sorted(unknown)} (known: {sorted(cfg)})")
        cfg["seed"] = int(user.get("seed", 0))
        cfg["model"] = dict(user.get("model") or {})
        cfg["augment"] = dict(user.get("augment") or {})
        t = dict(user.get("train") or {})
        bad = set(t) - set(DEFAULT_TRAIN)
        if bad:
            raise ValueError(f"{path}: train: unknown field(s) {sorted(bad)}")
        lw = dict(DEFAULT_TRAIN["loss_weights"])
        lw.update(t.pop("loss_weights", {}) or {})
        cfg["train"].update(t)
        cfg["train"]["loss_weights"] = lw
    occ = cfg["train"]["occluded_weight"]
    if isinstance(occ, bool) or not isinstance(occ, (int, float)) or not 0.0 <= occ < 1.0:
        raise ValueError(f"{path or 'config'}: train: occluded_weight must be in [0, 1) (a seen keypoint weighs 1), "
                         f"got {cfg['train']['occluded_weight']!r}")
    try:
        ModelConfig.from_dict(cfg["model"])
        AugConfig.from_dict(cfg["augment"])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path or 'config'}: {exc}") from None
    return cfg


def losses(model: KeypointModel, cb, gb, w: dict, hidden_sigma: float = 0.0) -> dict:
    """Loss terms of a stage-2 batch ``cb`` and a stage-1 batch ``gb`` (either may be None).
    ``hidden_sigma`` > 0: hidden keypoints (weight under 1, ``crop_sample``) get targets that wide."""
    cfg = model.cfg
    out = {}
    if cb is not None:
        x, kpc, valid, line, pres = cb
        heat, p = model.crop(x)
        sigma = cfg.kp_sigma
        if hidden_sigma > 0:
            sigma = torch.where((valid > 0) & (valid < 1), float(hidden_sigma), float(cfg.kp_sigma))
        out["kp"] = keypoint_loss(heat[:, :5], gaussian_targets(kpc, valid, cfg.heat, sigma))
        out["line"] = F.binary_cross_entropy_with_logits(heat[:, 5], line)
        out["presence"] = F.binary_cross_entropy_with_logits(p, pres)
        if cfg.visibility:   # seen (weight 1) or hidden (under 1); no statement where no target
            m = (valid > 0).float()
            bce = F.binary_cross_entropy_with_logits(visibility_logits(heat), (valid >= 1).float(),
                                                     reduction="none")
            out["visibility"] = (bce * m).sum() / m.sum().clamp_min(1.0)
    if gb is not None:
        gx, gheat, greg, gmask = gb
        g = model.glob(gx)
        out["global"] = focal_heatmap_loss(g[:, 0], gheat)
        m = gmask[:, None]
        out["box"] = (F.smooth_l1_loss(g[:, 1:5], greg, reduction="none", beta=0.1) * m).sum() / m.sum().clamp_min(1) / 4
        # image-level presence on the heatmap's peak (the detector's confidence): MIL-style
        has = (gmask.flatten(1).sum(1) > 0).float()
        out["global_presence"] = F.binary_cross_entropy_with_logits(g[:, 0].flatten(1).amax(1), has)
    out["total"] = sum(w.get(k, 0.0) * v for k, v in out.items())
    return out


def distillation_losses(model: KeypointModel, teacher: KeypointModel, cb, gb, w: dict,
                        keypoints: bool = False) -> dict:
    """Learning without forgetting (Li & Hoiem 2016), for what decides *whether* a needle is
    found: the loss terms of matching the frozen ``teacher``'s stage-2 presence on a stage-2
    batch ``cb`` and its stage-1 heatmap (each cell, and its peak: the image-level confidence)
    and boxes (where it sees a centre) on a stage-1 batch ``gb``, as soft targets (the batches'
    own targets are not used). Not the keypoint or centreline heatmaps: where no label was
    confirmed the teacher's keypoints are often wrong (a tip read at the wrong end), and copying
    them teaches that back. ``keypoints``: the keypoint heatmaps' softmax and the centreline
    ridge too, for folders where the teacher is right (the looks it was trained on).
    Weighted by ``w`` (the loss weights) and summed in ``total``."""
    out = {}
    if cb is not None:
        x = cb[0]
        with torch.no_grad():
            t_heat, t_p = teacher.crop(x)
        heat, p = model.crop(x)
        out["presence"] = F.binary_cross_entropy_with_logits(p, torch.sigmoid(t_p))
        if keypoints:
            n, k = t_heat.shape[0], 5
            soft = F.softmax(t_heat[:, :k].reshape(n, k, -1), dim=-1).reshape(t_heat[:, :k].shape)
            out["kp"] = keypoint_loss(heat[:, :k], soft)
            out["line"] = F.binary_cross_entropy_with_logits(heat[:, 5], torch.sigmoid(t_heat[:, 5]))
    if gb is not None:
        gx = gb[0]
        with torch.no_grad():
            tg = teacher.glob(gx)
        g = model.glob(gx)
        t_heat = torch.sigmoid(tg[:, 0])
        out["global"] = F.binary_cross_entropy_with_logits(g[:, 0], t_heat)
        m = t_heat[:, None]
        out["box"] = (F.smooth_l1_loss(g[:, 1:5], tg[:, 1:5], reduction="none", beta=0.1) * m).sum() / m.sum().clamp_min(1) / 4
        out["global_presence"] = F.binary_cross_entropy_with_logits(g[:, 0].flatten(1).amax(1),
                                                                    t_heat.flatten(1).amax(1))
    out["total"] = sum(w.get(k, 0.0) * v for k, v in out.items())
    return out


# ---------------------------------------------------------------- validation

@torch.inference_mode()
def validate(model: KeypointModel, records, threshold: float = 0.5) -> dict:
    """Validation figures on prepared records: stage 2 with the ground-truth box, and the whole
    two-stage pipeline (stage-1 box -> crop); per-keypoint pixel errors at full resolution."""
    model.eval()
    cfg = model.cfg
    err_gt, err_pipe = [], []
    found, n_pos, fp, n_neg = 0, 0, 0, 0
    for rec in records:
        gx = torch.from_numpy(global_input(rec.small)).permute(2, 0, 1)[None].contiguous()
        _, _, ds, box_scale = global_size(cfg, *rec.image_size)
        conf, cx, cy, bw, bh = decode_global(model.glob(gx), ds, box_scale)
        if not rec.has_needle:
            n_neg += 1
            if conf >= threshold:
                M = crop_affine(cx, cy, crop_side(cfg, bw, bh), cfg.crop)
                _, pres = model.crop(torch.from_numpy(crop_from(rec.neg if rec.neg.size else rec.region,
                                     rec.neg_origin if rec.neg.size else rec.origin, M, cfg.crop)
                                     ).permute(2, 0, 1)[None].contiguous())
                fp += int(float(torch.sigmoid(pres[0])) >= threshold)
            continue
        if rec.vis.sum() < 2:
            continue
        n_pos += 1
        boxes = [("gt", rec.box)]
        if conf >= threshold:
            boxes.append(("pipe", (cx, cy, bw, bh)))
        for kind, box in boxes:
            for rep in range(2 if kind == "pipe" else 1):   # the detector's second, re-centred pass
                bx, by, bw_, bh_ = box
                M = crop_affine(bx, by, crop_side(cfg, bw_, bh_), cfg.crop)
                crop = crop_from(rec.region, rec.origin, M, cfg.crop)
                heat, pres = model.crop(torch.from_numpy(crop).permute(2, 0, 1)[None].contiguous())
                uv, _ = decode_heatmaps(heat[:, :5], cfg.out_stride)
                uv_img = apply_affine(invert_affine(M), uv[0].numpy())
                lo, hi = uv_img.min(0), uv_img.max(0)
                box = ((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[0] - lo[0] + 4, hi[1] - lo[1] + 4)
            if kind == "pipe" and float(torch.sigmoid(pres[0])) < threshold:
                continue
            e = np.where(rec.vis, np.linalg.norm(uv_img - rec.kp, axis=1), np.nan)  # visible points only
            (err_gt if kind == "gt" else err_pipe).append(e)
            if kind == "pipe":
                found += 1
    res = {"n_pos": n_pos, "n_neg": n_neg, "found": found,
           "detection_rate": found / max(1, n_pos), "false_positives": fp}
    for name, errs in (("gtbox", err_gt), ("pipe", err_pipe)):
        if errs:
            e = np.asarray(errs)
            res[f"{name}_mean_px"] = float(np.nanmean(e))
            res[f"{name}_median_px"] = float(np.nanmedian(e))
            res[f"{name}_per_kp_px"] = [float(v) for v in np.nanmean(e, 0)]
    model.train()
    return res


# ---------------------------------------------------------------- files

def save_model(path, model: KeypointModel, meta: dict) -> None:
    """The weights file the detector loads (tensors and plain types only: weights_only=True)."""
    blob = {"format": MODEL_FORMAT, "version": MODEL_VERSION, "config": model.cfg.to_dict(),
            "state_dict": {k: v.detach().clone() for k, v in model.state_dict().items()},
            "meta": json.loads(json.dumps(meta))}
    tmp = str(path) + ".tmp"
    torch.save(blob, tmp)
    os.replace(tmp, path)


def plot_curves(metrics: list[dict], path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ep = [m["epoch"] for m in metrics]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].plot(ep, [m["train_loss"] for m in metrics], "o-", label="train loss")
    ax[0].set_xlabel("epoch"); ax[0].set_yscale("log"); ax[0].legend()
    for key, lab in (("gtbox_mean_px", "val, ground-truth box"), ("pipe_mean_px", "val, two-stage")):
        ax[1].plot(ep, [m["val"].get(key, np.nan) for m in metrics], "o-", label=lab)
    ax[1].set_xlabel("epoch"); ax[1].set_ylabel("mean keypoint error (px)"); ax[1].set_yscale("log")
    ax[1].grid(True, which="both", alpha=0.3); ax[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def prepare_records(data_dirs, out: Path, mcfg: ModelConfig, seed: int, progress: bool = True,
                    jaw_share: float = 0.0):
    """Records of all data folders, cached (outside the repository, in the temp folder) under a
    key made of the folders, their frames.jsonl size and time, the downscale and the seed."""
    import hashlib
    import tempfile
    def stamp(d):  # a folder that grew (or changed) invalidates the cache
        f = Path(d) / "frames.jsonl"
        return [str(Path(d).resolve()), f.stat().st_size if f.is_file() else -1,
                f.stat().st_mtime_ns if f.is_file() else -1]
    key = json.dumps({"data": [stamp(d) for d in data_dirs], "downscale": mcfg.global_downscale, "stage1_scale": "width",
                      "targets": "arc_seen",
                      "seed": seed, **({"jaw_share": jaw_share} if jaw_share else {})})
    cache_dir = Path(tempfile.gettempdir()) / "needletrack-keypoint-cache"
    cache_dir.mkdir(parents=True, exist_ok=True)
    h = hashlib.sha1(key.encode()).hexdigest()[:16]
    cache, key_path = cache_dir / f"{h}.npz", cache_dir / f"{h}.key"
    if cache.is_file() and key_path.is_file() and key_path.read_text() == key:
        return load_cached(cache)
    records = []
    for i, d in enumerate(data_dirs):
        records += load_records(d, mcfg, seed=seed + i, progress=progress, jaw_share=jaw_share)
    save_records(cache, records)
    key_path.write_text(key)
    return records


def split(records, fraction: float, seed: int):
    """Train/validation split by frame (both cameras of a frame on the same side)."""
    keys = sorted({(r.image_size, r.frame) for r in records})
    rng = np.random.default_rng(seed)
    order = rng.permutation(len(keys))
    n_val = int(round(fraction * len(keys)))
    val_keys = {keys[i] for i in order[:n_val]}
    tr = [r for r in records if (r.image_size, r.frame) not in val_keys]
    va = [r for r in records if (r.image_size, r.frame) in val_keys]
    return tr, va


# ---------------------------------------------------------------- main

def parameter_groups(model: KeypointModel, backbone_lr: float) -> list[dict]:
    """Optimiser groups: the pretrained trunks' parameters at ``backbone_lr`` x the learning rate
    (``lr_scale``), the rest at 1 x."""
    params = [(name, p) for name, p in model.named_parameters() if p.requires_grad]   # not the frozen blocks
    trunk = {id(p) for name, p in params if ".trunk." in f".{name}"}
    own = [p for _, p in params if id(p) not in trunk]
    pre = [p for _, p in params if id(p) in trunk]
    return [g for g in ({"params": own, "lr_scale": 1.0}, {"params": pre, "lr_scale": backbone_lr}) if g["params"]]


def train(data_dirs, out, config_path=None, log=print, progress=True, init=None,
          teacher_dirs=None) -> dict:
    """Train (or resume) into the folder ``out``; returns the last epoch's metrics. ``init``: a
    weights file to start from (fine-tuning) when ``out`` holds no checkpoint yet.
    ``teacher_dirs`` (with ``init``): folders whose images, at their frames' ``bbox``, are no
    targets but inputs on which the new weights keep ``init``'s presence and proposals
    (``distillation_losses``, weight ``train.distill_weight``): a needle the labels do not show
    is not forgotten."""
    cfg = load_config(config_path)
    tcfg = cfg["train"]
    mcfg = ModelConfig.from_dict(cfg["model"])
    aug = AugConfig.from_dict(cfg["augment"])
    seed = int(cfg["seed"])
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(max(1, int(tcfg["threads"])))
    (out / "train.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))

    records = prepare_records(data_dirs, out, mcfg, seed, progress, float(tcfg["jaw_negatives"]))
    tr, va = split(records, float(tcfg["val_fraction"]), seed)
    pos = [i for i, r in enumerate(tr) if r.has_needle]
    if not pos:
        raise DatasetError(f"{data_dirs}: no image with a visible needle to train on")
    log(f"train: {len(tr)} images ({len(pos)} with a needle), validation: {len(va)}")

    torch.manual_seed(seed)
    model = KeypointModel(mcfg)
    stages = list(tcfg["stages"])
    if not stages or set(stages) - {"global", "crop"}:
        raise ValueError(f"{config_path}: train.stages must list 'global' and/or 'crop', got {stages}")
    def load_init(into: KeypointModel) -> None:
        try:
            src = torch.load(init, map_location="cpu", weights_only=True)
            if ModelConfig.from_dict(dict(src.get("config") or {})) != mcfg:
                raise ValueError(f"--init {init}: its model config differs from {config_path}")
            into.load_state_dict(src["state_dict"])
        except (OSError, RuntimeError, KeyError, AttributeError) as exc:
            raise ValueError(f"--init {init}: cannot load ({exc})") from None

    if init and not (out / "checkpoint.pt").is_file():
        load_init(model)
        log(f"starting from the weights of {init}")
    elif not (out / "checkpoint.pt").is_file() and mcfg.backbone:
        model.load_pretrained()
        log(f"starting from the ImageNet weights of {mcfg.backbone} (common.detector.backbone)")
    teacher, t_recs = None, []
    if teacher_dirs and float(tcfg["distill_weight"]) > 0:
        if not init:
            raise ValueError("teacher folders need the weights to keep (--init)")
        teacher = KeypointModel(mcfg)
        load_init(teacher)
        teacher.eval()
        for p_ in teacher.parameters():
            p_.requires_grad_(False)
        for i, d in enumerate(teacher_dirs):
            t_recs += load_records(d, mcfg, seed=seed + 1000 + i, progress=progress, boxes_only=True)
        log(f"distillation: {len(t_recs)} images on which the weights of {init} are kept")
        if not t_recs:
            teacher = None
    # the teacher is kept on its own looks: no hue turn or motion blur it may never have seen
    t_aug = replace(aug, hue=0.0, motion_blur=0.0)
    hard = []
    at = tcfg["hard_mining_at"]
    # each mining adds the current weights' false proposals to the earlier ones
    mine_at = sorted(float(a) for a in (at if isinstance(at, list) else [at])) \
        if int(tcfg["hard_negatives"]) > 0 else []

    def mine() -> list:
        found = mine_hard_negatives(model, data_dirs, int(tcfg["hard_negatives"]), progress,
                                    int(tcfg["hard_mining_images"]), seed)
        log(f"{len(found)} hard negatives mined")
        return found
    steps_per_epoch = int(tcfg["steps_per_epoch"]) or max(1, len(tr) // int(tcfg["batch"]))
    total = steps_per_epoch * int(tcfg["epochs"])
    groups = parameter_groups(model, float(tcfg["backbone_lr"]))
    if tcfg["optimizer"] == "sgd":
        opt = torch.optim.SGD(groups, lr=tcfg["lr"], momentum=tcfg["momentum"],
                              weight_decay=tcfg["weight_decay"])
    elif tcfg["optimizer"] == "adamw":
        opt = torch.optim.AdamW(groups, lr=tcfg["lr"], weight_decay=tcfg["weight_decay"])
    else:
        raise ValueError(f"{config_path}: train.optimizer must be adamw or sgd, got {tcfg['optimizer']!r}")
    warm = int(tcfg["warmup_steps"])
    base_lr = float(tcfg["lr"])
    budget = float(tcfg["time_budget_min"]) * 60.0

    def progress_of(step: int, seconds: float) -> float:
        """Fraction of the schedule done: by steps, or by training time when a budget is set
        and runs out first (a shared machine can be much slower than planned)."""
        frac = step / max(1, total)
        return min(1.0, max(frac, seconds / budget) if budget else frac)

    start_epoch, best, elapsed, metrics, step_count = 0, float("inf"), 0.0, [], 0
    ckpt_path = out / "checkpoint.pt"
    if ckpt_path.is_file():
        ck = torch.load(ckpt_path, map_location="cpu", weights_only=True)
        if ModelConfig.from_dict(dict(ck.get("config") or {})) != mcfg:
            raise ValueError(f"{ckpt_path}: was trained with another model config; "
                             f"delete it or use another --out")
        model.load_state_dict(ck["state_dict"])
        opt.load_state_dict(ck["optimizer"])
        start_epoch, best, elapsed = int(ck["epoch"]), float(ck["best"]), float(ck["elapsed_s"])
        step_count = int(ck["step"])
        log(f"resuming from {ckpt_path} after epoch {start_epoch}")
    mpath = out / "metrics.jsonl"
    if mpath.is_file() and start_epoch:
        metrics = [json.loads(l) for l in mpath.read_text().splitlines() if l.strip()][:start_epoch]

    from common.progress import progress_bar
    w = tcfg["loss_weights"]
    last = {}
    model.train()
    for epoch in range(start_epoch, int(tcfg["epochs"])):
        if progress_of(step_count, elapsed) >= 1.0:
            log(f"schedule finished after {step_count} steps, {elapsed / 60:.1f} min of training")
            break
        t0 = time.time()
        rng = np.random.default_rng([seed, epoch])
        torch.manual_seed(seed * 1000 + epoch)
        order = rng.permutation(np.resize(rng.permutation(len(tr)), steps_per_epoch * int(tcfg["batch"])))
        running = None
        bar = progress_bar(range(steps_per_epoch), desc=f"epoch {epoch + 1}/{tcfg['epochs']}", show=progress,
                   unit="step", dynamic_ncols=True)
        for step in bar:
            frac = progress_of(step_count, elapsed + time.time() - t0)
            if frac >= 1.0:
                break
            if mine_at and frac >= mine_at[0]:
                mine_at = [a for a in mine_at if a > frac]
                t_mine = time.time()
                hard = hard + mine()
                t0 += time.time() - t_mine   # mining is not training time
            idx = order[step * int(tcfg["batch"]):(step + 1) * int(tcfg["batch"])]
            gidx = rng.integers(0, len(tr), int(tcfg["global_batch"]))
            cb = (crop_batch(tr, idx, mcfg, aug, rng, hard, float(tcfg["hard_prob"]), float(tcfg["occluded_weight"]))
                  if "crop" in stages else None)
            gb = global_batch(tr, gidx, mcfg, aug, rng) if "global" in stages else None
            L = losses(model, cb, gb, w, float(tcfg["hidden_sigma"]))
            if teacher is not None:
                tidx = rng.integers(0, len(t_recs), int(tcfg["distill_batch"]))
                D = distillation_losses(
                    model, teacher,
                    crop_batch(t_recs, tidx, mcfg, t_aug, rng) if "crop" in stages else None,
                    global_batch(t_recs, tidx, mcfg, t_aug, rng) if "global" in stages else None, w,
                    keypoints=bool(tcfg["distill_keypoints"]))
                L["distill"] = D["total"]
                L["total"] = L["total"] + float(tcfg["distill_weight"]) * D["total"]
            lr = base_lr * min(1.0, (step_count + 1) / max(1, warm)) * 0.5 * (1 + math.cos(math.pi * frac))
            for g in opt.param_groups:
                g["lr"] = lr * g["lr_scale"]
            opt.zero_grad(set_to_none=True)
            L["total"].backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
            opt.step()
            step_count += 1
            vals = {k: float(v.detach()) for k, v in L.items()}
            running = vals if running is None else {k: 0.95 * running[k] + 0.05 * vals[k] for k in vals}
            bar.set_postfix(loss=f"{running['total']:.3f}", kp=f"{running.get('kp', 0):.3f}",
                            glob=f"{running.get('global', 0):.3f}", lr=f"{lr:.1e}")
        bar.close()
        if running is None:
            break
        done = (epoch + 1 == int(tcfg["epochs"])
                or progress_of(step_count, elapsed + time.time() - t0) >= 1.0)
        checked = bool(va) and (done or (epoch + 1) % max(1, int(tcfg["val_every"])) == 0)
        val = validate(model, va) if checked else {}
        elapsed += time.time() - t0
        last = {"epoch": epoch + 1, "train_loss": running["total"], "train": running, "val": val,
                "elapsed_s": round(elapsed, 1)}
        metrics.append(last)
        score = val.get("pipe_mean_px", val.get("gtbox_mean_px", running["total"]))
        if val and val.get("detection_rate", 1.0) < 0.9:
            score = score + 100.0   # a model that misses needles is never "best"
        msg = (f"epoch {epoch + 1}: loss {running['total']:.4f}  ({elapsed / 60:.1f} min)" if not checked else
               f"epoch {epoch + 1}: loss {running['total']:.4f}  val gt-box {val.get('gtbox_mean_px', float('nan')):.3f} px"
               f"  two-stage {val.get('pipe_mean_px', float('nan')):.3f} px  detected {val.get('found', 0)}/{val.get('n_pos', 0)}"
               f"  fp {val.get('false_positives', 0)}/{val.get('n_neg', 0)}  ({elapsed / 60:.1f} min)")
        log(msg)
        meta = {"epoch": epoch + 1, "val": val, "train_seconds": round(elapsed, 1),
                "data": [str(d) for d in data_dirs], "seed": seed}
        if mcfg.backbone:   # the pretrained weights' provenance and licence travel with the file
            from common.detector.backbone import provenance
            meta["backbone"] = provenance()
        scored = checked or not va
        if scored and score <= best or not (out / "model.pt").is_file():
            if scored:   # a first model saved without validation sets no bar for the next
                best = min(best, score)
            save_model(out / "model.pt", model, meta)
        with open(mpath, "w") as f:
            f.write("".join(json.dumps(m) + "\n" for m in metrics))
        ck = {"config": mcfg.to_dict(), "state_dict": model.state_dict(), "optimizer": opt.state_dict(),
              "step": step_count, "epoch": epoch + 1, "best": best, "elapsed_s": elapsed}
        torch.save(ck, str(ckpt_path) + ".tmp")
        os.replace(str(ckpt_path) + ".tmp", ckpt_path)
        try:
            plot_curves(metrics, out / "curves.png")
        except Exception as exc:  # a plotting problem must not stop training
            log(f"could not plot curves: {exc}")
    return last


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="needletrack train",
                                 description="Train the learned needle keypoint detector (CPU).")
    ap.add_argument("--data", action="append", required=True, help="dataset folder (repeatable)")
    ap.add_argument("--config", default=None, help="training YAML (e.g. models/train.yaml)")
    ap.add_argument("--out", required=True, help="output folder, e.g. models/keypoint")
    ap.add_argument("--init", default=None, help="start from these weights (fine-tuning)")
    ap.add_argument("--teacher", action="append", default=None,
                    help="folder on which the --init weights' outputs are kept (learning without "
                         "forgetting: train.distill_weight, distill_keypoints); repeatable")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    a = ap.parse_args(argv)
    try:
        train(a.data, a.out, a.config, progress=not a.no_progress, init=a.init, teacher_dirs=a.teacher)
    except (DatasetError, ValueError, OSError) as exc:
        print(f"needletrack train: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("needletrack train: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
