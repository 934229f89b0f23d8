"""The learned needle detector's two networks, their losses, and decoding to sub-pixel keypoints.

Single instance, two stages, in Keypoint R-CNN's spirit:

- ``GlobalNet`` sees the whole image downscaled by ``global_downscale`` (8: 1920x1080 -> 240x135,
  BGR, cv2.INTER_AREA) and predicts, per cell of ``GLOBAL_STRIDE`` small pixels, a needle-centre
  logit (CenterNet-style heatmap, whose peak sigmoid is the presence confidence), the box size
  (log of w, h in full-resolution pixels / ``BOX_UNIT``) and the sub-cell centre offset.
- ``CropNet`` sees a square full-resolution crop around the box, warped to ``crop`` x ``crop``
  pixels, and predicts 5 keypoint heatmaps A..E (each a softmax over all crop positions, trained
  with cross-entropy as Keypoint R-CNN's keypoint loss, against a Gaussian soft target so that the
  log-probability is a quadratic whose vertex is the sub-pixel position), one centreline heatmap
  (sigmoid: the projected arc as a thin ridge), and a needle-presence logit.

Pixel conventions are OpenCV's: integer coordinates are pixel centres. Heatmaps have one cell per
crop pixel (``out_stride`` 1, via a pixel-shuffle head) or per 2 crop pixels (``out_stride`` 2);
cell (i, j) is centred on crop pixel ``(j * s + (s - 1) / 2, i * s + (s - 1) / 2)``.
"""
from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

N_KP = 5
GLOBAL_STRIDE = 4      # GlobalNet output cell = 4 small pixels
BOX_UNIT = 64.0        # box sizes are regressed as log(size_px / (BOX_UNIT * box scale))
REFERENCE_WIDTH = 1920  # px: stage 1 downscales an image this wide by exactly ``global_downscale``


@dataclass
class ModelConfig:
    """Architecture hyperparameters; stored inside the weights file."""

    global_downscale: int = 8
    global_widths: tuple = (16, 32, 48)
    crop: int = 128
    crop_widths: tuple = (16, 32, 48, 80)
    out_stride: int = 1
    kp_sigma: float = 1.5          # target Gaussian sigma, in heatmap cells
    line_sigma: float = 1.0        # centreline ridge sigma, in heatmap cells
    crop_margin: float = 1.45      # crop side = crop_margin * max(box w, h) + crop_pad px
    crop_pad: float = 12.0
    crop_min: float = 56.0         # smallest crop side, px
    backbone: str = ""             # "": both networks from scratch; "efficientnet_lite0": stage 2's encoder
                                   # is that ImageNet-pretrained trunk (``common.detector.backbone``)
    backbone_cut: int = 16         # the stage-2 trunk's deepest stride (8 or 16)
    backbone_frozen: int = 0       # the trunks' stem and first blocks kept as pretrained (3: all at strides 2, 4)
    global_backbone: bool = False  # stage 1 on the same pretrained trunk, cut at stride 8
    visibility: bool = False       # 5 more heatmap channels: per-keypoint visibility logits (``visibility_logits``)

    def to_dict(self) -> dict:
        d = asdict(self)
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        known = {f for f in cls.__dataclass_fields__}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"model config: unknown field(s) {sorted(unknown)}")
        kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()}
        return cls(**kw)

    @property
    def heat(self) -> int:
        """Heatmap side in cells."""
        return self.crop // self.out_stride

    @property
    def heat_channels(self) -> int:
        """Stage 2's heatmap channels: A..E, the centreline, and A..E's visibility if ``visibility``."""
        return N_KP + 1 + (N_KP if self.visibility else 0)

    @property
    def descriptor_size(self) -> int:
        """Length of stage 2's crop descriptor (``CropNet.forward_features``)."""
        if self.backbone:
            from common.detector.backbone import LEVELS
            return 2 * (LEVELS[4] + LEVELS[8] + LEVELS[self.backbone_cut])
        return 2 * sum(self.crop_widths[1:])


def cbr(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    """3x3 conv + batch norm + ReLU (fused into one conv for inference by ``fuse_conv_bn``)."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


def _normalise(x: torch.Tensor) -> torch.Tensor:
    """uint8 (or 0..255 float) NCHW BGR -> float in [-0.5, 0.5]."""
    return x.float() * (1.0 / 255.0) - 0.5


class GlobalNet(nn.Module):
    """Stage 1 on the downscaled image: (N, 5, H/4, W/4) = centre logit, log w, log h, dx, dy."""

    def __init__(self, widths=(16, 32, 48)):
        super().__init__()
        w0, w1, w2 = widths
        self.s1 = nn.Sequential(cbr(3, w0, 2), cbr(w0, w0))                      # /2
        self.s2 = nn.Sequential(cbr(w0, w1, 2), cbr(w1, w1))                     # /4
        self.s3 = nn.Sequential(cbr(w1, w2, 2), cbr(w2, w2, dilation=2),
                                cbr(w2, w2, dilation=4))                           # /8
        self.lat = nn.Conv2d(w1, w2, 1)
        self.fuse = cbr(w2, w2)
        self.head = nn.Conv2d(w2, 5, 1)
        nn.init.constant_(self.head.bias, 0.0)
        with torch.no_grad():
            self.head.bias[0] = -4.0   # start with "no needle anywhere"

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = _normalise(x)
        b = self.s2(self.s1(x))
        c = self.s3(b)
        f = self.fuse(F.interpolate(c, size=b.shape[-2:], mode="nearest") + self.lat(b))
        return self.head(f)


class UNetCropHeads(nn.Module):
    """What both stage-2 networks put on their encoder's features at strides 2, 4, 8 and the deepest
    (16, or 8 when the encoder stops there): a U-Net decoder to the heatmaps, the presence logit on
    the deepest features' mean and max, and the crop's descriptor. Its layers are attributes of the
    network itself (the weights files' keys: ``d3``, ``l4``, ``head``, ``presence`` ...)."""

    def build_heads(self, w0: int, w1: int, w2: int, w3: int, n_out: int, out_stride: int,
                    deepest_stride: int = 16) -> None:
        self.out_stride = out_stride
        self.l4 = nn.Conv2d(w3, w2, 1) if deepest_stride == 16 else None
        self.d3 = cbr(w2, w2)
        self.l3 = nn.Conv2d(w2, w1, 1)
        self.d2 = cbr(w1, w1)
        self.l2 = nn.Conv2d(w1, w0, 1)
        self.d1 = cbr(w0, w0)
        self.head = heatmap_head(w0, n_out, out_stride)
        self.presence = nn.Linear(2 * w3, 1)

    def heads(self, a, b, c, d):
        """(heatmaps, presence logit, descriptor) from the features at strides 2, 4, 8 and the
        deepest. The descriptor (``common.detector.familiarity``): the spatial mean and standard
        deviation of the stride 4 and 8 features (the look: colour, light, texture) and the deepest
        features' mean and max (what the presence head reads)."""
        deep = torch.cat([d.mean((2, 3)), d.amax((2, 3))], 1)
        pres = self.presence(deep)[:, 0]
        feat = torch.cat([b.mean((2, 3)), b.std((2, 3)), c.mean((2, 3)), c.std((2, 3)), deep], 1)
        u = c if self.l4 is None else c + F.interpolate(self.l4(d), scale_factor=2.0, mode="nearest")
        u = self.d3(u)
        u = self.d2(F.interpolate(self.l3(u), scale_factor=2.0, mode="nearest") + b)
        u = self.d1(F.interpolate(self.l2(u), scale_factor=2.0, mode="nearest") + a)
        return self.head(u), pres, feat

    def forward(self, x: torch.Tensor):
        heat, pres, _ = self.forward_features(x)
        return heat, pres


class CropNet(UNetCropHeads):
    """Stage 2 on the crop: heatmaps (N, 6, m, m) = 5 keypoint logits + centreline logit,
    and the presence logit (N,)."""

    def __init__(self, widths=(16, 32, 48, 80), out_stride: int = 1, n_out: int = N_KP + 1):
        super().__init__()
        w0, w1, w2, w3 = widths
        self.e1 = nn.Sequential(cbr(3, w0, 2), cbr(w0, w0))                      # /2
        self.e2 = nn.Sequential(cbr(w0, w1, 2), cbr(w1, w1))                     # /4
        self.e3 = nn.Sequential(cbr(w1, w2, 2), cbr(w2, w2))                     # /8
        self.e4 = nn.Sequential(cbr(w2, w3, 2), cbr(w3, w3, dilation=2))         # /16
        self.build_heads(w0, w1, w2, w3, n_out, out_stride)

    def forward_features(self, x: torch.Tensor):
        """(heatmaps, presence logit, the crop's descriptor (N, 2 (w1 + w2 + w3)); ``UNetCropHeads.heads``)."""
        a = self.e1(_normalise(x))
        b = self.e2(a)
        c = self.e3(b)
        return self.heads(a, b, c, self.e4(c))


def heatmap_head(cin: int, n_out: int, out_stride: int) -> nn.Module:
    """Stride-2 features -> ``n_out`` heatmaps at crop resolution (``out_stride`` 1: a pixel shuffle
    learns the sub-cell structure) or at stride 2."""
    if out_stride == 1:
        return nn.Sequential(nn.Conv2d(cin, n_out * 4, 1), nn.PixelShuffle(2))
    if out_stride == 2:
        return nn.Conv2d(cin, n_out, 3, padding=1)
    raise ValueError(f"out_stride must be 1 or 2, got {out_stride}")


class PretrainedCropNet(UNetCropHeads):
    """Stage 2 on EfficientNet-Lite0's ImageNet-pretrained trunk (``common.detector.backbone``) cut at
    stride ``cut``, with a U-Net decoder over its stride 8, 4 and 2 features; the same outputs as
    ``CropNet`` (heatmaps, presence logit, descriptor)."""

    def __init__(self, out_stride: int = 1, n_out: int = N_KP + 1, cut: int = 16, frozen: int = 0):
        super().__init__()
        from common.detector.backbone import LEVELS, EfficientLiteTrunk
        if cut not in (8, 16):
            raise ValueError(f"backbone_cut must be 8 or 16, got {cut}")
        self.cut = cut
        self.trunk = EfficientLiteTrunk(cut, frozen)
        self.build_heads(LEVELS[2], LEVELS[4], LEVELS[8], LEVELS[cut], n_out, out_stride, cut)

    def forward_features(self, x: torch.Tensor):
        """(heatmaps, presence logit, descriptor; ``UNetCropHeads.heads``) on the trunk's features."""
        from common.detector.backbone import normalise
        f = self.trunk(normalise(x))
        return self.heads(f[2], f[4], f[8], f[self.cut])


class PretrainedGlobalNet(nn.Module):
    """Stage 1 on EfficientNet-Lite0's pretrained trunk cut at stride 8: its stride-8 features, up-sampled
    onto the stride-4 ones, give ``GlobalNet``'s output (N, 5, H/4, W/4)."""

    def __init__(self, frozen: int = 0):
        super().__init__()
        from common.detector.backbone import LEVELS, EfficientLiteTrunk
        self.trunk = EfficientLiteTrunk(8, frozen)
        self.lat = nn.Conv2d(LEVELS[4], LEVELS[8], 1)
        self.fuse = cbr(LEVELS[8], LEVELS[8])
        self.head = nn.Conv2d(LEVELS[8], 5, 1)
        nn.init.constant_(self.head.bias, 0.0)
        with torch.no_grad():
            self.head.bias[0] = -4.0   # start with "no needle anywhere"

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        from common.detector.backbone import normalise
        f = self.trunk(normalise(x))
        b, c = f[4], f[8]
        return self.head(self.fuse(F.interpolate(c, size=b.shape[-2:], mode="nearest") + self.lat(b)))


class CropWithFeatures(nn.Module):
    """A ``CropNet`` that also returns its descriptor (``CropNet.forward_features``), for tracing."""

    def __init__(self, crop: CropNet):
        super().__init__()
        self.crop = crop

    def forward(self, x: torch.Tensor):
        return self.crop.forward_features(x)


class KeypointModel(nn.Module):
    """Both stages plus their configuration (what a weights file holds)."""

    def __init__(self, cfg: ModelConfig | None = None):
        super().__init__()
        self.cfg = cfg or ModelConfig()
        if self.cfg.crop % 16:
            raise ValueError(f"crop must be a multiple of 16, got {self.cfg.crop}")
        c = self.cfg
        if c.backbone not in ("", "efficientnet_lite0"):
            raise ValueError(f"backbone must be '' or 'efficientnet_lite0', got {c.backbone!r}")
        if c.global_backbone and not c.backbone:
            raise ValueError("global_backbone needs backbone: efficientnet_lite0")
        self.glob = PretrainedGlobalNet(c.backbone_frozen) if c.global_backbone else GlobalNet(c.global_widths)
        self.crop = (PretrainedCropNet(c.out_stride, c.heat_channels, c.backbone_cut, c.backbone_frozen) if c.backbone
                     else CropNet(c.crop_widths, c.out_stride, c.heat_channels))

    def load_pretrained(self) -> dict:
        """ImageNet weights into the pretrained trunks (training from scratch starts here); returns the
        provenance to store in the weights file's meta. A no-op returning {} without a backbone."""
        if not self.cfg.backbone:
            return {}
        from common.detector.backbone import load_imagenet
        info = load_imagenet(self.crop.trunk)
        if self.cfg.global_backbone:
            load_imagenet(self.glob.trunk)
        return info


# ---------------------------------------------------------------- inference-time fusion

def fuse_conv_bn(module: nn.Module) -> nn.Module:
    """Fold every Conv2d followed by BatchNorm2d (inside an nn.Sequential) into one conv, in place.
    Only valid in eval mode; speeds up CPU inference."""
    for name, child in module.named_children():
        if isinstance(child, nn.Sequential):
            setattr(module, name, _fuse_sequence(child))
        else:
            fuse_conv_bn(child)
    return module


class FrozenForInference:
    """A module's TorchScript trace, frozen (weights as constants, conv + activation fused by
    the JIT: 10-20% faster for both networks on the CPU, outputs unchanged), traced once per
    input shape; the module itself wherever tracing fails. Eval mode, no gradients.

    ``torch.jit`` is deprecated in favour of ``torch.compile``, which needs a C++ toolchain and
    minutes of compilation on a 2-core CPU; should a later torch drop the JIT, the fallback
    runs the module as it is."""

    def __init__(self, module: nn.Module, max_shapes: int = 4):
        self.module, self.max_shapes = module, max_shapes
        self._traced: dict = {}

    def __call__(self, x: torch.Tensor):
        key = (tuple(x.shape), x.dtype, x.device)
        net = self._traced.get(key)
        if net is None:
            net = self.module
            if len(self._traced) < self.max_shapes:
                try:
                    with torch.inference_mode(), warnings.catch_warnings():
                        warnings.simplefilter("ignore", DeprecationWarning)
                        warnings.simplefilter("ignore", torch.jit.TracerWarning)   # shapes: per-shape traces
                        net = torch.jit.freeze(torch.jit.trace(self.module, x, check_trace=False))
                except Exception:   # noqa: BLE001 -- any tracing failure: run the module eagerly
                    net = self.module
                self._traced[key] = net
        return net(x)


def _fuse_sequence(seq: nn.Sequential) -> nn.Sequential:
    items = list(seq)
    out, i = [], 0
    while i < len(items):
        m = items[i]
        if isinstance(m, nn.Conv2d) and i + 1 < len(items) and isinstance(items[i + 1], nn.BatchNorm2d):
            out.append(_fold(m, items[i + 1]))
            i += 2
            continue
        out.append(_fuse_sequence(m) if isinstance(m, nn.Sequential) else fuse_conv_bn(m))
        i += 1
    return nn.Sequential(*out)


def _fold(conv: nn.Conv2d, bn: nn.BatchNorm2d) -> nn.Conv2d:
    fused = nn.Conv2d(conv.in_channels, conv.out_channels, conv.kernel_size, conv.stride,
                      conv.padding, conv.dilation, conv.groups, bias=True)
    scale = bn.weight.detach() / torch.sqrt(bn.running_var + bn.eps)
    fused.weight.data = conv.weight.detach() * scale[:, None, None, None]
    b0 = conv.bias.detach() if conv.bias is not None else torch.zeros_like(bn.running_mean)
    fused.bias.data = (b0 - bn.running_mean) * scale + bn.bias.detach()
    return fused


# ---------------------------------------------------------------- targets and losses

def gaussian_targets(uv_cells: torch.Tensor, valid: torch.Tensor, m: int, sigma) -> torch.Tensor:
    """Soft targets (N, K, m, m): a Gaussian of ``sigma`` cells (a float, or (N, K) per keypoint)
    centred on ``uv_cells`` (N, K, 2) = (x, y) in cell coordinates, summing to ``valid`` (N, K): a
    weight, 0 for no target."""
    g = torch.arange(m, dtype=torch.float32, device=uv_cells.device)
    if torch.is_tensor(sigma):
        sigma = sigma[..., None].float()
    gx = torch.exp(-0.5 * ((g[None, None, :] - uv_cells[..., 0:1]) / sigma) ** 2)   # N,K,m
    gy = torch.exp(-0.5 * ((g[None, None, :] - uv_cells[..., 1:2]) / sigma) ** 2)
    t = gy[..., :, None] * gx[..., None, :]
    t = t / t.sum((-2, -1), keepdim=True).clamp_min(1e-12)
    return t * valid[..., None, None].float()


def keypoint_loss(logits: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Keypoint R-CNN's keypoint loss with soft labels: cross-entropy of an m*m-way softmax per
    keypoint. A target sums to the keypoint's weight (1, less for an occluded point, 0 for none);
    the loss is the weighted mean over keypoints."""
    n, k = logits.shape[:2]
    logp = F.log_softmax(logits.reshape(n, k, -1), dim=-1)
    t = targets.reshape(n, k, -1)
    w = t.sum(-1)
    ce = -(t * logp).sum(-1)
    # subtract the (weighted) target entropy so that a perfect prediction scores 0 (same gradients)
    tn = t / w[..., None].clamp_min(1e-12)
    ent = -(t * torch.log(tn.clamp_min(1e-12))).sum(-1)
    return (ce - ent).sum() / w.sum().clamp_min(1e-6)


def centreline_target(polys_cells: list, m: int, sigma: float) -> torch.Tensor:
    """(N, m, m) ridge targets exp(-d^2 / 2 sigma^2), d = distance (cells) to each polyline.

    ``polys_cells``: per sample an (P, 2) float array of the projected arc in cell coordinates,
    NaN rows where it is not seen (the ridge breaks there: no chord across a jaw), or None for no
    needle. Computed with OpenCV's distance transform on a 2x supersampled raster of the
    polyline's seen runs."""
    import cv2
    ss = 2
    out = np.zeros((len(polys_cells), m, m), np.float32)
    for i, poly in enumerate(polys_cells):
        if poly is None:
            continue
        poly = np.asarray(poly, float)
        ok = np.isfinite(poly).all(1)
        runs = [r for r in np.split(np.arange(len(poly)), np.flatnonzero(np.diff(ok.astype(int))) + 1)
                if ok[r[0]] and len(r) >= 2]
        if not runs:
            continue
        canvas = np.full((m * ss, m * ss), 255, np.uint8)
        pts = [np.round((poly[r] + 0.5) * ss - 0.5).astype(np.int32).reshape(-1, 1, 2) for r in runs]
        cv2.polylines(canvas, pts, False, 0, 1, cv2.LINE_8)
        d = cv2.distanceTransform(canvas, cv2.DIST_L2, 5) / ss
        d = cv2.resize(d, (m, m), interpolation=cv2.INTER_AREA)
        out[i] = np.exp(-0.5 * (d / sigma) ** 2)
    return torch.from_numpy(out)


def focal_heatmap_loss(logits: torch.Tensor, target: torch.Tensor, alpha: float = 2.0,
                       beta: float = 4.0) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss; ``target`` peaks at exactly 1 at object centres."""
    p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    pos = target.ge(0.999).float()
    neg = 1.0 - pos
    pos_loss = -(torch.log(p) * (1 - p) ** alpha * pos).sum()
    neg_loss = -(torch.log(1 - p) * p ** alpha * (1 - target) ** beta * neg).sum()
    return (pos_loss + neg_loss) / pos.sum().clamp_min(1.0)


def visibility_logits(heat: torch.Tensor) -> torch.Tensor:
    """Per-keypoint visibility logits (N, 5) from stage 2's heatmaps (N, 11, m, m): each keypoint's
    visibility map (channels 6..10) averaged under its own heatmap's softmax (channels 0..4), so the
    statement is about the place the keypoint is read at. The softmax is not differentiated through:
    the visibility loss does not move the keypoints."""
    n, m = heat.shape[0], heat.shape[-1]
    p = F.softmax(heat[:, :N_KP].detach().reshape(n, N_KP, m * m), dim=-1)
    return (p * heat[:, N_KP + 1:2 * N_KP + 1].reshape(n, N_KP, m * m)).sum(-1)


# ---------------------------------------------------------------- decoding

def decode_heatmaps(kp_logits: torch.Tensor, out_stride: int):
    """Sub-pixel keypoints from (N, K, m, m) logits.

    Per keypoint: the argmax of the softmax, then a separable quadratic fit to the
    log-probabilities of its 3x3 neighbourhood (exact for the Gaussian the loss trains towards).
    Returns ``uv`` (N, K, 2) in crop pixels and ``score`` (N, K): the softmax mass within 2 cells
    of the peak (near 1 for a sharp, single peak). Computed in numpy on the 5x5 cells around each
    peak (the log-probability there is the logit less the map's log-sum-exp): per detection this
    is a handful of array calls, where torch's per-call cost doubled the time."""
    x = kp_logits.detach().float().cpu().numpy()
    n, k, m, _ = x.shape
    flat = x.reshape(n, k, m * m)
    peak = flat.argmax(-1)
    top = np.take_along_axis(flat, peak[..., None], -1)
    lse = top[..., 0] + np.log(np.exp(flat - top).sum(-1))
    iy, ix = peak // m, peak % m
    o = np.arange(-2, 3)
    wy, wx = iy[..., None, None] + o[:, None], ix[..., None, None] + o[None, :]
    inside = (wy >= 0) & (wy < m) & (wx >= 0) & (wx < m)
    # edge cells repeat past the border (replicate padding); cells past it hold no mass
    idx = (np.clip(wy, 0, m - 1) * m + np.clip(wx, 0, m - 1)).reshape(n, k, 25)
    win = (np.take_along_axis(flat, idx, -1) - lse[..., None]).reshape(n, k, 5, 5)
    c, l, r, u, d = win[..., 2, 2], win[..., 2, 1], win[..., 2, 3], win[..., 1, 2], win[..., 3, 2]
    s = out_stride
    xs = (ix + parabola_vertex(l, c, r)) * s + (s - 1) / 2.0
    ys = (iy + parabola_vertex(u, c, d)) * s + (s - 1) / 2.0
    uv = np.stack([xs, ys], -1).astype(np.float32)
    score = np.clip((np.exp(win) * inside).sum((-1, -2)), 0.0, 1.0).astype(np.float32)
    return torch.from_numpy(uv), torch.from_numpy(score)


def parabola_vertex(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Vertex offset in [-0.5, 0.5] of the parabola through (-1, a), (0, b), (1, c)."""
    den = a - 2 * b + c
    off = np.where(den < -1e-6, 0.5 * (a - c) / np.minimum(den, -1e-6), 0.0)
    return np.clip(off, -0.5, 0.5)


def global_size(cfg: ModelConfig, w: int, h: int) -> tuple[int, int, float, float]:
    """Stage 1's input (ws, hs) for a w x h image, its downscale w / ws and its box scale.

    Any image is seen at the scale of a ``REFERENCE_WIDTH`` one of the same field of view (downscale
    ``global_downscale`` there, in proportion elsewhere, never upscaled), so a needle spans the
    same cells at 640x480 as at 1920x1080; box sizes are regressed relative to that scale."""
    ds = max(1.0, cfg.global_downscale * w / REFERENCE_WIDTH)
    ws, hs = max(1, round(w / ds)), max(1, round(h / ds))
    ds = w / ws
    return ws, hs, ds, ds / cfg.global_downscale


def decode_global(out: torch.Tensor, downscale: float, box_scale: float = 1.0):
    """Best box from GlobalNet output (1, 5, h, w): (confidence, cx, cy, w, h) in full-res px."""
    return decode_global_topk(out, downscale, 1, box_scale=box_scale)[0]


def decode_global_topk(out: torch.Tensor, downscale: float, k: int = 2, min_conf: float = 0.0,
                       min_dist_cells: int = 2, box_scale: float = 1.0):
    """Up to ``k`` boxes (confidence, cx, cy, w, h), best first, from the local maxima of the
    GlobalNet heatmap at least ``min_dist_cells`` apart with confidence >= ``min_conf``."""
    heat = out[0, 0]
    pooled = F.max_pool2d(heat[None, None], 2 * min_dist_cells + 1, 1, min_dist_cells)[0, 0]
    peaks = (heat == pooled) & (torch.sigmoid(heat) >= min_conf)
    ys, xs = torch.nonzero(peaks, as_tuple=True)
    order = torch.argsort(heat[ys, xs], descending=True)[:k]
    cell, unit = GLOBAL_STRIDE * downscale, BOX_UNIT * box_scale
    boxes = []
    for i in order.tolist():
        iy, ix = int(ys[i]), int(xs[i])
        lw, lh, ox, oy = (float(v) for v in out[0, 1:5, iy, ix])
        boxes.append((float(torch.sigmoid(heat[iy, ix])), (ix + ox) * cell + (cell - 1) / 2.0,
                      (iy + oy) * cell + (cell - 1) / 2.0, unit * float(np.exp(np.clip(lw, -4, 4))),
                      unit * float(np.exp(np.clip(lh, -4, 4)))))
    return boxes


def crop_side(cfg: ModelConfig, w: float, h: float) -> float:
    """Side (full-res px) of the square crop taken around a needle box of w x h px."""
    return max(cfg.crop_min, cfg.crop_margin * max(w, h) + cfg.crop_pad)


def crop_affine(cx: float, cy: float, side: float, crop: int, angle_rad: float = 0.0,
                flip: bool = False) -> np.ndarray:
    """2x3 affine mapping image px -> crop px for a square of ``side`` px centred at (cx, cy),
    optionally rotated by ``angle_rad`` and mirrored left-right (augmentation)."""
    s = crop / side
    c, sn = np.cos(angle_rad) * s, np.sin(angle_rad) * s
    A = np.array([[c, -sn], [sn, c]])
    if flip:
        A = np.array([[-1.0, 0.0], [0.0, 1.0]]) @ A
    centre = (crop - 1) / 2.0
    t = np.array([centre, centre]) - A @ np.array([cx, cy])
    return np.hstack([A, t[:, None]])


def invert_affine(M: np.ndarray) -> np.ndarray:
    A, t = M[:, :2], M[:, 2]
    Ai = np.linalg.inv(A)
    return np.hstack([Ai, (-Ai @ t)[:, None]])


def apply_affine(M: np.ndarray, pts: np.ndarray) -> np.ndarray:
    pts = np.asarray(pts, dtype=float).reshape(-1, 2)
    return pts @ M[:, :2].T + M[:, 2]
