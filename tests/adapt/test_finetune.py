"""``needletrack finetune`` on a tiny hand-labelled folder (labels by simulated clicks through the
page's own save path, ``needletrack bench label --out``): weights the detector loads, the
calibrations beside them, a before/after report with pictures, and a run killed mid-training
that the same command resumes."""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from common.cli import dataset_main

pytestmark = pytest.mark.training
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def labelled(tmp_path_factory):
    root = tmp_path_factory.mktemp("finetune")
    truth = root / "truth"
    assert dataset_main(["generate", "--out", str(truth), "--sequences", "3", "--steps", "2", "--width", "960",
                         "--height", "540", "--seed", "7", "--randomise", "silicone", "--jobs", "1", "--quiet"]) == 0
    from common.bench.label_bench import run
    r = run(str(truth), end_px=2.0, max_frames=5, progress=False, out=str(root / "labelled"))
    assert not r["failed"]
    return root


def _config(path, epochs, steps):
    cfg = yaml.safe_load((REPO / "models" / "finetune.yaml").read_text())
    cfg["model"] = {"global_downscale": 2}        # replaced by the init weights' own
    cfg["train"].update(epochs=epochs, steps_per_epoch=steps, batch=4, global_batch=2, hard_negatives=0,
                        threads=1, warmup_steps=1)
    path.write_text(yaml.safe_dump(cfg))
    return path


def test_finetune_writes_weights_the_detector_loads_and_a_report(labelled, tmp_path):
    from common.adapt.finetune import main
    out = tmp_path / "out"
    args = ["--labels", str(labelled / "labelled"), "--out", str(out), "--config",
            str(_config(tmp_path / "tiny.yaml", 1, 2)), "--rehearse", "2", "--hold-out", "0.34", "--quiet"]
    assert main(args) == 0
    split = json.loads((out / "labels" / "split.json").read_text())
    # 5 of 6 frames labelled (the 6th is never a target), whole takes of 2 held out
    train = sum(len(s["frames"]) for s in split["train"])
    held = sum(len(s["frames"]) for s in split["heldout"])
    assert train + held == 5 and held in (2, 3) and train >= 2
    assert split["folders"][str(labelled / "labelled")]["unlabelled"] == 1
    from common.detector.backends import load_backend
    from common.data.dataset import Dataset
    det = load_backend("learned", {"weights": str(out / "model.pt")})
    ds = Dataset(str(labelled / "labelled"))
    det.detect(ds.image(0, "left"), "left", None, None)
    assert (out / "end_identity.json").is_file()
    cal = json.loads((out / "end_identity.json").read_text())
    assert "hand labels" in cal["fitted_on"][0]
    rep = json.loads((out / "report" / "report.json").read_text())
    for side in ("before", "after"):
        s = rep[side]
        assert s["images_with_needle"] >= 2 and 0 <= s["found"] <= s["images_with_needle"]
        assert s["found"] == 0 or s["keypoint_px"]["mean"] >= 0
    assert rep["held_out_frames"] == held
    assert rep["worst"] and all((out / "report" / w["picture"]).is_file() for w in rep["worst"])
    md = (out / "report" / "report.md").read_text()
    assert "| images with a needle: found |" in md and "## Label next" in md
    assert [x["frame"] for x in rep["label_next"]] == [5]          # the one unlabelled frame
    import torch
    meta = torch.load(out / "model.pt", map_location="cpu", weights_only=True)
    init = torch.load(REPO / "models" / "keypoint" / "model.pt", map_location="cpu", weights_only=True)
    from common.detector.model import ModelConfig
    # the init network's own, not the YAML's (global_downscale 2)
    assert ModelConfig.from_dict(meta["config"]) == ModelConfig.from_dict(init["config"])
    assert meta["meta"]["data"][-1] == str(out / "rehearsal")


def test_a_killed_finetune_resumes(labelled, tmp_path):
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "common.cli", "finetune", "--labels", str(labelled / "labelled"), "--out", str(out),
           "--config", str(_config(tmp_path / "tiny.yaml", 40, 1)), "--rehearse", "0", "--hold-out", "0.34",
           "--quiet"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    p = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    ck = out / "train" / "checkpoint.pt"
    deadline = time.monotonic() + 300
    while not ck.is_file() and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert p.poll() is None, p.stdout.read().decode()[-2000:]
    p.send_signal(signal.SIGKILL)
    p.wait()
    assert not (out / "train" / "done.json").exists()
    split = (out / "labels" / "split.json").stat().st_mtime_ns
    r = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "resuming from" in r.stdout
    assert (out / "labels" / "split.json").stat().st_mtime_ns == split      # the split is kept
    last = json.loads((out / "train" / "done.json").read_text())
    assert last["epoch"] == 40 and (out / "report" / "report.json").is_file()
