"""The team server's pose graph (slam.dense.team.server.Server's mixin): every agent's keyframes, tracking edges,
intra- and inter-agent loops as one graph.PoseGraph, rebuilt at every optimisation from edges built once."""

from __future__ import annotations

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.slam.dense.loops.edge_information import fixed_information

_rigid = se3.project_rigid  # poses composed from many tracked and moved frames drift off SE(3)


class TeamGraph:
    def build_graph(self):
        """One multi-agent PoseGraph: every agent's keyframes, tracking edges, intra and inter loops (minus GNC
        outliers). Returns (graph, edge tags) with a tag per edge: None for odometry, else ("intra", a, n) or
        ("inter", n)."""
        from swarmsplat.graph.pose_graph import PoseGraph

        fixed = fixed_information(self.cfg.loop_sigma_rot, self.cfg.loop_sigma_trans)
        g, tags = PoseGraph(), []
        for a, s in enumerate(self.slots):
            kfs = s.agent.keyframes
            if kfs:  # one batched projection per agent (the same numbers as one by one)
                for kf, T in zip(kfs, _rigid(np.stack([self.global_pose(a, kf) for kf in kfs]))):
                    g.add_pose(self.key(a, kf.id), T)
            for n, e in enumerate(s.agent.loops.odometry):
                self._add_edge(g, ("odometry", a, n), e, a, e.i, a, e.j, e.T_ij, e.info)
                tags.append(None)
            for n, e in enumerate(s.agent.loops.loops):
                if ("intra", a, n) not in self.rejected_edges and not e.rejected:
                    self._add_edge(g, ("intra", a, n), e, a, e.i, a, e.j, e.T_ij, e.info)
                    tags.append(("intra", a, n))
        for n, L in enumerate(self.inter):
            if ("inter", n) not in self.rejected_edges and not L.rejected:
                self._add_edge(g, ("inter", n), L, L.agent_i, L.kf_i, L.agent_j, L.kf_j, L.T_ij,
                               fixed if L.info is None else L.info)
                tags.append(("inter", n))
        return g, tags

    def _add_edge(self, g, tag, src, a, i, b, j, T_ij, info) -> None:
        """Edge `tag` of graph `g`, built from `src` (an odometry edge, an intra loop or an InterLoop) once: its
        projected measurement and checked information are kept for every later graph while `src` holds the same
        arrays (the graph is rebuilt at every optimisation, and building every edge anew was a third of a long
        mission's server time). A checkpoint keeps no such cache (__getstate__)."""
        from swarmsplat.graph.pose_graph import LOOP, ODOMETRY, Edge

        cache = self.__dict__.setdefault("_edges", {})
        hit = cache.get(tag)
        if hit is not None and hit[0] is src and hit[1] is T_ij and hit[2] is src.info:  # (None: the fixed sigmas)
            g.add_edge(hit[3], checked=True)
            return
        kind = ODOMETRY if tag[0] == "odometry" else LOOP
        e = g.add_edge(Edge(self.key(a, i), self.key(b, j), _rigid(T_ij), np.asarray(info, float), kind))
        cache[tag] = (src, T_ij, src.info, e)

    def __getstate__(self):
        return {k: v for k, v in self.__dict__.items() if k != "_edges"}
