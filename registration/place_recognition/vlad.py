"""Place-recognition descriptors aggregated from RootSIFT local features: no downloaded weights needed.

The vocabulary (K centroids of RootSIFT descriptors) is trained from the data by k-means with a fixed seed, so
the same images always give the same vocabulary, and it is saved/loaded as a small `.npz`. Two aggregations:

- `BoWRecognizer` ("bow", the default): bag of visual words, sqrt(tf) * idf weights, L2 norm. Dimension K (256
  -> 1 KiB). Similarities are >= 0 and grow with the share of common words, which suits a cosine threshold.
- `VLADRecognizer` ("vlad"): VLAD (Jégou et al. 2010) with signed square-root (power) and intra-normalisation.
  Dimension K * 128. With a vocabulary trained on the same few images it searches, residuals are centred on
  them and unrelated images score below zero; rankings stay useful, absolute thresholds less so.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import InputError
from swarmsplat.kernels.fileio import atomic_path

from .base import PlaceRecognizer


def rootsift(rgb: np.ndarray, n_features: int, max_side: int) -> np.ndarray:
    """RGB uint8 [H, W, 3] -> RootSIFT descriptors float32 [M, 128] (M may be 0 on a blank image)."""
    import cv2

    from swarmsplat.registration.images import resize_max_side, to_grey

    small, _ = resize_max_side(rgb, max_side)
    grey = to_grey(small)
    _, desc = cv2.SIFT_create(nfeatures=n_features).detectAndCompute(grey, None)
    if desc is None or not len(desc):
        return np.zeros((0, 128), np.float32)
    desc = desc.astype(np.float32)
    desc /= np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)  # L1, then sqrt: Hellinger kernel (RootSIFT)
    return np.sqrt(desc)


def kmeans(x: np.ndarray, k: int, *, seed: int = 0, iters: int = 25) -> np.ndarray:
    """Deterministic k-means++ / Lloyd on x [N, D] float32 -> centroids [k, D]."""
    rng = np.random.default_rng(seed)
    x = np.asarray(x, dtype=np.float32)
    n = len(x)
    centres = np.empty((k, x.shape[1]), np.float32)
    centres[0] = x[rng.integers(n)]
    d2 = ((x - centres[0]) ** 2).sum(1)
    for c in range(1, k):  # k-means++ seeding
        p = d2 / d2.sum() if d2.sum() > 0 else np.full(n, 1.0 / n)
        centres[c] = x[rng.choice(n, p=p)]
        d2 = np.minimum(d2, ((x - centres[c]) ** 2).sum(1))
    for _ in range(iters):
        assign = _assign(x, centres)
        moved = 0.0
        for c in range(k):
            members = x[assign == c]
            new = members.mean(0) if len(members) else x[rng.integers(n)]  # re-seed an empty cluster
            moved = max(moved, float(np.abs(new - centres[c]).max()))
            centres[c] = new
        if moved < 1e-6:
            break
    return centres


def _assign(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    # ||x - c||^2 = |x|^2 - 2 x.c + |c|^2; |x|^2 is constant per row
    d = -2.0 * x @ centres.T + (centres**2).sum(1)[None]
    return np.argmin(d, axis=1)


class _VocabularyRecognizer(PlaceRecognizer):
    """Shared vocabulary handling: training by k-means, `.npz` save/load."""

    name = "vocabulary"
    default_clusters = 32
    per_cluster_dim = 128
    local_dim = 128  # dimension of the local descriptors the vocabulary clusters

    def __init__(self, centroids: np.ndarray | None = None, *, n_clusters: int | None = None, n_features: int = 1000,
                 max_side: int = 640, idf: np.ndarray | None = None):
        self.n_features = int(n_features)
        self.max_side = int(max_side)
        self.n_clusters = int(n_clusters or self.default_clusters)
        self.centroids: np.ndarray | None = None
        self.idf = None if idf is None else np.asarray(idf, np.float32)
        if centroids is not None:
            self._set_centroids(centroids)
        self.dim = self.n_clusters * self.per_cluster_dim

    def _set_centroids(self, centroids: np.ndarray) -> None:
        c = np.asarray(centroids, dtype=np.float32)
        if c.ndim != 2 or c.shape[1] != self.local_dim or len(c) < 1:
            raise InputError(f"{self.name} vocabulary must be [K, {self.local_dim}] float, got {list(c.shape)}")
        self.centroids = c
        self.n_clusters = len(c)
        self.dim = self.n_clusters * self.per_cluster_dim
        if self.idf is not None and self.idf.shape != (len(c),):
            raise InputError(f"{self.name} vocabulary: idf has shape {list(self.idf.shape)}, expected [{len(c)}]")

    @property
    def trained(self) -> bool:
        return self.centroids is not None

    def _local(self, rgb: np.ndarray) -> np.ndarray:
        """Validated RGB -> local descriptors float32 [M, local_dim] (RootSIFT here)."""
        return rootsift(rgb, self.n_features, self.max_side)

    def fit(self, images, *, seed: int = 0, max_descriptors: int = 50_000) -> "_VocabularyRecognizer":
        """Train the vocabulary from an iterable of RGB images (deterministic for a given seed and input)."""
        from swarmsplat.registration.images import as_rgb8

        parts = [self._local(as_rgb8(im, f"images[{i}]")) for i, im in enumerate(images)]
        return self.fit_local(parts, seed=seed, max_descriptors=max_descriptors)

    def fit_local(self, parts: list[np.ndarray], *, seed: int = 0,
                  max_descriptors: int = 50_000) -> "_VocabularyRecognizer":
        """Train from local descriptors already computed, one [M_i, local_dim] array per training image."""
        x = np.concatenate(parts) if parts else np.zeros((0, self.local_dim), np.float32)
        if len(x) < self.n_clusters:
            raise InputError(f"{self.name}.fit: the training images gave {len(x)} features, need at least "
                             f"{self.n_clusters} (more or more textured images)")
        if len(x) > max_descriptors:
            x = x[np.random.default_rng(seed).choice(len(x), max_descriptors, replace=False)]
        self.idf = None
        self._set_centroids(kmeans(x, self.n_clusters, seed=seed))
        self._fit_weights(parts)
        return self

    def _fit_weights(self, parts: list[np.ndarray]) -> None:
        """Hook for weights learnt from the training images (BoW's idf)."""

    def save(self, path: str | Path) -> Path:
        """Write the vocabulary and settings as `.npz` (atomically)."""
        if not self.trained:
            raise InputError(f"{self.name}.save: the vocabulary is not trained")
        extra = {} if self.idf is None else {"idf": self.idf}
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, kind=self.name, centroids=self.centroids, n_features=self.n_features,
                         max_side=self.max_side, **extra)
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "_VocabularyRecognizer":
        """Load a vocabulary saved by `save`; the file says whether it is for BoW or VLAD."""
        path = Path(path)
        if not path.is_file():
            raise InputError(f"vocabulary file not found: {path}")
        try:
            with np.load(path, allow_pickle=False) as z:
                kind = str(z["kind"]) if "kind" in z else "vlad"
                klass = _vocabulary_class(kind)
                return klass(z["centroids"], n_features=int(z["n_features"]), max_side=int(z["max_side"]),
                             idf=z["idf"] if "idf" in z else None)
        except (KeyError, ValueError, OSError) as e:
            raise InputError(f"{path}: not a vocabulary file (.npz with 'centroids'): {e}") from None


def _vocabulary_class(kind: str):
    """Vocabulary kind ('bow', 'vlad', 'xfeat-vlad') -> its recogniser class (KeyError for others)."""
    if kind == "xfeat-vlad":
        from .xfeat_vlad import XFeatVLADRecognizer

        return XFeatVLADRecognizer
    return {"bow": BoWRecognizer, "vlad": VLADRecognizer}[kind]


def vlad_aggregate(x: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """Local descriptors [M, D] -> VLAD [K * D]: residual sums per nearest centroid, signed square root, then
    intra-normalisation (each cluster's block to unit norm; empty clusters stay zero)."""
    v = np.zeros(centroids.shape, np.float32)
    if len(x):
        a = _assign(x, centroids)
        np.add.at(v, a, x - centroids[a])
    v = np.sign(v) * np.sqrt(np.abs(v))
    n = np.linalg.norm(v, axis=1, keepdims=True)
    v = np.where(n > 1e-12, v / np.maximum(n, 1e-12), 0.0)
    return v.reshape(-1)


class VLADRecognizer(_VocabularyRecognizer):
    """VLAD of RootSIFT with a vocabulary trained by `fit` or loaded by `load`."""

    name = "vlad"

    def _describe(self, rgb: np.ndarray) -> np.ndarray:
        if not self.trained:
            raise InputError(f"{self.name} vocabulary is not trained: call fit(images) or load(path)")
        return vlad_aggregate(self._local(rgb), self.centroids)


class BoWRecognizer(_VocabularyRecognizer):
    """Bag of visual words over RootSIFT: sqrt(tf) * idf, L2-normalised; dimension = vocabulary size."""

    name = "bow"
    default_clusters = 256
    per_cluster_dim = 1

    def _fit_weights(self, parts: list[np.ndarray]) -> None:
        df = np.zeros(self.n_clusters)
        for x in parts:
            if len(x):
                df[np.unique(_assign(x, self.centroids))] += 1
        self.idf = np.log((len(parts) + 1) / (df + 1)).astype(np.float32) + 1e-3  # smoothed; never exactly 0

    def _describe(self, rgb: np.ndarray) -> np.ndarray:
        if not self.trained:
            raise InputError("BoW vocabulary is not trained: call fit(images) or load(path)")
        x = self._local(rgb)
        tf = np.bincount(_assign(x, self.centroids), minlength=self.n_clusters) if len(x) else np.zeros(self.n_clusters)
        idf = self.idf if self.idf is not None else np.ones(self.n_clusters, np.float32)
        return np.sqrt(tf.astype(np.float32)) * idf
