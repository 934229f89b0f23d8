"""Which frames of a hand-labelled folder are training targets (``needletrack finetune``,
docs/adapt.md).

Only what a person stated counts (``needletrack label``'s ``label`` field, docs/label.md):

- ``target``: a labelled frame whose every camera was either clicked or marked "not seen"; its
  keypoints are targets, those marked hidden (``visible`` false) hidden targets (the trainer's
  ``occluded_weight``), a camera marked not seen a negative image;
- ``no_needle``: a frame marked "no needle": both images are negatives;
- ``one_camera``: a camera neither clicked nor marked not seen (a one-camera label writes its
  keypoints as not visible): not trained on, since that image would pass for one without a
  needle;
- ``unlabelled`` and ``truth`` (ground truth not made by a person here, e.g. a render's): not
  targets. An unlabelled frame is never taken for a negative.
"""
from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from typing import Optional

import numpy as np

from common.data.dataset import FRAMES_FILE, META_FILE, Dataset
from common.data.writer import link_or_copy, staged_folder
from common.errors import NeedletrackError
from common.frames import CAMERAS
from common.label.store import LABEL_FIELD, LabelStore

TRAINED_KINDS = ("target", "no_needle")


class LabelsError(NeedletrackError, ValueError):
    """A folder that gives no hand labels to train on (named, with what to do)."""


@dataclass(frozen=True)
class LabelledFrame:
    """One frame of ``folder`` (its ``index``) and what its hand label makes of it (``kind``, the
    module docstring); ``hidden``: keypoints marked hidden in cameras that show the needle;
    ``stamp``: when the label was saved (0 without one)."""

    folder: str
    index: int
    kind: str
    sequence: Optional[int] = None
    hidden: int = 0
    stamp: float = 0.0


def _camera_stated(clicks: Optional[dict]) -> bool:
    """Whether a camera's recorded clicks state something: marked not seen, or clicked."""
    if not isinstance(clicks, dict):
        return False
    return bool(clicks.get("unseen")) or clicks.get("tip") is not None or clicks.get("tail") is not None \
        or bool(clicks.get("wire"))


def read_labels(folder: str) -> list[LabelledFrame]:
    """Every frame of ``folder`` with its kind (``DatasetError`` for a folder that is no dataset)."""
    store = LabelStore(folder)
    where = os.path.realpath(store.path)
    out = []
    for i, fr in enumerate(store.ds.frames):
        status = store.status(i)
        hidden = 0
        if status == "labelled":
            clicks = (store.label(i) or {}).get("clicks") or {}
            kind = "target" if all(_camera_stated(clicks.get(c)) for c in CAMERAS) else "one_camera"
            if kind == "target" and fr.visible is not None:
                hidden = sum(int((~np.asarray(fr.visible[c], bool)).sum()) for c in CAMERAS
                             if not (clicks.get(c) or {}).get("unseen"))
        else:
            kind = status
        stamp = (store.label(i) or {}).get("stamp", 0.0)
        out.append(LabelledFrame(where, i, kind, fr.sequence, hidden,
                                 float(stamp) if isinstance(stamp, (int, float)) else 0.0))
    return out


def counts(frames: list[LabelledFrame]) -> dict:
    """How many frames of each kind, and the hidden keypoints of the targets."""
    out = {k: 0 for k in ("target", "no_needle", "one_camera", "unlabelled", "truth")}
    for f in frames:
        out[f.kind] = out.get(f.kind, 0) + 1
    out["hidden_keypoints"] = sum(f.hidden for f in frames if f.kind == "target")
    return out


def trainable(folders: list[str]) -> list[LabelledFrame]:
    """The frames of ``folders`` that are trained on (``TRAINED_KINDS``); ``LabelsError`` naming
    each folder and what it holds when there are none."""
    frames, said = [], []
    for d in folders:
        fs = read_labels(d)
        c = counts(fs)
        said.append(f"{d}: {len(fs)} frames, {c['target']} labelled, {c['no_needle']} marked no needle, "
                    f"{c['one_camera']} labelled in one camera only, {c['unlabelled']} unlabelled"
                    + (f", {c['truth']} with ground truth not made by needletrack label" if c["truth"] else ""))
        frames += [f for f in fs if f.kind in TRAINED_KINDS]
    if not any(f.kind == "target" for f in frames):
        raise LabelsError("no hand-labelled frame with a needle to fine-tune on (" + "; ".join(said)
                          + "); label some first: needletrack label DIR (docs/label.md)")
    return frames


def split_held_out(frames: list[LabelledFrame], fraction: float, seed: int = 0) -> tuple[list, list]:
    """(train, held out): about ``fraction`` of the frames held out, whole takes at a time (the
    frames of one folder's ``sequence`` are near copies of each other: one on each side would
    flatter the held-out figures), at least one take with a needle on each side when there are
    two; seeded."""
    if not 0.0 <= fraction < 1.0:
        raise ValueError(f"held-out fraction must be in [0, 1), got {fraction}")
    groups: dict = {}
    for f in frames:
        key = (f.folder, f.sequence if f.sequence is not None else f"frame-{f.index}")
        groups.setdefault(key, []).append(f)
    keys = sorted(groups, key=str)
    rng = np.random.default_rng(seed)
    order = [keys[i] for i in rng.permutation(len(keys))]
    want = int(round(fraction * len(frames)))
    held, n = set(), 0
    with_needle = [k for k in order if any(f.kind == "target" for f in groups[k])]
    if fraction > 0 and len(with_needle) >= 2:       # a take with a needle is held out first
        held.add(with_needle[0])
        n += len(groups[with_needle[0]])
    for k in order:
        if n >= want:
            break
        if k in held or (len([j for j in with_needle if j not in held]) <= 1 and k in with_needle):
            continue                                    # keep a take with a needle to train on
        held.add(k)
        n += len(groups[k])
    train = [f for k in keys if k not in held for f in groups[k]]
    return sorted(train, key=lambda f: (f.folder, f.index)), sorted(
        [f for k in keys if k in held for f in groups[k]], key=lambda f: (f.folder, f.index))


def write_subset(frames: list[LabelledFrame], out: str) -> int:
    """A new dataset folder ``out`` of ``frames`` (one source folder): its dataset.yaml, the
    frames' lines as they are (reindexed, the source index kept in ``label.source_index``) and
    their images (hard-linked where possible). Written whole or not at all; returns the frames."""
    folders = {f.folder for f in frames}
    if len(folders) != 1:
        raise ValueError(f"write_subset: frames of one folder expected, got {sorted(folders)}")
    src = folders.pop()
    ds = Dataset(src)
    with open(os.path.join(ds.path, FRAMES_FILE), encoding="utf-8-sig") as f:
        lines = [json.loads(t) for t in f if t.strip()]
    with staged_folder(out) as tmp:
        shutil.copy2(os.path.join(ds.path, META_FILE), os.path.join(tmp, META_FILE))
        with open(os.path.join(tmp, FRAMES_FILE), "w", encoding="utf-8") as fo:
            for n, lf in enumerate(sorted(frames, key=lambda f: f.index)):
                line = dict(lines[lf.index])
                for c in CAMERAS:
                    link_or_copy(os.path.join(ds.path, line[c]), os.path.join(tmp, line[c]))
                line["index"] = n
                if isinstance(line.get(LABEL_FIELD), dict):
                    line[LABEL_FIELD] = {**line[LABEL_FIELD], "source_index": lf.index}
                fo.write(json.dumps(line, separators=(",", ":")) + "\n")
    return len(frames)
