"""FLOCC-SLAM's loop-closure front-end for one candidate pair (§III-B): register the candidate, register the
query robot's own odometry pair, and turn the ratio of their correspondence counts into a gate and a confidence.

For a candidate (I_i^a, I_j^b):
    1. loop = register(enc(I_i^a), enc(I_j^b))               -> T_{a,i}^{b,j} up to scale, n_pair
    2. odom = register(enc(I_{i-1}^a), enc(I_i^a))          -> n_odom (cached per keyframe)
    3. r = n_pair / n_odom (eq. 1), rejected below R_thr, p = logistic(k (r - 1)) (eq. 2)
Counting and the logistic live in `graph.confidence` (one copy); this module only orchestrates. Encodings are
computed once per keyframe and cached, as each robot would keep its own.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Callable

import numpy as np

from swarmsplat.graph.confidence import K_DEFAULT, R_THR_DEFAULT, correspondence_ratio, loop_confidence
from swarmsplat.kernels.camera import PinholeCamera
from swarmsplat.kernels.errors import InputError
from swarmsplat.registration.pair.base import Encoding, PairRegistrar, PairResult

KeyframeId = tuple[str, int]  # (agent, keyframe index)


@dataclass
class LoopMeasurement:
    """The outcome for one candidate. `T_query_match` has a unit translation (scale it with odometry, eq. 6)."""

    query: KeyframeId
    match: KeyframeId
    similarity: float
    loop: PairResult
    odom: PairResult | None
    odom_pair: tuple[int, int] | None  # the query agent's keyframes registered for eq. (1)
    ratio: float | None
    p: float | None  # eq. (2); None when rejected
    accepted: bool
    reason: str = ""

    @property
    def T_query_match(self) -> np.ndarray:
        return self.loop.T_query_match


# The eq. 1 gate per pair backend. The paper's 0.3 is tuned for MASt3R's dense reciprocal matches, whose count
# scales with the overlapping area. Classical SIFT inliers fall off faster with viewpoint change: on the generated
# teams the correct classical loops have ratios 0.16-0.21 at the 10th percentile and the wrong ones 0.13-0.25 at the
# 90th. 0.15 is the lowest gate with no false merge up to 0.6 m keyframe spacing there (precision 0.97, recall 0.93;
# 0.3 loses 15 % of the correct loops): perf/results/fig5-cpu.md. XFeat + LighterGlue keeps more inliers across
# viewpoints: correct ratios p10 0.33 / p50 0.72, wrong p50 0.044 / p90 0.154 (`python -m perf.flocc_fig5 --quick
# --backends classical xfeat`, seed 1, 486 registrations); 0.25 sits between the two (pooled precision 0.94,
# recall 0.95; the IS-LM ATE is the same for every gate from 0.15 to 0.4). Unmeasured backends keep the paper's.
R_THR_BY_BACKEND = {"classical": 0.15, "xfeat": 0.25, "mast3r": R_THR_DEFAULT}


def default_r_thr(backend: str) -> float:
    """The correspondence-ratio gate R_thr used for pair backend `backend` when none is given."""
    return R_THR_BY_BACKEND.get(backend, R_THR_DEFAULT)


@dataclass
class LoopFrontend:
    """Registers loop candidates with one pair backend and gates them with the correspondence ratio.

    image_of(agent, index) -> RGB uint8 image; camera_of(agent) -> PinholeCamera. Both are called lazily, so the
    front-end holds only encodings (what a robot would keep), never a whole image sequence.
    """

    registrar: PairRegistrar
    image_of: Callable[[str, int], np.ndarray]
    camera_of: Callable[[str], PinholeCamera]
    num_keyframes: Callable[[str], int]
    k: float = K_DEFAULT
    r_thr: float | None = None  # None: default_r_thr(registrar.name)
    _enc: dict = field(default_factory=dict, repr=False)
    _odom: dict = field(default_factory=dict, repr=False)
    encode_calls: int = 0

    def __post_init__(self) -> None:
        if self.r_thr is None:
            self.r_thr = default_r_thr(getattr(self.registrar, "name", ""))

    def encoding(self, kf: KeyframeId) -> Encoding:
        """Encode keyframe `kf` once; later calls return the cached encoding."""
        if kf not in self._enc:
            self._enc[kf] = self.registrar.encode(self.image_of(*kf))
            self.encode_calls += 1
        return self._enc[kf]

    def has_encoding(self, kf: KeyframeId) -> bool:
        """True when keyframe `kf` is encoded here (computed or received)."""
        return kf in self._enc

    def put_encoding(self, kf: KeyframeId, encoding: Encoding) -> None:
        """Store an encoding received from the robot that owns keyframe `kf` (it is never re-encoded here)."""
        if not isinstance(encoding, Encoding):
            raise InputError(f"put_encoding({kf}): expected an Encoding, got {type(encoding).__name__}")
        self._enc[kf] = encoding

    @property
    def encodings(self) -> dict:
        """Read-only view of the cache: keyframe -> Encoding."""
        return MappingProxyType(self._enc)

    def odometry_pair(self, agent: str, i: int) -> tuple[tuple[int, int] | None, PairResult | None]:
        """Register (I_{i-1}, I_i) of `agent` (for i = 0 the next keyframe stands in: (I_0, I_1)); cached."""
        if (agent, i) not in self._odom:
            n = self.num_keyframes(agent)
            pair = (i - 1, i) if i > 0 else ((0, 1) if n > 1 else None)
            res = None
            if pair is not None:
                cam = self.camera_of(agent)
                res = self.registrar.register(self.encoding((agent, pair[0])), self.encoding((agent, pair[1])), cam, cam)
            self._odom[(agent, i)] = (pair, res)
        return self._odom[(agent, i)]

    def evaluate(self, query: KeyframeId, match: KeyframeId, similarity: float = float("nan")) -> LoopMeasurement:
        """Register one candidate and gate it (see the module docstring)."""
        loop = self.registrar.register(self.encoding(query), self.encoding(match), self.camera_of(query[0]),
                                       self.camera_of(match[0]))
        pair, odom = self.odometry_pair(*query)

        def out(ratio, p, ok, why):
            return LoopMeasurement(query, match, float(similarity), loop, odom, pair, ratio, p, ok, why)

        if odom is None:
            return out(None, None, False, "no odometry pair (agent has a single keyframe)")
        if odom.n_correspondences == 0:
            return out(None, None, False, f"odometry pair has no correspondences ({odom.reason or 'none'})")
        ratio = correspondence_ratio(loop.n_correspondences, odom.n_correspondences)
        if not loop.success:
            return out(ratio, None, False, f"registration failed: {loop.reason}")
        p = loop_confidence(ratio, k=self.k, r_thr=self.r_thr)
        if p is None:
            return out(ratio, None, False, f"ratio {ratio:.3f} < R_thr {self.r_thr}")
        return out(ratio, p, True, "")
