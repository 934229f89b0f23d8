"""models/finetune.sh, the documented adaptation recipe: fine-tunes the shipped weights on a
folder and scores the shipped and the fine-tuned weights on a test folder (a short schedule here;
the recipe's own is models/finetune.yaml)."""
import pytest
import json
import os
import subprocess
import sys
from pathlib import Path

import yaml

import common.sim.render  # noqa: F401  (headless GL before mujoco)
from common.detector.end_identity import FEATURES
from common.detector.weights import load_end_coefficients
from common.sim.generate import GenerateConfig, generate

pytestmark = pytest.mark.training

ROOT = Path(__file__).resolve().parents[2]


def test_finetune_recipe_trains_fits_the_end_identity_then_scores_before_and_after(tmp_path):
    train_dir, test_dir, fit_dir = tmp_path / "train", tmp_path / "test", tmp_path / "fit"
    generate(train_dir, GenerateConfig(3, 1, 11, "wide", thread="none", msaa=0), progress=False)
    generate(test_dir, GenerateConfig(2, 2, 12, "wide", thread="none", msaa=0), progress=False)
    generate(fit_dir, GenerateConfig(2, 1, 13, "wide", thread="none", msaa=0), progress=False)
    cfg = yaml.safe_load((ROOT / "models/finetune.yaml").read_text())
    cfg["train"].update(epochs=1, steps_per_epoch=3, batch=4, global_batch=2, warmup_steps=1,
                        val_fraction=0.0, hard_negatives=0, threads=1)
    (tmp_path / "short.yaml").write_text(yaml.safe_dump(cfg))
    env = dict(os.environ, CONFIG=str(tmp_path / "short.yaml"), SUPPORT_NORMAL="0,0,1", FIT=str(fit_dir),
               PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    out = tmp_path / "out"
    out.mkdir()
    (out / "end_identity.json").write_text("stale: fitted for other weights")
    run = subprocess.run(["bash", str(ROOT / "models/finetune.sh"), str(out), str(test_dir), str(train_dir)],
                         env=env, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    assert (out / "model.pt").is_file()
    fitted = json.loads((out / "end_identity.json").read_text())      # the stale file replaced
    # folder names, not the machine's paths; the fit folder also read without colour
    assert fitted["fitted_on"] == [fit_dir.name, f"{fit_dir.name}@grey"] and len(fitted["coef"]) == len(FEATURES)
    assert "too few for a familiarity reference" in run.stderr          # 2 frames: said, not fitted
    assert not (out / "familiarity.json").exists()
    assert load_end_coefficients(out / "model.pt") is not None
    assert "too few of one kind to learn how sure" in run.stderr        # a 2-frame fit folder says so
    assert "== before" in run.stdout and "== after" in run.stdout
    for label in ("before", "after"):
        res = json.loads((out / f"eval_{label}" / "results.json").read_text())
        assert res["frames"] == 4 and "refined" in res["pose"]
    assert json.loads((out / "eval_before/results.json").read_text())["detector"]


def test_finetune_recipe_explains_itself_without_arguments():
    run = subprocess.run(["bash", str(ROOT / "models/finetune.sh")], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and "TRAIN_DIR" in run.stdout
