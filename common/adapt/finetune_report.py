"""Before and after a fine-tune, on the user's held-out hand-labelled frames (``needletrack
finetune``'s report, docs/adapt.md): the weights run cold on each held-out image through the
detector backend's public API (``learned``, whatever network the weights hold), scored against
the labels:

- **found**: of the images whose label shows the needle (two or more keypoints seen), the share
  the detector finds; **false detections**: images labelled without a needle (a "no needle"
  frame, a camera marked not seen) where it finds one;
- **keypoint error**: pixels from each labelled seen keypoint to the detection's (found images);
- **tip right**: A nearer the labelled tip than the labelled tail (found images); **sure and
  right** / **confident swaps**: the stated end identity sure (``TIP_SURE``) and right / wrong.

The worst images of the new weights (missed, then the largest keypoint error) are drawn before
and after (``draw_detection``, the label's keypoints as green rings), and the frames to label
next are the unlabelled frames of the label folders the new weights are least sure of
(``common.label.proposals.doubt``, the page's own order).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from common.frames import CAMERAS

LABEL_BGR = (80, 220, 80)
WORST_PICTURES = 4


@dataclass
class ImageScore:
    """One held-out camera image: its frame in the held-out folder (``folder``, ``index``; the
    labelled folder's frame ``source_index``), whether the label shows a needle, and what the
    weights read (``found``, keypoint errors of the seen keypoints (px), tip right, stated end
    identity ``p_tip``, ``confidence``)."""

    folder: str
    index: int
    source_index: int
    camera: str
    needle: bool
    found: bool
    errors: Optional[list] = None
    tip_right: Optional[bool] = None
    p_tip: Optional[float] = None
    confidence: float = 0.0

    @property
    def badness(self) -> float:
        """For ranking the worst: a missed needle or a false detection first, then the largest error."""
        if self.needle != self.found:
            return 1e6
        return max(self.errors) if self.errors else 0.0


def score_weights(folders: list[str], weights: str, progress: bool = True) -> list[ImageScore]:
    """Each labelled image of the held-out ``folders`` read cold by ``weights``."""
    from common.data.dataset import Dataset
    from common.detector.backends import load_backend
    from common.label.proposals import stereo_detections
    backend = load_backend("learned", {"weights": str(weights), "tracking": False, "threads": 2})
    out = []
    for d in folders:
        ds = Dataset(d)
        for fr, kps in stereo_detections(ds, backend, progress=progress, desc=f"scoring {Path(weights).name}"):
            lab = fr.label or {}
            src = int(lab.get("source_index", fr.index))
            for c in CAMERAS:
                vis = np.zeros(5, bool) if fr.visible is None else np.asarray(fr.visible[c], bool)
                needle = bool(not lab.get("no_needle") and fr.keypoints is not None and vis.sum() >= 2)
                unseen = bool(((lab.get("clicks") or {}).get(c) or {}).get("unseen"))
                if not needle and not (lab.get("no_needle") or unseen):
                    continue                       # a needle the label does not place: not scored
                k = None if kps is None else kps[c]
                s = ImageScore(ds.path, fr.index, src, c, needle, bool(k is not None and k.found),
                               confidence=0.0 if k is None else float(k.confidence))
                if needle and s.found:
                    true, uv = np.asarray(fr.keypoints[c], float), np.asarray(k.uv, float)
                    s.errors = [float(e) for e in np.linalg.norm(uv - true, axis=1)[vis]]
                    as_said = np.linalg.norm(uv[0] - true[0]) + np.linalg.norm(uv[4] - true[4])
                    turned = np.linalg.norm(uv[0] - true[4]) + np.linalg.norm(uv[4] - true[0])
                    s.tip_right = bool(as_said < turned)
                    s.p_tip = None if k.end_identity is None else float(k.end_identity)
                out.append(s)
    return out


def summary(scores: list[ImageScore]) -> dict:
    """The figures of the module docstring over ``scores``."""
    from common.geometry.end_identity import TIP_SURE
    pos = [s for s in scores if s.needle]
    neg = [s for s in scores if not s.needle]
    found = [s for s in pos if s.found]
    err = np.array([e for s in found for e in (s.errors or [])])
    q = lambda f: float(f(err)) if len(err) else None
    sure = [s for s in found if s.p_tip is not None and (s.p_tip >= TIP_SURE or s.p_tip <= 1 - TIP_SURE)]
    said = lambda s: s.p_tip >= 0.5
    return {
        "images_with_needle": len(pos), "found": len(found), "found_share": len(found) / len(pos) if pos else None,
        "images_without": len(neg), "false_detections": sum(s.found for s in neg),
        "keypoint_px": {"mean": q(np.mean), "median": q(np.median), "p90": q(lambda a: np.percentile(a, 90)),
                        "max": q(np.max), "n": int(len(err))},
        "tip_right": sum(bool(s.tip_right) for s in found) / len(found) if found else None,
        "sure_right": sum(said(s) == s.tip_right for s in sure) / len(found) if found else None,
        "confident_swaps": sum(said(s) != s.tip_right for s in sure),
    }


def _with_label(img: np.ndarray, fr, camera: str) -> np.ndarray:
    """``img`` with the label's keypoints as small green rings (drawn on the full-size image, so
    the picture's zoomed crop shows them sharp; a broken ring where marked hidden)."""
    out = img.copy()
    if fr.keypoints is None:
        return out
    vis = np.ones(5, bool) if fr.visible is None else np.asarray(fr.visible[camera], bool)
    for p, v in zip(np.asarray(fr.keypoints[camera], float), vis):
        if np.isfinite(p).all():
            c = (int(round(p[0])), int(round(p[1])))
            for a in range(0, 360, 360 if v else 60):
                cv2.ellipse(out, c, (3, 3), 0, a, a + (360 if v else 30), LABEL_BGR, 1, cv2.LINE_AA)
    return out


def worst_pictures(before: list[ImageScore], after: list[ImageScore], weights: tuple[str, str], out_dir,
                   k: int = WORST_PICTURES) -> list[dict]:
    """Pictures of the ``k`` worst held-out images of the new weights, before | after, written to
    ``out_dir``; returns what each shows."""
    from common.data.dataset import Dataset
    from common.detector.backends import load_backend
    from common.label.proposals import stereo_detections
    from common.viewer.draw import draw_detection, side_by_side
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for old in out_dir.glob("worst-*.png"):
        old.unlink()
    by_key = {(s.folder, s.index, s.camera): s for s in before}
    worst = sorted(after, key=lambda s: -s.badness)[:k]
    backends = [load_backend("learned", {"weights": str(w), "tracking": False, "threads": 2}) for w in weights]
    done = []
    for n, s in enumerate(worst, 1):
        ds = Dataset(s.folder)
        fr = ds.frames[s.index]
        img = ds.image(fr, s.camera)
        pics = []
        for name, b, sc in (("before", backends[0], by_key.get((s.folder, s.index, s.camera))), ("after", backends[1], s)):
            _f, kps = next(stereo_detections(ds, b, [fr], progress=False))
            cap = f"{name}: {describe(sc)}"
            pics.append(draw_detection(_with_label(img, fr, s.camera), kps[s.camera], cap, max_width=960, max_height=720))
        path = out_dir / f"worst-{n}-frame{s.source_index}-{s.camera}.png"
        cv2.imwrite(str(path), side_by_side(*pics))
        done.append({"picture": path.name, "frame": s.source_index, "camera": s.camera, "after": describe(s),
                     "before": describe(by_key.get((s.folder, s.index, s.camera)))})
    return done


def describe(s: Optional[ImageScore]) -> str:
    """One image's reading in words."""
    if s is None:
        return "not scored"
    if not s.needle:
        return "false detection" if s.found else "no needle, right"
    if not s.found:
        return "missed"
    tip = "tip right" if s.tip_right else "tip and tail swapped"
    sure = "" if s.p_tip is None else f", p(tip) {s.p_tip:.2f}"
    return f"max {max(s.errors):.1f} px, mean {np.mean(s.errors):.1f} px, {tip}{sure}" if s.errors else tip


def label_next(folders: list[str], weights: str, k: int = 10, most: int = 200, progress: bool = True) -> list[dict]:
    """The ``k`` unlabelled frames of ``folders`` (at most ``most`` read, evenly spread) the
    ``weights`` are least sure of (``doubt``, the page's order): the frames worth labelling next."""
    from common.data.dataset import Dataset
    from common.detector.backends import load_backend
    from common.label.proposals import doubt, proposal_of, stereo_detections
    from common.label.targets import read_labels
    backend = load_backend("learned", {"weights": str(weights), "tracking": False, "threads": 2})
    found = []
    for d in folders:
        ds = Dataset(d)
        todo = [ds.frames[f.index] for f in read_labels(d) if f.kind == "unlabelled"]
        if len(todo) > most:
            todo = [todo[int(i)] for i in np.linspace(0, len(todo) - 1, most).round()]
        for fr, kps in stereo_detections(ds, backend, todo, progress=progress, desc="frames to label next"):
            found.append({"folder": ds.path, "frame": fr.index,
                          "doubt": round(doubt(None if kps is None else proposal_of(kps)), 3)})
    return sorted(found, key=lambda x: (-x["doubt"], x["folder"], x["frame"]))[:k]


def _cell(x, fmt="{:.2f}", pct=False) -> str:
    if x is None:
        return "n/a"
    return f"{100 * x:.1f}%" if pct else fmt.format(x)


def markdown(report: dict) -> str:
    """The report as Markdown (OUT/report/report.md)."""
    b, a = report["before"], report["after"]
    rows = [("images with a needle: found", lambda s: f"{s['found']} / {s['images_with_needle']} "
                                                       f"({_cell(s['found_share'], pct=True)})"),
            ("images without: false detections", lambda s: f"{s['false_detections']} / {s['images_without']}"),
            ("keypoint error, mean (median, p90) px", lambda s: f"{_cell(s['keypoint_px']['mean'])} "
             f"({_cell(s['keypoint_px']['median'])}, {_cell(s['keypoint_px']['p90'])})"),
            ("tip read right", lambda s: _cell(s["tip_right"], pct=True)),
            ("tip sure and right", lambda s: _cell(s["sure_right"], pct=True)),
            ("confident swaps", lambda s: str(s["confident_swaps"]))]
    lines = [f"# Fine-tune report: {report['out']}", "",
             f"Held-out hand-labelled frames: {report['held_out_frames']} ({report['held_out_images']} images "
             f"scored), never trained on. Before: `{report['weights']['before']}`; after: "
             f"`{report['weights']['after']}`.", "",
             "| | before | after |", "| --- | --- | --- |"]
    lines += [f"| {name} | {f(b)} | {f(a)} |" for name, f in rows]
    lines += ["", "## The worst held-out images after (before | after; the label's keypoints as green rings)", ""]
    for w in report["worst"]:
        lines += [f"- frame {w['frame']} ({w['camera']}): before {w['before']}; after {w['after']}", "",
                  f"  ![frame {w['frame']} {w['camera']}]({w['picture']})", ""]
    lines += ["## Label next", ""]
    if report["label_next"]:
        lines += ["The unlabelled frames the new weights are least sure of (`needletrack label` opens them "
                  "in this order too when started with the new weights as its detector):", ""]
        lines += [f"- {x['folder']} frame {x['frame']}: doubt {x['doubt']:.2f}" for x in report["label_next"]]
    else:
        lines += ["No unlabelled frames in the label folders."]
    return "\n".join(lines) + "\n"


def write_report(out_dir, held: list[str], before_w: str, after_w: str, label_folders: list[str],
                 progress: bool = True, cache: Optional[Path] = None) -> dict:
    """Score ``before_w`` and ``after_w`` on the ``held`` folders, draw the worst, list the frames
    to label next; writes ``out_dir``/report.json, report.md and the pictures; returns the report.
    ``cache``: a JSON file keeping the before-weights' scores between runs."""
    from common.data.dataset import Dataset
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if cache is not None and cache.is_file():
        before = [ImageScore(**d) for d in json.loads(cache.read_text())]
    else:
        before = score_weights(held, before_w, progress)
        if cache is not None:
            cache.write_text(json.dumps([s.__dict__ for s in before]))
    after = score_weights(held, after_w, progress)
    report = {"out": str(out_dir), "weights": {"before": str(before_w), "after": str(after_w)},
              "held_out": [str(h) for h in held],
              "held_out_frames": sum(len(Dataset(h)) for h in held), "held_out_images": len(after),
              "before": summary(before), "after": summary(after),
              "worst": worst_pictures(before, after, (before_w, after_w), out_dir),
              "label_next": label_next(label_folders, after_w, progress=progress)}
    (out_dir / "report.json").write_text(json.dumps(report, indent=1) + "\n")
    (out_dir / "report.md").write_text(markdown(report))
    return report
