"""The HoloLens cases of `wide-joins` alone (perf/wide_joins.py): the office walk split in two agents and the whole
walk as one agent, with the defaults — the two runs that judge wide-viewpoint loops on a real camera, in about half of
the subject's time."""

from __future__ import annotations

DESCRIPTION = "wide-viewpoint loops on the real HoloLens office walk: split in two agents, and whole as one"


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    from .wide_joins import run as wide_joins

    return wide_joins(backends=backends, device=device, quick=False, hololens_only=True)
