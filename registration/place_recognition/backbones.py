"""Convolutional backbones with torchvision's parameter names (torchvision itself is not a dependency), so the
published CosPlace and NetVLAD checkpoints, which were saved from torchvision models, load unchanged.

`resnet_trunk(depth)` -> nn.Sequential(conv1, bn1, relu, maxpool, layer1..layer4) (torchvision's children
without avgpool/fc, indices 0..7); `vgg16_trunk()` -> VGG16 `features` without its last ReLU and max-pool
(indices 0..28), as both projects cut them.
"""

from __future__ import annotations

import torch
from torch import nn

from swarmsplat.kernels.errors import InputError


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, cin: int, planes: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, planes, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(planes, planes, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.downsample = _shortcut(cin, planes * self.expansion, stride)

    def forward(self, x):
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return self.relu(y + (x if self.downsample is None else self.downsample(x)))


class Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, cin: int, planes: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride, 1, bias=False)  # stride on the 3x3 (ResNet v1.5)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, planes * 4, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(planes * 4)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = _shortcut(cin, planes * 4, stride)

    def forward(self, x):
        y = self.relu(self.bn1(self.conv1(x)))
        y = self.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return self.relu(y + (x if self.downsample is None else self.downsample(x)))


def _shortcut(cin: int, cout: int, stride: int):
    if stride == 1 and cin == cout:
        return None
    return nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))


_RESNETS = {18: (BasicBlock, [2, 2, 2, 2]), 34: (BasicBlock, [3, 4, 6, 3]), 50: (Bottleneck, [3, 4, 6, 3]),
            101: (Bottleneck, [3, 4, 23, 3]), 152: (Bottleneck, [3, 8, 36, 3])}


def resnet_trunk(depth: int) -> tuple[nn.Sequential, int]:
    """ResNet-`depth` without avgpool and fc -> (module, output channels)."""
    if depth not in _RESNETS:
        raise InputError(f"ResNet depth must be one of {sorted(_RESNETS)}, got {depth}")
    block, counts = _RESNETS[depth]
    layers: list[nn.Module] = [nn.Conv2d(3, 64, 7, 2, 3, bias=False), nn.BatchNorm2d(64), nn.ReLU(inplace=True),
                               nn.MaxPool2d(3, 2, 1)]
    cin = 64
    for i, (planes, n) in enumerate(zip([64, 128, 256, 512], counts)):
        blocks = []
        for j in range(n):
            blocks.append(block(cin, planes, stride=2 if (j == 0 and i > 0) else 1))
            cin = planes * block.expansion
        layers.append(nn.Sequential(*blocks))
    return nn.Sequential(*layers), cin


def vgg16_trunk() -> tuple[nn.Sequential, int]:
    """VGG16 `features[:-2]` (ends with conv5_3, no ReLU) -> (module, 512)."""
    cfg = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"]
    layers: list[nn.Module] = []
    cin = 3
    for c in cfg:
        if c == "M":
            layers.append(nn.MaxPool2d(2, 2))
        else:
            layers += [nn.Conv2d(cin, c, 3, padding=1), nn.ReLU(inplace=True)]
            cin = c
    return nn.Sequential(*layers[:-2]), 512


IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def imagenet_tensor(rgb, size: tuple[int, int] | None) -> torch.Tensor:
    """RGB uint8 [H, W, 3] -> normalised float32 [1, 3, h, w]; resized to size=(w, h) when given."""
    import cv2
    import numpy as np

    if size is not None and (rgb.shape[1], rgb.shape[0]) != tuple(size):
        rgb = cv2.resize(rgb, tuple(int(s) for s in size), interpolation=cv2.INTER_AREA)
    x = torch.from_numpy(np.ascontiguousarray(rgb)).float().div_(255.0).permute(2, 0, 1)
    x = (x - torch.tensor(IMAGENET_MEAN)[:, None, None]) / torch.tensor(IMAGENET_STD)[:, None, None]
    return x[None]


def load_state_dict_file(path, what: str) -> dict:
    """Read a checkpoint saved by torch.save -> plain state dict (unwrapping 'state_dict'/'model', 'module.')."""
    from pathlib import Path

    if path is None:
        raise InputError(f"{what}: no checkpoint given (pass the path of the published weights; nothing is downloaded)")
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what}: checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises many kinds for a bad file
        raise InputError(f"{what}: cannot read checkpoint {path}: {type(e).__name__}: {str(e).splitlines()[0]}") from None
    for key in ("state_dict", "model"):
        if isinstance(ckpt, dict) and key in ckpt and isinstance(ckpt[key], dict):
            ckpt = ckpt[key]
    if not isinstance(ckpt, dict):
        raise InputError(f"{what}: {path} does not hold a state dict")
    return {k.replace("module.", ""): v for k, v in ckpt.items()}


def load_into(model: nn.Module, state: dict, what: str, path, *, assign: bool = False) -> None:
    """load_state_dict(strict) with one clear line when keys or shapes do not fit (`assign` for meta models)."""
    own = model.state_dict()
    missing = [k for k in own if k not in state]
    unexpected = [k for k in state if k not in own]
    bad = [k for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or bad:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing (e.g. {missing[0]})")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected (e.g. {unexpected[0]})")
        if bad:
            parts.append(f"shape mismatch at {bad[0]}: {list(state[bad[0]].shape)} vs {list(own[bad[0]].shape)}")
        raise InputError(f"{what}: checkpoint {path} does not fit this architecture: " + "; ".join(parts))
    model.load_state_dict(state, strict=True, assign=assign)
