"""Deterministic choice of the robot that optimises (Swarm-SLAM's rule): the lowest id among the robots in range.

Every robot evaluates the rule on its own view (itself plus the neighbours it has heard from recently), so two
robots that see the same group elect the same optimiser without exchanging a single extra message; robots whose
views differ for a moment (a heartbeat lost) may both act, which the estimate stamps resolve (`node.py`).
"""

from __future__ import annotations

from typing import Iterable


def elect(robot: int, neighbours: Iterable[int]) -> int:
    """Id of the optimiser for `robot`'s group: min(robot, *neighbours)."""
    return min([int(robot), *map(int, neighbours)])


def is_optimiser(robot: int, neighbours: Iterable[int]) -> bool:
    """True when `robot` is the elected optimiser of a group that has at least one other robot."""
    nb = [int(n) for n in neighbours if int(n) != int(robot)]
    return bool(nb) and elect(robot, nb) == int(robot)
