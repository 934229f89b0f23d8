"""What ``needletrack train`` (``common.detector.train``) trains on: stage-2 crop batches (the
keypoints, the centreline, presence; with mined hard negatives, ``mine_hard_negatives``) and
stage-1 global batches (the needle's box)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from common.detector.data import OCCLUDED_WEIGHT, crop_from, crop_sample, global_input, global_sample
from common.detector.model import (
    KeypointModel,
    ModelConfig,
    centreline_target,
    crop_affine,
    crop_side,
    global_size,
)
from common.frames import CAMERAS


def crop_batch(records, idx, cfg: ModelConfig, aug, rng, hard=None, hard_prob: float = 0.0,
               occluded_weight: float = OCCLUDED_WEIGHT):
    items = [hard_sample(hard[rng.integers(len(hard))], cfg, aug, rng) if hard and rng.random() < hard_prob
             else crop_sample(records[i], cfg, aug, rng, occluded_weight=occluded_weight) for i in idx]
    x = torch.from_numpy(np.stack([it[0] for it in items])).permute(0, 3, 1, 2).contiguous()
    kpc = torch.from_numpy(np.stack([it[1] for it in items]))
    valid = torch.from_numpy(np.stack([it[2] for it in items]))
    line = centreline_target([it[3] for it in items], cfg.heat, cfg.line_sigma)
    pres = torch.tensor([it[4] for it in items], dtype=torch.float32)
    return x, kpc, valid, line, pres


def hard_sample(h, cfg: ModelConfig, aug, rng):
    """A stage-2 negative crop around a mined false proposal ``h`` = (region, origin, box)."""
    region, origin, (cx, cy, bw, bh) = h
    side = crop_side(cfg, bw, bh) * float(np.exp(rng.uniform(-0.25, 0.25)))
    cx += rng.uniform(-0.12, 0.12) * side
    cy += rng.uniform(-0.12, 0.12) * side
    M = crop_affine(cx, cy, side, cfg.crop, rng.uniform(-np.pi, np.pi), bool(rng.random() < 0.5))
    img = crop_from(region, origin, M, cfg.crop)
    if aug is not None:
        from common.detector.data import photometric
        img = photometric(img, aug, rng)
    return img, np.zeros((5, 2), np.float32), np.zeros(5, np.float32), None, 0.0


@torch.inference_mode()
def mine_hard_negatives(model: KeypointModel, data_dirs, per_image: int, progress=True,
                        max_images: int = 0, seed: int = 0) -> list:
    """Stage-1 proposals (confidence >= 0.15) far from the needle in the training images (all, or
    a seeded random subset of ``max_images`` frames' cameras):
    [(region uint8, origin (2,), box (cx, cy, w, h))], regions cut at full resolution."""
    import cv2
    from common.progress import progress_bar

    from common.detector.data import cut_square, read_dataset
    from common.detector.model import decode_global_topk
    model.eval()
    cfg = model.cfg
    out = []
    jobs = [(d, fr, cam) for d in data_dirs for fr in read_dataset(d)[1] for cam in CAMERAS]
    if 0 < max_images < len(jobs):
        keep = np.random.default_rng(seed).choice(len(jobs), max_images, replace=False)
        jobs = [jobs[i] for i in sorted(keep)]
    for d, fr, cam in progress_bar(jobs, desc="mining hard negatives", show=progress, unit="image"):
        img = cv2.imread(str(Path(d) / fr[cam]), cv2.IMREAD_COLOR)
        if img is None:
            continue
        h, w = img.shape[:2]
        ws, hs, ds, box_scale = global_size(cfg, w, h)
        small = cv2.resize(img, (ws, hs), interpolation=cv2.INTER_AREA)
        g = model.glob(torch.from_numpy(global_input(small)).permute(2, 0, 1)[None].contiguous())
        kp = np.asarray((fr.get("keypoints") or {}).get(cam) or np.full((5, 2), np.nan), float)
        n_img = 0
        for conf, cx, cy, bw, bh in decode_global_topk(g, ds, per_image + 1, 0.15, box_scale=box_scale):
            if np.isfinite(kp).all():
                near = np.linalg.norm(kp - [cx, cy], axis=1).min()
                if near < 0.6 * max(bw, bh, np.ptp(kp, 0).max()):
                    continue
            side = int(2.6 * max(bw, bh) + 48)
            region, origin = cut_square(img, int(cx - side / 2), int(cy - side / 2), side)
            if region.size:
                out.append((region, origin, (cx, cy, bw, bh)))
                n_img += 1
            if n_img >= per_image:
                break
    model.train()
    return out


def global_batch(records, idx, cfg: ModelConfig, aug, rng):
    items = [global_sample(records[i], cfg, aug, rng) for i in idx]
    shapes = {it[0].shape for it in items}
    if len(shapes) > 1:  # mixed image sizes: train on the most common one only
        common = max(shapes, key=lambda s: sum(it[0].shape == s for it in items))
        items = [it for it in items if it[0].shape == common]
    x = torch.from_numpy(np.stack([it[0] for it in items])).permute(0, 3, 1, 2).contiguous()
    heat = torch.from_numpy(np.stack([it[1] for it in items]))
    reg = torch.from_numpy(np.stack([it[2] for it in items]))
    mask = torch.from_numpy(np.stack([it[3] for it in items]))
    return x, heat, reg, mask
