"""The documented training scripts (models/train_from_scratch.sh, train_real.sh, finetune.sh) call
``needletrack`` with options its commands accept: every call is parsed by the command's own
argument parser (nothing runs), so a renamed option fails here, not 90 minutes into a run."""
import argparse
import re
import shlex
from pathlib import Path

import pytest

from common.cli import main as needletrack

pytestmark = pytest.mark.training

ROOT = Path(__file__).resolve().parents[2]
VALUES = {"DATA": "data/train", "OUT": "models/keypoint", "HERE": "models", "L": "data/train/looks",
          "C": "data/train/end_identity", "H": "data/train/held", "R": "data/train/random", "STAGE": "all", "CONFIG": "models/finetune.yaml", "INIT": "models/keypoint/model.pt",
          "TEST": "data/test", "data[@]": "--data data/mine", "extra[@]": "--support-normal 0,0,1",
          "fit[@]": "--data data/mine_fit", "grey[@]": "--grey-data data/mine_fit"}


class Parsed(Exception):
    pass


def calls(script: Path) -> list[list[str]]:
    """The script's ``needletrack`` calls (its ``gen`` shorthand expanded), as argument lists."""
    text = re.sub(r"\\\n\s*", " ", script.read_text())
    out = []
    for line in text.splitlines():
        line = line.split(" #")[0].strip().rstrip("&").strip()
        if line.startswith("gen "):
            line = "needletrack dataset generate --quiet " + line[4:]
        if not line.startswith("needletrack "):
            continue
        line = re.sub(r"\"?\$\{(\w+\[@\])\}\"?", lambda m: VALUES[m.group(1)], line)     # bash arrays
        line = re.sub(r"\$\{?(\w+)(?::-[^}]*)?\}?", lambda m: VALUES.get(m.group(1), "X"), line)
        out.append(shlex.split(line)[1:])
    return out


@pytest.mark.parametrize("script", ["train_from_scratch.sh", "train_real.sh", "finetune.sh"])
def test_every_needletrack_call_in_the_script_parses(script, monkeypatch):
    parse = argparse.ArgumentParser.parse_args

    def parse_then_stop(self, args=None, namespace=None):
        parse(self, args, namespace)   # exits (SystemExit 2) on an option the command does not take
        raise Parsed

    monkeypatch.setattr(argparse.ArgumentParser, "parse_args", parse_then_stop)
    found = calls(ROOT / "models" / script)
    assert found, f"no needletrack call found in {script}"
    for argv in found:
        with pytest.raises(Parsed):
            needletrack(argv)


def test_the_from_scratch_script_fits_the_end_identity_on_folders_it_does_not_train_on():
    found = calls(ROOT / "models/train_from_scratch.sh")
    fit = [a for a in found if a[:2] == ["bench", "end-identity"]]
    assert len(fit) == 1 and "--fit" in fit[0]
    fit_dirs = {fit[0][i + 1] for i, a in enumerate(fit[0]) if a in ("--data", "--hue-data", "--grey-data")}
    trained = {a[i + 1] for a in found if a[0] == "train" for i, x in enumerate(a) if x == "--data"}
    assert fit_dirs and not fit_dirs & trained


def test_the_from_scratch_script_fits_familiarity_on_training_looks_and_the_end_identity_on_unfamiliar_ones_too():
    """familiarity.json from folders of the training looks; the end identity's fit also sees a
    look family no training renders (`liver`) and folders read hue-turned and colourless."""
    found = calls(ROOT / "models/train_from_scratch.sh")
    fam = [a for a in found if a[:2] == ["bench", "familiarity"]]
    assert len(fam) == 1 and "--fit" in fam[0]
    fit = [a for a in found if a[:2] == ["bench", "end-identity"]][0]
    assert "--hue-data" in fit and "--grey-data" in fit
    rendered = {a[a.index("--out") + 1]: a[a.index("--randomise") + 1] for a in found
                if a[:2] == ["dataset", "generate"] and "--randomise" in a}
    fit_looks = {rendered[fit[i + 1]] for i, x in enumerate(fit) if x == "--data"}
    trained = {a[i + 1] for a in found if a[0] == "train" for i, x in enumerate(a) if x == "--data"}
    trained_looks = {rendered[d] for d in trained if d in rendered}
    assert "liver" in fit_looks and "liver" not in trained_looks and "silicone" not in trained_looks | fit_looks


def test_the_pretrained_recipe_keeps_the_held_out_families_out_of_training_and_of_every_fit():
    """models/train_real.sh: no render of the held-out families (`unseen`, `silicone`, the second
    renderer's threadless needles) anywhere; the statements' fits (familiarity, end identity, the
    presence gate) on folders no stage trains on;
    the trainer starts from models/real.yaml's pretrained trunk, with visibility."""
    import yaml
    found = calls(ROOT / "models/train_real.sh")
    looks = {a[a.index("--randomise") + 1] for a in found if "--randomise" in a}
    assert "random" in looks and not looks & {"unseen", "silicone"}
    assert not any(a[:2] == ["dataset", "generate-alt"] for a in found)
    trained = {a[i + 1] for a in found if a[0] == "train" for i, x in enumerate(a) if x == "--data"}
    fits = [a for a in found if a[0] == "bench" and "--fit" in a]
    assert sorted(a[1] for a in fits) == ["end-identity", "familiarity", "presence"]
    fit_dirs = {a[i + 1] for a in fits for i, x in enumerate(a)
                if x in ("--data", "--hue-data", "--grey-data", "--negatives")}
    assert trained and fit_dirs and not fit_dirs & trained
    model = yaml.safe_load((ROOT / "models/real.yaml").read_text())["model"]
    assert model["backbone"] == "efficientnet_lite0" and model["visibility"] is True


def test_the_pretrained_recipes_later_stage_starts_from_the_earlier_ones_weights_with_the_same_network():
    """Stage R2 trains from stage R1's weights (--init), so its network is R1's: the model sections
    of models/real.yaml and models/real_r2.yaml agree."""
    import yaml
    found = calls(ROOT / "models/train_real.sh")
    r2 = [a for a in found if a[0] == "train" and a[a.index("--config") + 1].endswith("real_r2.yaml")]
    assert len(r2) == 1 and r2[0][r2[0].index("--init") + 1].endswith("stage_r1/model.pt")
    r1_model = yaml.safe_load((ROOT / "models/real.yaml").read_text())["model"]
    assert yaml.safe_load((ROOT / "models/real_r2.yaml").read_text())["model"] == r1_model
