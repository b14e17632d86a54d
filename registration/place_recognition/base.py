"""Place recognition: one interface for global image descriptors and a database that matches them by cosine.

A descriptor is a float32 [D] vector with unit L2 norm, so cosine similarity is a dot product and its size on
the wire is `4 * D` bytes. Robots exchange descriptors and each one searches its neighbours' keyframes for the
nearest neighbour of every own keyframe (FLOCC-SLAM §III-A); a pair whose similarity passes the threshold
becomes a loop-closure candidate for pair registration.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from swarmsplat.kernels.errors import InputError

PAPER_THRESHOLD = 0.1  # FLOCC-SLAM §IV: "a permissive value of 0.1"; registration filters the rest


class PlaceRecognizer(ABC):
    """A global image descriptor. Subclasses set `name` and `dim` and implement `_describe`."""

    name: str = "base"
    dim: int = 0
    min_side: int | None = None  # smallest image side accepted; None: registration.images.MIN_SIDE

    @abstractmethod
    def _describe(self, rgb: np.ndarray) -> np.ndarray:
        """Validated RGB uint8 [H, W, 3] -> raw descriptor [dim] (any float dtype, any norm)."""

    def describe(self, image: np.ndarray) -> np.ndarray:
        """RGB uint8 [H, W, 3] (or grey [H, W]) -> L2-normalised float32 [dim].

        An image with no usable structure (blank) gives the zero vector, whose similarity to anything is 0, so it
        never becomes a candidate; a malformed image raises InputError.
        """
        from swarmsplat.registration.images import MIN_SIDE, as_rgb8

        rgb = as_rgb8(image, min_side=self.min_side or MIN_SIDE)
        return l2_normalise(np.asarray(self._describe(rgb), dtype=np.float32).reshape(-1))

    def describe_many(self, images) -> np.ndarray:
        """Iterable of images -> float32 [N, dim]."""
        out = [self.describe(im) for im in images]
        return np.stack(out) if out else np.zeros((0, self.dim), np.float32)

    @property
    def descriptor_bytes(self) -> int:
        """Bytes one descriptor takes on the wire (float32)."""
        return 4 * int(self.dim)


def l2_normalise(v: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Unit-norm rows (float32); all-zero (or non-finite) rows stay zero instead of becoming NaN."""
    v = np.asarray(v, dtype=np.float32)
    v = np.where(np.isfinite(v), v, 0.0).astype(np.float32)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > eps, v / np.maximum(n, eps), 0.0).astype(np.float32)


@dataclass(frozen=True)
class PlaceMatch:
    """One candidate: keyframe `query_index` of `query_agent` looks like keyframe `index` of `agent`."""

    query_agent: str
    query_index: int
    agent: str
    index: int
    similarity: float


class PlaceDatabase:
    """Keyframe descriptors of any number of agents, searched by cosine similarity.

    `add(agent, index, descriptor)` stores one keyframe; `query(...)` returns the best matches of one
    descriptor; `candidates(...)` runs the per-keyframe nearest-neighbour search of FLOCC-SLAM for a whole agent.
    """

    def __init__(self, dim: int):
        if int(dim) <= 0:
            raise InputError(f"PlaceDatabase: dim must be positive, got {dim}")
        self.dim = int(dim)
        self._agents: list[str] = []
        self._indices: list[int] = []
        self._rows: list[np.ndarray] = []
        self._matrix: np.ndarray | None = None  # [N, D] cache, rebuilt after additions

    def __len__(self) -> int:
        return len(self._rows)

    def _check(self, descriptor, name: str = "descriptor") -> np.ndarray:
        d = np.asarray(descriptor, dtype=np.float32)
        if d.shape != (self.dim,):
            raise InputError(f"PlaceDatabase: {name} must have shape [{self.dim}], got {list(d.shape)}")
        return l2_normalise(d)

    def add(self, agent: str, index: int, descriptor: np.ndarray) -> None:
        """Store the descriptor [dim] of keyframe `index` of `agent` (re-normalised defensively)."""
        self._rows.append(self._check(descriptor))
        self._agents.append(str(agent))
        self._indices.append(int(index))
        self._matrix = None

    def add_many(self, agent: str, indices, descriptors: np.ndarray) -> None:
        """Store [N] keyframe indices with their descriptors [N, dim]."""
        descriptors = np.asarray(descriptors, dtype=np.float32)
        indices = list(indices)
        if descriptors.ndim != 2 or len(descriptors) != len(indices):
            raise InputError(f"PlaceDatabase.add_many: expected [N, {self.dim}] descriptors for {len(indices)} "
                             f"indices, got {list(descriptors.shape)}")
        for i, d in zip(indices, descriptors):
            self.add(agent, i, d)

    def _db(self) -> np.ndarray:
        if self._matrix is None:
            self._matrix = np.stack(self._rows) if self._rows else np.zeros((0, self.dim), np.float32)
        return self._matrix

    def query(self, descriptor: np.ndarray, *, query_agent: str = "", query_index: int = -1, k: int = 1,
              threshold: float | None = None, exclusion_window: int = 0, other_agents_only: bool = False,
              agents: list[str] | None = None) -> list[PlaceMatch]:
        """The `k` most similar stored keyframes, best first.

        threshold: keep only similarity >= threshold (None keeps all; `PAPER_THRESHOLD` = 0.1 as the paper).
        exclusion_window: for a query from `query_agent` itself, skip its own keyframes with
            |index - query_index| <= exclusion_window (the neighbours that trivially look alike).
        other_agents_only: never return keyframes of `query_agent` (inter-robot search only).
        agents: restrict the search to these agents.
        """
        if k < 1:
            raise InputError(f"PlaceDatabase.query: k must be >= 1, got {k}")
        q = self._check(descriptor)
        db = self._db()
        if not len(db):
            return []
        sim = db @ q  # [N] cosine similarities
        agent_arr = np.asarray(self._agents)
        idx_arr = np.asarray(self._indices)
        ok = np.ones(len(sim), bool)
        own = agent_arr == str(query_agent)
        if other_agents_only:
            ok &= ~own
        elif exclusion_window >= 0 and query_index >= 0:
            ok &= ~(own & (np.abs(idx_arr - int(query_index)) <= int(exclusion_window)))
        if agents is not None:
            ok &= np.isin(agent_arr, [str(a) for a in agents])
        if threshold is not None:
            ok &= sim >= float(threshold)
        cand = np.flatnonzero(ok)
        # stable order: similarity descending, then insertion order, so ties resolve deterministically
        order = cand[np.lexsort((cand, -sim[cand]))][:k]
        return [PlaceMatch(str(query_agent), int(query_index), self._agents[i], self._indices[i], float(sim[i]))
                for i in order]

    def candidates(self, agent: str, indices, descriptors: np.ndarray, *, threshold: float | None = PAPER_THRESHOLD,
                   k: int = 1, exclusion_window: int | None = None, agents: list[str] | None = None) -> list[PlaceMatch]:
        """FLOCC-SLAM's search for one agent: for each of its keyframes, the best match(es) among stored keyframes.

        With `exclusion_window=None` only other agents are searched (inter-robot loop closures); with an integer,
        the agent's own keyframes outside that window are searched too (intra-robot loops). `agents` restricts the
        search to some agents, e.g. the one neighbour whose descriptors just arrived.
        """
        descriptors = np.asarray(descriptors, dtype=np.float32)
        out: list[PlaceMatch] = []
        for i, d in zip(list(indices), descriptors):
            out += self.query(d, query_agent=agent, query_index=int(i), k=k, threshold=threshold,
                              exclusion_window=-1 if exclusion_window is None else exclusion_window,
                              other_agents_only=exclusion_window is None, agents=agents)
        return out
