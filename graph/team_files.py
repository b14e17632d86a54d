"""A team's pose graph from the files robots record: one g2o per robot, or DPGO's robotN/measurements.csv.

`read_team(inputs)` takes what `swarmsplat graph solve` is given:

  * several g2o files, one per robot (DGS's layout: Symbol keys, each inter-robot edge in both robots' files);
  * a folder of such files named `<k>.g2o` (DGS's `blocks_world/<N>robots/`; a `fullGraph.g2o` beside them, the
    centralised copy, is not read);
  * a folder of `robotN/measurements.csv` (graph.dpgo_csv);
  * one g2o file (a centralised graph).

The copies of an inter-robot edge must agree (one line naming both files and lines otherwise), and an edge to a
robot whose file is missing is refused (one line naming the edge's file:line).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import InputError

from .dpgo_csv import is_measurements_folder, read_measurements
from .g2o import read_g2o
from .pose_graph import PoseGraph, key_str


def robot_g2o_files(folder: str | Path) -> list[Path]:
    """`<k>.g2o` files of a DGS folder in robot order."""
    files = [p for p in Path(folder).glob("*.g2o") if re.fullmatch(r"\d+", p.stem)]
    if not files:
        raise InputError(f"{folder}: no <k>.g2o files (one per robot) and no robotN/measurements.csv")
    return sorted(files, key=lambda p: int(p.stem))


def read_team(inputs: list[str | Path], information: str = "strict") -> PoseGraph:
    """One PoseGraph of the whole team from `inputs` (module docstring). `information` is g2o's policy for
    matrices that are not positive definite (graph.information)."""
    inputs = [Path(p) for p in inputs]
    if len(inputs) == 1 and inputs[0].is_dir():
        if is_measurements_folder(inputs[0]):
            return read_measurements(inputs[0])
        inputs = robot_g2o_files(inputs[0])
    for p in inputs:
        if p.is_dir():
            raise InputError(f"{p}: a folder among several inputs; give g2o files, or one folder")
    graphs = [read_g2o(p, information=information) for p in inputs]
    if len(graphs) == 1:
        return graphs[0]
    _check_copies(graphs)
    graph = graphs[0]
    for g in graphs[1:]:
        graph = graph.merged(g)
    if graph.pending:
        e = graph.pending[0]
        missing = key_str(e.key_i if e.key_i not in graph.poses else e.key_j)
        raise InputError(f"{e.source}: edge {key_str(e.key_i)}-{key_str(e.key_j)} goes to pose {missing} of a robot "
                         f"none of the files defines")
    return graph


def _check_copies(graphs: list[PoseGraph]) -> None:
    """Two files' copies of one inter-robot edge (same keys, either direction) must be the same measurement."""
    first: dict[tuple[int, int], object] = {}
    for g in graphs:
        for e in g.edges + g.pending:
            if not e.inter_robot:
                continue
            key = (min(e.key_i, e.key_j), max(e.key_i, e.key_j))
            other = first.get(key)
            if other is None:
                first[key] = e
                continue
            T = e.T_ij if (e.key_i, e.key_j) == (other.key_i, other.key_j) else np.linalg.inv(e.T_ij)
            if not np.allclose(T, other.T_ij, rtol=1e-5, atol=1e-6):
                field = "translation" if np.allclose(T[:3, :3], other.T_ij[:3, :3], atol=1e-6) else "rotation"
                raise InputError(f"{e.source}: {field} of edge {key_str(e.key_i)}-{key_str(e.key_j)} differs from "
                                 f"its copy at {other.source}")
            if not np.allclose(e.info, other.info, rtol=1e-5, atol=1e-9):
                raise InputError(f"{e.source}: information of edge {key_str(e.key_i)}-{key_str(e.key_j)} differs "
                                 f"from its copy at {other.source}")
