"""The adapted weights' familiarity and end-identity coefficients, fitted without ground truth.

Both are fitted on the pseudo-labels' held-out groups (``pseudo_labels``: ``out/fit``), which
training never sees:

- familiarity (``common.detector.familiarity``): needs no labels, only the new weights'
  detections on images of the look; fitted on them as ``needletrack bench familiarity --fit``.
- end identity (``common.detector.end_identity``): each detection is labelled by the group's
  agreed tip, which the *shipped* model's views voted for. Those labels are not independent of
  the model that made them: a group whose views all read the needle end for end the same way
  is kept, labelled turned, and no geometry can see it; and a held-out set with few errors
  cannot say how sure the new weights may be. So the new weights are never surer than the
  shipped ones: ``safe_scale`` shrinks the coefficients (towards stating nothing, p = 0.5, which
  is never sure and so never surely wrong) until, on the held-out groups' images, the new
  weights state a sure tip no more often than the shipped weights with their own coefficients
  do, and are surely wrong against the group's tip no more often. The coefficients are fitted
  only when the new weights read at least ``MIN_FIT_ERRORS`` of the held-out detections each
  way (as said, end for end); else the shipped coefficients are the start.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

SCALES = tuple(round(1.0 - 0.025 * i, 3) for i in range(41))
"""The shrink factors ``safe_scale`` tries, largest first, in steps of 0.025 (a sure share can fall
from most detections to almost none within 0.2, when the new weights' evidence is strong and
alike); 0 states no preference at all."""
MIN_DETECTIONS = 20
"""Fewer held-out detections than this: no fit (the shipped coefficients are kept)."""


def sure_wrong(X: np.ndarray, y: np.ndarray, coef: np.ndarray) -> float:
    """Share of detections whose stated tip is sure (``TIP_SURE``) and against the label."""
    from common.bench.end_identity_bench import summary
    return summary("", {"features": X, "labels": y, "images": len(y)}, coef)["sure_wrong"] if len(y) else 0.0


def sure_share(X: np.ndarray, coef: np.ndarray) -> float:
    """Share of detections whose stated tip is sure either way (``TIP_SURE``)."""
    from common.geometry.end_identity import TIP_SURE
    if not len(X):
        return 0.0
    p = 1.0 / (1.0 + np.exp(-X[:, :len(coef)] @ coef))
    return float(np.mean((p >= TIP_SURE) | (p <= 1 - TIP_SURE)))


def safe_scale(X: np.ndarray, y: np.ndarray, coef: np.ndarray, bound: float,
               max_sure: float = 1.0) -> float:
    """The largest of ``SCALES`` at which ``coef`` is surely wrong on (X, y) no more often than
    ``bound`` and sure no more often than ``max_sure`` (the shipped weights' rates on the same
    groups)."""
    for s in SCALES:
        if sure_wrong(X, y, s * coef) <= bound + 1e-12 and sure_share(X, s * coef) <= max_sure + 1e-12:
            return s
    return 0.0


def refit(new_weights, shipped_weights, fit_folder, log=print, progress: bool = True,
          labels: str = "pseudo-labels: the group-agreed tip") -> dict:
    """Write ``familiarity.json`` and ``end_identity.json`` beside ``new_weights`` from the
    held-out labelled ``fit_folder`` (a folder or a list of them; the module docstring);
    ``labels`` says what labelled them (hand labels: ``needletrack finetune``); returns what was
    done."""
    from common.detector.end_identity import COEF, FEATURES, fit_coefficients
    from common.detector.familiarity import fit_familiarity, save_familiarity
    from common.detector.inference import KeypointDetector
    from common.detector.weights import load_end_coefficients
    from common.bench.end_identity_bench import FIT_L2, MIN_FIT_ERRORS, collect
    from common.bench.familiarity_bench import descriptors
    new_weights = Path(new_weights)
    out_end, out_fam = new_weights.parent / "end_identity.json", new_weights.parent / "familiarity.json"
    shipped_coef = load_end_coefficients(shipped_weights)
    shipped_coef = COEF if shipped_coef is None else shipped_coef
    done: dict = {}
    folders = [fit_folder] if isinstance(fit_folder, (str, Path)) else list(fit_folder or [])
    folders = [str(f) for f in folders if Path(f).is_dir()]
    if not folders:
        Path(out_end).write_text(json.dumps({"features": list(FEATURES), "coef": [float(c) for c in shipped_coef],
                                             "fitted_on": ["shipped coefficients: no held-out groups"],
                                             "detections": 0}, indent=1) + "\n")
        log("warning: no held-out groups: the new weights keep the shipped end-identity coefficients "
            "and state no familiarity")
        return {"end_identity": "shipped", "familiarity": None}
    det = KeypointDetector(str(new_weights), device="cpu", tracking=False, threads=1, familiarity=False)
    feats = [d for d in (descriptors(f, det, progress=progress) for f in folders) if len(d)]
    feats = np.vstack(feats) if feats else np.zeros((0, 1))
    where = ", ".join(Path(f).name for f in folders)
    if len(feats) >= MIN_DETECTIONS:
        fam = fit_familiarity(feats, fitted_on=[f"{where} ({labels.split(':')[0]}, held out)"])
        save_familiarity(fam, out_fam)
        done["familiarity"] = {"detections": int(len(feats))}
    else:
        out_fam.unlink(missing_ok=True)
        done["familiarity"] = None
        log(f"warning: {len(feats)} held-out detections: no familiarity fitted")
    shipped = KeypointDetector(str(shipped_weights), device="cpu", tracking=False, threads=1)
    new, old = ({"features": np.vstack([c["features"] for c in cs]), "labels": np.concatenate([c["labels"] for c in cs])}
                for cs in ([collect(f, d, progress=progress) for f in folders] for d in (det, shipped)))
    X, y = new["features"], new["labels"]
    bound = sure_wrong(old["features"], old["labels"], shipped_coef)
    max_sure = sure_share(old["features"], shipped_coef)
    errors = int(min(np.sum(y == 0), np.sum(y == 1)))
    if len(y) >= MIN_DETECTIONS and errors >= MIN_FIT_ERRORS:
        coef = fit_coefficients(X, y, l2=FIT_L2, weights=np.full(len(y), 1000.0 / len(y)))
        how = f"fitted on {labels.split(': ')[-1]}s"
    else:
        coef = np.asarray(shipped_coef, float)
        how = (f"shipped coefficients (too few held-out detections: {len(y)})" if len(y) < MIN_DETECTIONS else
               f"shipped coefficients (the new weights read {errors} held-out detections against the "
               f"group's tip: too few to fit how sure they may be)")
    s = safe_scale(X, y, coef, bound, max_sure)
    coef = s * coef
    Path(out_end).write_text(json.dumps({
        "features": list(FEATURES), "coef": [float(c) for c in coef],
        "fitted_on": [f"{where} ({labels}; {how}; scaled {s:g})"],
        "detections": int(len(y))}, indent=1) + "\n")
    done["end_identity"] = {"how": how, "scale": s, "detections": int(len(y)),
                            "sure_wrong_new": sure_wrong(X, y, coef), "sure_wrong_shipped": bound,
                            "sure_new": sure_share(X, coef), "sure_shipped": max_sure,
                            "network_swaps_new": float(np.mean(y == 0)) if len(y) else None,
                            "network_swaps_shipped": float(np.mean(old["labels"] == 0)) if len(old["labels"]) else None}
    log(f"end identity: {how}, scaled {s:g}; on the held-out groups sure "
        f"{done['end_identity']['sure_new']:.1%} (shipped {max_sure:.1%}), surely wrong "
        f"{done['end_identity']['sure_wrong_new']:.1%} (shipped {bound:.1%})")
    return done
