"""CosPlace (Berton et al., CVPR 2022): a ResNet/VGG16 trunk, then L2-norm, GeM pooling, a linear layer and
L2-norm. Parameter names follow the published `GeoLocalizationNet` (`backbone.*`, `aggregation.1.p`,
`aggregation.3.{weight,bias}`), so the released `<Backbone>_<dim>_cosplace.pth` files load directly:

    rec = CosPlaceRecognizer.from_checkpoint("ResNet50_512_cosplace.pth", backbone="ResNet50", dim=512)
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from swarmsplat.kernels.errors import InputError

from .backbones import imagenet_tensor, load_into, load_state_dict_file, resnet_trunk, vgg16_trunk
from .base import PlaceRecognizer

BACKBONES = {"ResNet18": 18, "ResNet50": 50, "ResNet101": 101, "ResNet152": 152, "VGG16": "vgg16"}


class L2Norm(nn.Module):
    def forward(self, x):
        return F.normalize(x, p=2.0, dim=1)


class GeM(nn.Module):
    """Generalised-mean pooling with a learnt exponent p (one parameter, as published)."""

    def __init__(self, p: float = 3.0, eps: float = 1e-6):
        super().__init__()
        self.p = nn.Parameter(torch.ones(1) * p)
        self.eps = eps

    def forward(self, x):  # [B, C, H, W] -> [B, C, 1, 1]
        return F.avg_pool2d(x.clamp(min=self.eps).pow(self.p), x.shape[-2:]).pow(1.0 / self.p)


class Flatten(nn.Module):
    def forward(self, x):
        return x[:, :, 0, 0]


class CosPlaceNet(nn.Module):
    def __init__(self, backbone: str = "ResNet50", dim: int = 512):
        super().__init__()
        if backbone not in BACKBONES:
            raise InputError(f"CosPlace backbone must be one of {list(BACKBONES)}, got {backbone!r}")
        kind = BACKBONES[backbone]
        self.backbone, features = vgg16_trunk() if kind == "vgg16" else resnet_trunk(kind)
        self.aggregation = nn.Sequential(L2Norm(), GeM(), Flatten(), nn.Linear(features, int(dim)), L2Norm())

    def forward(self, x):  # [B, 3, H, W] ImageNet-normalised -> [B, dim] unit norm
        return self.aggregation(self.backbone(x))


class CosPlaceRecognizer(PlaceRecognizer):
    """CosPlace descriptor. `resize=(w, h)` as in the paper's evaluation (512x512 by default); None keeps size."""

    name = "cosplace"

    def __init__(self, net: CosPlaceNet, *, resize: tuple[int, int] | None = (512, 512), device: str = "cpu"):
        self.net = net.eval().to(device)
        self.device = device
        self.resize = resize
        self.dim = int(net.aggregation[3].out_features)

    @classmethod
    def from_checkpoint(cls, path, *, backbone: str = "ResNet50", dim: int = 512, **kw) -> "CosPlaceRecognizer":
        net = CosPlaceNet(backbone, dim)
        load_into(net, load_state_dict_file(path, "CosPlace"), "CosPlace", path)
        return cls(net, **kw)

    @torch.no_grad()
    def _describe(self, rgb: np.ndarray) -> np.ndarray:
        x = imagenet_tensor(rgb, self.resize).to(self.device)
        return self.net(x)[0].float().cpu().numpy()
