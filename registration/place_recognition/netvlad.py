"""NetVLAD (Arandjelović et al., CVPR 2016) as in the widely used PyTorch port (Nanne/pytorch-NetVlad): VGG16
conv5_3 features (`encoder.0` .. `encoder.28`), NetVLAD pooling (`pool.conv.weight` [K, 512, 1, 1] soft-assignment,
`pool.centroids` [K, 512]), intra- and global L2 normalisation. Its released checkpoints (a dict with
'state_dict') load directly:

    rec = NetVLADRecognizer.from_checkpoint("checkpoint.pth.tar")     # K = 64 clusters -> 32768-d

The descriptor is large (128 KiB as float32); a PCA projection would shrink it but is not part of that release.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from .backbones import imagenet_tensor, load_into, load_state_dict_file, vgg16_trunk
from .base import PlaceRecognizer


class NetVLADPool(nn.Module):
    def __init__(self, num_clusters: int = 64, dim: int = 512, vladv2: bool = False):
        super().__init__()
        self.num_clusters, self.dim = int(num_clusters), int(dim)
        self.conv = nn.Conv2d(dim, num_clusters, 1, bias=vladv2)
        self.centroids = nn.Parameter(torch.rand(num_clusters, dim))

    def forward(self, x):  # [B, C, H, W] -> [B, K * C]
        b, c = x.shape[:2]
        x = F.normalize(x, p=2, dim=1)
        a = F.softmax(self.conv(x).view(b, self.num_clusters, -1), dim=1)  # [B, K, HW] soft assignment
        xf = x.view(b, c, -1)  # [B, C, HW]
        # sum_n a_kn (x_n - c_k) = (A X^T)_k - (sum_n a_kn) c_k, without the [B, K, C, HW] residual tensor
        vlad = torch.bmm(a, xf.transpose(1, 2)) - a.sum(-1, keepdim=True) * self.centroids[None]
        vlad = F.normalize(vlad, p=2, dim=2)
        return F.normalize(vlad.reshape(b, -1), p=2, dim=1)


class NetVLADNet(nn.Module):
    def __init__(self, num_clusters: int = 64, vladv2: bool = False):
        super().__init__()
        self.encoder, dim = vgg16_trunk()
        self.pool = NetVLADPool(num_clusters, dim, vladv2)

    def forward(self, x):
        return self.pool(self.encoder(x))


class NetVLADRecognizer(PlaceRecognizer):
    name = "netvlad"

    def __init__(self, net: NetVLADNet, *, resize: tuple[int, int] | None = None, device: str = "cpu"):
        self.net = net.eval().to(device)
        self.device = device
        self.resize = resize
        self.dim = net.pool.num_clusters * net.pool.dim

    @classmethod
    def from_checkpoint(cls, path, *, num_clusters: int = 64, vladv2: bool = False, **kw) -> "NetVLADRecognizer":
        state = load_state_dict_file(path, "NetVLAD")
        net = NetVLADNet(num_clusters, vladv2="pool.conv.bias" in state or vladv2)
        load_into(net, state, "NetVLAD", path)
        return cls(net, **kw)

    @torch.no_grad()
    def _describe(self, rgb: np.ndarray) -> np.ndarray:
        x = imagenet_tensor(rgb, self.resize).to(self.device)
        return self.net(x)[0].float().cpu().numpy()
