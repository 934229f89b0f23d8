"""The keypoint network's pieces: targets, loss, sub-pixel decoding, crops, BN folding."""
import numpy as np
import pytest
import torch

from common.detector.model import (
    FrozenForInference,
    KeypointModel,
    ModelConfig,
    apply_affine,
    centreline_target,
    crop_affine,
    decode_global,
    decode_heatmaps,
    fuse_conv_bn,
    gaussian_targets,
    global_size,
    invert_affine,
    keypoint_loss,
)


@pytest.mark.parametrize("stride", [1, 2])
def test_decode_recovers_subpixel_peak_of_the_trained_target(stride):
    m = 32
    rng = np.random.default_rng(0)
    uv = torch.tensor(rng.uniform(3, m - 4, (2, 5, 2)), dtype=torch.float32)
    t = gaussian_targets(uv, torch.ones(2, 5), m, 1.5)
    logits = torch.log(t.clamp_min(1e-30))   # a network that predicts exactly the target
    got, score = decode_heatmaps(logits, stride)
    want = uv * stride + (stride - 1) / 2
    assert torch.allclose(got, want, atol=1e-3)
    assert torch.all(score > 0.7)


def test_keypoint_loss_is_zero_at_the_target_and_positive_elsewhere():
    m = 16
    uv = torch.tensor([[[5.3, 7.8], [10.1, 2.2], [8, 8], [1, 1], [14, 3]]])
    w = torch.tensor([[1.0, 1.0, 0.3, 0.0, 1.0]])
    t = gaussian_targets(uv, w, m, 1.5)
    assert torch.allclose(t.sum((-2, -1)), w, atol=1e-5)
    good = torch.log(gaussian_targets(uv, torch.ones(1, 5), m, 1.5).clamp_min(1e-30))
    assert float(keypoint_loss(good, t)) == pytest.approx(0.0, abs=1e-4)
    assert float(keypoint_loss(torch.zeros(1, 5, m, m), t)) > 1.0


def test_centreline_target_peaks_on_the_polyline():
    poly = np.array([[4.0, 10.0], [20.0, 10.0]])
    t = centreline_target([poly, None], 32, 1.0)
    assert t.shape == (2, 32, 32)
    assert float(t[0, 10, 12]) > 0.9 and float(t[0, 20, 12]) < 1e-3
    assert float(t[1].max()) == 0.0


def test_centreline_target_breaks_where_the_arc_is_unseen():
    # a jaw over the middle: the seen runs get a ridge, the chord across the gap none
    poly = np.array([[4.0, 10.0], [8.0, 10.0], [np.nan, np.nan], [np.nan, np.nan], [20.0, 10.0], [26.0, 10.0]])
    t = centreline_target([poly], 32, 1.0)[0]
    assert float(t[10, 6]) > 0.9 and float(t[10, 23]) > 0.9
    assert float(t[10, 14]) < 1e-3
    lone = np.array([[4.0, 10.0], [np.nan, np.nan], [20.0, 10.0]])   # no run of two points
    assert float(centreline_target([lone], 32, 1.0)[0].max()) == 0.0


def test_crop_affine_round_trip_and_centre():
    M = crop_affine(500.0, 300.0, 100.0, 128, angle_rad=0.7, flip=True)
    p = np.array([[500.0, 300.0], [480.5, 333.25]])
    q = apply_affine(M, p)
    assert np.allclose(q[0], [63.5, 63.5])
    assert np.allclose(apply_affine(invert_affine(M), q), p)


def test_fused_model_matches_the_unfused_one():
    torch.manual_seed(0)
    model = KeypointModel(ModelConfig(crop=64))
    for mod in model.modules():   # non-trivial batch-norm statistics
        if isinstance(mod, torch.nn.BatchNorm2d):
            mod.running_mean.uniform_(-0.2, 0.2)
            mod.running_var.uniform_(0.5, 2.0)
            mod.weight.data.uniform_(0.5, 1.5)
    model.eval()
    x = torch.randint(0, 256, (2, 3, 64, 64), dtype=torch.uint8)
    g = torch.randint(0, 256, (1, 3, 48, 80), dtype=torch.uint8)
    with torch.no_grad():
        h0, p0 = model.crop(x)
        g0 = model.glob(g)
        fuse_conv_bn(model)
        h1, p1 = model.crop(x)
        g1 = model.glob(g)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules())
    assert torch.allclose(h0, h1, atol=1e-4) and torch.allclose(p0, p1, atol=1e-4)
    assert torch.allclose(g0, g1, atol=1e-4)


def test_frozen_networks_match_the_modules_per_shape_and_fall_back():
    torch.manual_seed(1)
    model = fuse_conv_bn(KeypointModel(ModelConfig(crop=64)).eval())
    crop, glob = FrozenForInference(model.crop), FrozenForInference(model.glob)
    with torch.inference_mode():
        for shape in ((1, 3, 64, 64), (2, 3, 64, 64)):
            x = torch.randint(0, 256, shape, dtype=torch.uint8)
            for a, b in zip(crop(x), model.crop(x)):
                assert torch.allclose(a, b, atol=1e-5)
        for shape in ((1, 3, 48, 80), (1, 3, 64, 120)):   # one trace per image size
            g = torch.randint(0, 256, shape, dtype=torch.uint8)
            assert torch.allclose(glob(g), model.glob(g), atol=1e-5)
    assert len(crop._traced) == 2 and len(glob._traced) == 2
    assert all(isinstance(n, torch.jit.ScriptModule) for n in crop._traced.values())

    class Untraceable(torch.nn.Module):
        def forward(self, x):
            return {"n": int(x.sum())}   # data-dependent Python value: tracing fails

    net = FrozenForInference(Untraceable())
    assert net(torch.ones(2, 2)) == {"n": 4}


def test_output_shapes_and_global_decoding():
    cfg = ModelConfig()
    model = KeypointModel(cfg).eval()
    with torch.no_grad():
        heat, pres = model.crop(torch.zeros(3, 3, cfg.crop, cfg.crop, dtype=torch.uint8))
        g = model.glob(torch.zeros(1, 3, 136, 240, dtype=torch.uint8))
    assert heat.shape == (3, 6, cfg.heat, cfg.heat) and pres.shape == (3,)
    assert g.shape == (1, 5, 34, 60)
    out = torch.full((1, 5, 34, 60), -10.0)
    out[0, 0, 12, 20] = 3.0
    out[0, 1:5, 12, 20] = torch.tensor([0.0, np.log(2.0), 0.25, -0.25])
    conf, cx, cy, w, h = decode_global(out, 8)
    assert conf > 0.9
    assert (cx, cy) == pytest.approx(((20 + 0.25) * 32 + 15.5, (12 - 0.25) * 32 + 15.5))
    assert (w, h) == pytest.approx((64.0, 128.0))


def test_model_config_rejects_unknown_fields():
    with pytest.raises(ValueError, match="unknown field"):
        ModelConfig.from_dict({"crop": 128, "widht": 3})


def test_a_perfect_heatmap_scores_one_after_normalisation():
    from common.detector.arc_fit import ideal_peak_mass
    from common.detector.model import decode_heatmaps, gaussian_targets
    sigma = 1.5
    t = gaussian_targets(torch.tensor([[[30.0, 41.0]]]), torch.ones(1, 1), 64, sigma)
    _, score = decode_heatmaps(torch.log(t.clamp_min(1e-30)), 1)
    assert float(score[0, 0]) / ideal_peak_mass(sigma) == pytest.approx(1.0, abs=1e-3)
    flat = torch.zeros(1, 1, 64, 64)                       # no peak at all
    _, score = decode_heatmaps(flat, 1)
    assert float(score[0, 0]) / ideal_peak_mass(sigma) < 0.01


def test_stage1_sees_any_image_size_at_the_reference_scale():
    cfg = ModelConfig(global_downscale=4)
    assert global_size(cfg, 1920, 1080) == (480, 270, 4.0, 1.0)
    ws, hs, ds, box_scale = global_size(cfg, 640, 480)     # same field of view, a third of the pixels
    assert (ws, hs) == (480, 360) and ds == pytest.approx(4 / 3) and box_scale == pytest.approx(1 / 3)
    assert global_size(cfg, 320, 240)[:3] == (320, 240, 1.0)  # never upscaled
    # a box decoded at 640x480 is in that image's pixels: a third of the 1920 px one
    out = torch.full((1, 5, 34, 60), -10.0)
    out[0, 0, 12, 20] = 3.0
    out[0, 1:5, 12, 20] = torch.tensor([0.0, 0.0, 0.0, 0.0])
    _, cx, _, w, _ = decode_global(out, ds, box_scale)
    assert w == pytest.approx(64.0 / 3) and cx == pytest.approx(20 * 4 * ds + (4 * ds - 1) / 2)
