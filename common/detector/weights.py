"""The keypoint network's weights file: loading (``torch.load(..., weights_only=True)``, never a
pickle of code), its format check, the end-identity coefficients fitted for it, and the device.
A missing, corrupt or mismatched file raises ``ModelFileError`` saying how to retrain."""
from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import torch

from common.detector.end_identity import FEATURE_SETS, FEATURES
from common.detector.model import (
    KeypointModel,
    ModelConfig,
    fuse_conv_bn,
)
from common.errors import NeedletrackError

MODEL_FORMAT = "needletrack-keypoint-detector"
MODEL_VERSION = 1
REPO = Path(__file__).resolve().parents[2]
DEFAULT_WEIGHTS = REPO / "models" / "keypoint" / "model.pt"
RETRAIN = ("retrain with `needletrack train --data DATASET --config models/train.yaml "
           "--out models/keypoint` (models/README.md gives the full recipe)")
def load_end_coefficients(weights) -> np.ndarray | None:
    """The end-identity coefficients fitted for these weights (``end_identity.json`` beside
    them; ``needletrack bench end-identity --fit``), or None: then no end identity is stated."""
    path = Path(weights or DEFAULT_WEIGHTS).with_name("end_identity.json")
    if not path.is_file():
        return None
    try:
        coef = np.asarray(json.loads(path.read_text())["coef"], float)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ModelFileError(f"{path}: not an end-identity coefficient file ({exc})") from None
    if coef.ndim != 1 or len(coef) not in FEATURE_SETS or not np.isfinite(coef).all():
        raise ModelFileError(f"{path}: coef must be {' or '.join(map(str, FEATURE_SETS))} finite numbers "
                             f"({', '.join(FEATURES)}), got {coef.tolist()}")
    return coef


class ModelFileError(NeedletrackError, RuntimeError):
    """A weights file that is missing, unreadable or made for another model."""


def load_model(path=None, device="cpu") -> tuple[KeypointModel, dict]:
    """(model in eval mode with BN folded, the file's meta) from a weights file."""
    path = Path(path or DEFAULT_WEIGHTS)
    if not path.is_file():
        raise ModelFileError(f"{path}: no such weights file; {RETRAIN}")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)    # never unpickles code
    except pickle.UnpicklingError as exc:  # a pickle of objects other than tensors and plain data
        first = " ".join(str(exc).split())[:200]
        raise ModelFileError(f"{path}: refused: the file holds pickled Python objects that a weights "
                             f"file does not (torch.load weights_only: {first}); not loaded; {RETRAIN}") from None
    except Exception as exc:  # zip errors of a truncated or foreign file
        first = str(exc).split(". ")[0][:160]
        raise ModelFileError(f"{path}: not a readable weights file, truncated or corrupt "
                             f"({type(exc).__name__}: {first}); {RETRAIN}") from None
    if not isinstance(blob, dict) or blob.get("format") != MODEL_FORMAT:
        raise ModelFileError(f"{path}: not a needletrack keypoint-detector weights file "
                             f"(format {blob.get('format') if isinstance(blob, dict) else type(blob).__name__!r}); {RETRAIN}")
    if blob.get("version") != MODEL_VERSION:
        raise ModelFileError(f"{path}: weights format version {blob.get('version')!r}, this code reads "
                             f"version {MODEL_VERSION}; {RETRAIN}")
    try:
        cfg = ModelConfig.from_dict(dict(blob["config"]))
        model = KeypointModel(cfg)
        model.load_state_dict(blob["state_dict"], strict=True)
        model.eval()
        fuse_conv_bn(model)
        meta = dict(blob.get("meta") or {})
    except Exception as exc:      # any field of the wrong kind: the file, not the code, is wrong
        why = " ".join(str(exc).split())[:300]
        raise ModelFileError(f"{path}: weights do not match the network ({type(exc).__name__}: {why}); "
                             f"{RETRAIN}") from None
    model = model.to(device=device, memory_format=torch.channels_last)
    return model, meta


def pick_device(device: str = "auto") -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} asked for, but CUDA is not available")
    return torch.device(device)
