"""How a team's pose graph splits among its robots for the distributed solver.

A robot holds its own keyframe poses (GTSAM Symbol keys: robot = key >> 56) and every edge that touches one of
them; an inter-robot loop is therefore held by both of its robots, as their files hold it. Each loop has one
owner, the lower-numbered of its two robots (an intra-robot loop: its robot): the owner decides its GNC weight
and reports its scale variable (IS / SS; SS clusters join loops of one robot pair only, so a cluster has one
owner), which both robots of the pair move in their steps. Neighbours are robots that share a loop; a robot sends each neighbour its separators (its poses that
the neighbour's loops touch) and the scales and weights of the loops the two share. Robots are coloured
greedily in id order so that no two neighbours share a colour: robots of one colour update at the same time.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..pose_graph import PoseGraph


def robot_of(key: int) -> int:
    return int(key) >> 56


@dataclass
class RobotPart:
    robot: int  # Symbol character code
    keys: list[int]  # own pose keys, sorted
    edges: list[int]  # edges (indices into the team graph) touching an own pose
    owned: set[int] = field(default_factory=set)  # loop edges this robot owns
    separators: dict[int, list[int]] = field(default_factory=dict)  # neighbour -> own keys it needs
    pair_loops: dict[int, list[int]] = field(default_factory=dict)  # neighbour -> loop edges shared, in order
    anchors: list[int] = field(default_factory=list)  # the team graph's anchors among the own keys
    colour: int = 0

    @property
    def neighbours(self) -> list[int]:
        return sorted(self.separators)


def loop_owner(graph: PoseGraph, n: int) -> int:
    e = graph.edges[n]
    return min(robot_of(e.key_i), robot_of(e.key_j))


def partition(graph: PoseGraph) -> dict[int, RobotPart]:
    """Robot number -> its part (module docstring)."""
    parts = {}
    by_robot: dict[int, list[int]] = {}
    for k in graph.keys():
        by_robot.setdefault(robot_of(k), []).append(k)
    anchors = set(graph.anchors())
    for r, keys in by_robot.items():
        parts[r] = RobotPart(r, keys, [], anchors=[k for k in keys if k in anchors])
    for n, e in enumerate(graph.edges):
        ri, rj = robot_of(e.key_i), robot_of(e.key_j)
        parts[ri].edges.append(n)
        if rj != ri:
            parts[rj].edges.append(n)
            for a, b, kb in ((ri, rj, e.key_j), (rj, ri, e.key_i)):
                parts[b].separators.setdefault(a, set()).add(kb)  # b sends a its pose kb
                parts[a].pair_loops.setdefault(b, []).append(n)
        if e.kind != "odometry":
            parts[min(ri, rj)].owned.add(n)
    for p in parts.values():
        p.separators = {q: sorted(s) for q, s in p.separators.items()}
        for q in p.pair_loops:
            p.pair_loops[q].sort(key=lambda n: (graph.edges[n].key_i, graph.edges[n].key_j, n))
        for q in p.separators:
            p.pair_loops.setdefault(q, [])
    for r in sorted(parts):
        used = {parts[q].colour for q in parts[r].neighbours if q < r}
        parts[r].colour = next(c for c in range(len(parts) + 1) if c not in used)
    return parts
