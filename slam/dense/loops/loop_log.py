"""Loop-closure diagnostics: one record per candidate, intra- or inter-agent, with the reason it was accepted or
rejected, written as `loops.csv` and summarised in the report.

"No loops found" without an explanation is the most common complaint about SLAM systems; every candidate that
reached the similarity test is therefore kept, with a short machine-readable `reason_code`
(`accepted`, `similarity`, `overlap`, `registration`, `fitness`, `rmse`, `correction`, `gnc`, `inconsistent`,
`move`, `unconfirmed`: verified between agents not yet in one frame, but no second consistent loop confirmed the
join, `render`: the matched agent's map rendered from the hypothesised pose contradicts the query's view) beside the human sentence; `source` says where the candidate came from (`descriptor`: place recognition,
`pose`: the tracked poses' view overlap, GRAND-SLAM eq. 6) and `route` how its start was found (`image`: the
tracked poses or image matches, `cloud`: 3-D registration of the two local maps, slam.dense.loops.local_clouds).

Intra-agent candidates come from the agent's own `LoopCloser.log` (slam.dense.loops.loop_closure.LoopCandidate); that record
has no reason code, so it is derived from the start of its reason sentence (`reason_code_of`).
"""

from __future__ import annotations

import csv
import io
from collections import Counter
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from swarmsplat.kernels.fileio import atomic_write_text

INTRA, INTER = "intra", "inter"
REASON_CODES = ("accepted", "similarity", "overlap", "registration", "fitness", "rmse", "correction", "gnc",
                "inconsistent", "move", "unconfirmed", "render")
SOURCES = ("descriptor", "pose")


@dataclass
class LoopRecord:
    """One loop candidate. Keyframe ids index each agent's keyframe list; frames are input frame indices."""

    kind: str  # INTRA or INTER
    query_agent: str
    query_kf: int
    query_frame: int
    match_agent: str
    match_kf: int
    match_frame: int
    similarity: float
    accepted: bool = False
    reason_code: str = ""  # one of REASON_CODES
    reason: str = ""  # the sentence: thresholds and values
    registration: str = ""  # registration outcome ("ok", "poor alignment", "not converged", ...; "" = not run)
    fitness: float = 0.0
    inlier_rmse: float = float("inf")  # metres
    correction_m: float = 0.0  # translation the loop applies to the current estimate (same frame only)
    joined: bool = False  # this loop brought two agents' frames together (first inter-agent loop of a pair)
    step: int = 0  # team step (round) at which the candidate was checked
    source: str = "descriptor"  # one of SOURCES
    route: str = "image"  # "image" (tracked pose / image matches) or "cloud" (3-D registration of local maps)
    render_covisible: float = float("nan")  # verification by rendering (slam.dense.loops.render_check); NaN: not run
    render_agree: float = float("nan")
    render_violate: float = float("nan")
    render_photometric: float = float("nan")

    def reject(self, code: str, reason: str) -> "LoopRecord":
        self.accepted, self.reason_code, self.reason = False, code, reason
        return self


def reason_code_of(reason: str, accepted: bool) -> str:
    """Reason code of an intra-agent `LoopCandidate`'s sentence (see slam.dense.loops.loop_closure.LoopCloser.verify)."""
    if accepted:
        return "accepted"
    r = reason.lower()
    for prefix, code in (("similarity", "similarity"), ("overlap", "overlap"), ("registration", "registration"),
                         ("render", "render"),
                         ("fitness", "fitness"), ("inlier rmse", "rmse"), ("correction", "correction"), ("gnc", "gnc"),
                         ("inconsistent", "inconsistent"), ("optimisation would move", "move")):
        if r.startswith(prefix):
            return code
    return "registration"


def from_intra(agent: str, candidate, step: int = 0) -> LoopRecord:
    """A LoopRecord from one of `LoopCloser.log`'s LoopCandidates (duck-typed: only its fields are read)."""
    c = candidate
    code = reason_code_of(c.reason, c.accepted)
    reg = "" if code in ("similarity", "overlap") else (
        "ok" if code != "registration" else c.reason.split(":", 1)[-1].strip())
    nan = float("nan")
    return LoopRecord(INTRA, agent, c.query_kf, c.query_frame, agent, c.match_kf, c.match_frame, float(c.similarity),
                      bool(c.accepted), code, c.reason, reg, float(c.fitness), float(c.inlier_rmse),
                      float(c.correction_m), False, step, getattr(c, "source", "descriptor"),
                      getattr(c, "route", "image"), *(float(getattr(c, f"render_{k}", nan))
                                                      for k in ("covisible", "agree", "violate", "photometric")))


def write_loops_csv(path: str | Path, records: list[LoopRecord]) -> Path:
    """Every record, one row each, columns in LoopRecord's field order (atomic write)."""
    cols = [f.name for f in fields(LoopRecord)]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n")
    w.writeheader()
    for r in records:
        row = asdict(r)
        for k in ("similarity", "fitness", "inlier_rmse", "correction_m", "render_covisible", "render_agree",
                  "render_violate", "render_photometric"):
            row[k] = f"{row[k]:.6g}"
        w.writerow(row)
    atomic_write_text(path, buf.getvalue())
    return Path(path)


def count_by_source(items) -> dict:
    """{source: {"candidates": n, "accepted": k}} over records or LoopCandidates (anything with .source/.accepted)."""
    src = Counter(r.source for r in items)
    acc = Counter(r.source for r in items if r.accepted)
    return {s: {"candidates": src[s], "accepted": acc[s]} for s in SOURCES if src[s]}


def summarise(records: list[LoopRecord]) -> dict:
    """Counts per kind and reason code: {"intra": {"candidates": n, "accepted": k, "by_reason": {...}}, ...}."""
    out = {}
    for kind in (INTRA, INTER):
        rs = [r for r in records if r.kind == kind]
        by = Counter(r.reason_code for r in rs)
        out[kind] = {"candidates": len(rs), "accepted": sum(r.accepted for r in rs),
                     "by_reason": {c: by[c] for c in REASON_CODES if by[c]}, "by_source": count_by_source(rs)}
    return out
