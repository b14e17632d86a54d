"""graph/information: non-positive-definite information matrices (strict / repair / isotropic) on a synthetic graph."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from swarmsplat.graph import lie
from swarmsplat.graph.formulations import build_problem
from swarmsplat.graph.g2o import read_g2o, repaired_edges, write_g2o
from swarmsplat.graph.information import (
    REPAIR_FLOOR, apply_policy, is_positive_definite, isotropic_information, isotropic_weights, nearest_pd,
    se_sync_weights)
from swarmsplat.graph.init import initialize
from swarmsplat.graph.pose_graph import LOOP, ODOMETRY, Edge, PoseGraph
from swarmsplat.graph.solvers import levenberg_marquardt
from swarmsplat.kernels.errors import InputError

N_POSES = 60
GROSS, MILD = (3, 17, 30, 41, 62), (5, 22, 36, 50, 70)  # edges whose matrix the file gets badly / slightly wrong
BAD = GROSS + MILD


def _noisy_graph(seed=0):
    """A 3D loop of 60 poses (radius 10 m, climbing), odometry + loops every 10 poses across the loop. Each edge
    has its own anisotropic PD information (with rotation-translation cross terms) and a measurement drawn with
    that covariance. Returns (true poses, graph with the true matrices, graph whose GROSS edges carry an
    indefinite matrix with the same diagonal blocks and whose MILD edges' smallest eigenvalue is pushed just
    below zero, as rounding would)."""
    rng = np.random.default_rng(seed)
    gt = {}
    for k in range(N_POSES):
        a = 2 * np.pi * k / N_POSES
        T = np.eye(4)
        T[:3, :3] = lie.so3_exp(np.array([0.05 * np.sin(3 * a), 0.05, a + np.pi / 2]))
        T[:3, 3] = [10 * np.cos(a), 10 * np.sin(a), 0.5 * np.sin(2 * a)]
        gt[k] = T
    pairs = [(k, k + 1) for k in range(N_POSES - 1)] + [(k, (k + N_POSES // 2) % N_POSES) for k in range(0, 60, 4)]
    pairs += [(k, k + 3) for k in range(0, N_POSES - 3, 7)]
    clean, bad = PoseGraph(), PoseGraph()
    for k in range(N_POSES):
        clean.add_pose(k, np.eye(4))
        bad.add_pose(k, np.eye(4))
    for n, (i, j) in enumerate(pairs):
        A = rng.normal(size=(6, 6)) * 0.3
        S = np.diag(np.r_[rng.uniform(0.01, 0.03, 3), rng.uniform(0.05, 0.2, 3)]) ** 2 + 1e-4 * (A @ A.T)
        info = np.linalg.inv(S)
        xi = rng.multivariate_normal(np.zeros(6), S)
        T = np.linalg.inv(gt[i]) @ gt[j] @ lie.exp(xi[None])[0]
        kind = ODOMETRY if j == i + 1 else LOOP
        clean.edges.append(Edge(i, j, T, info, kind))
        wrong = info.copy()
        if n in GROSS:  # cross block large enough to make the matrix indefinite, diagonal blocks untouched
            d = np.sqrt(np.diag(info))
            C = 3.0 * np.outer(d[:3], d[3:]) * rng.choice([-1, 1], (3, 3))
            wrong[:3, 3:], wrong[3:, :3] = C, C.T
        elif n in MILD:
            w, V = np.linalg.eigh(info)
            wrong = info - (1 + 1e-3) * w[0] * np.outer(V[:, 0], V[:, 0])
        bad.edges.append(Edge(i, j, T, wrong, kind))
    return gt, clean, bad


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    gt, clean, bad = _noisy_graph()
    d = tmp_path_factory.mktemp("nonpd")
    return gt, clean, write_g2o(clean, d / "clean.g2o"), write_g2o(bad, d / "bad.g2o")


def test_nearest_pd_is_the_eigenvalue_projection():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6))
    A = A + A.T  # indefinite
    w = np.linalg.eigvalsh(A)
    assert w[0] < 0 < w[-1]
    B = nearest_pd(A)
    wb = np.linalg.eigvalsh(B)
    assert np.allclose(B, B.T) and wb[0] == pytest.approx(REPAIR_FLOOR * w[-1], rel=1e-6)
    assert np.allclose(np.sort(wb)[w >= REPAIR_FLOOR * w[-1]], w[w >= REPAIR_FLOOR * w[-1]])  # kept as they were
    dist = np.linalg.norm(A - B)
    assert dist == pytest.approx(np.sqrt(np.sum((w[w < wb[0]] - wb[0]) ** 2)), rel=1e-9)
    for _ in range(200):  # no other matrix with eigenvalues above the floor is closer
        C = B + 0.3 * rng.normal() * (lambda M: M + M.T)(rng.normal(size=(6, 6)))
        if np.linalg.eigvalsh(C)[0] >= wb[0]:
            assert np.linalg.norm(A - C) >= dist - 1e-12
    assert nearest_pd(-np.eye(6)) is None
    assert apply_policy(-np.eye(6), "repair") is None  # no positive part anywhere: nothing to repair
    P = np.diag([1.0, 2, 3, 4, 5, 6])
    P[0, 5] = P[5, 0] = 10.0  # indefinite 6x6, both diagonal blocks PD
    iso = isotropic_information(P)
    assert np.allclose(iso, np.diag([3 / (1 + 1 / 2 + 1 / 3)] * 3 + [3 / (1 / 4 + 1 / 5 + 1 / 6)] * 3))
    assert apply_policy(P, "strict") is None
    assert isotropic_weights(iso) == pytest.approx(isotropic_weights(P))  # SE-Sync sees the same edge


def test_strict_refuses_with_file_and_line(synthetic):
    _, _, _, bad = synthetic
    with pytest.raises(InputError, match="not positive definite") as err:
        read_g2o(bad)  # the library default is strict, today's behaviour
    first_edge_line = N_POSES + min(BAD) + 1
    assert f"{bad}:{first_edge_line}:" in str(err.value)


def _positions(graph):
    poses, _ = initialize(graph)
    res = levenberg_marquardt(build_problem(graph, initial_poses=poses), relative_tol=1e-8, absolute_tol=1e-10)
    assert res.converged
    return np.stack([res.poses[k][:3, 3] for k in sorted(res.poses)])


@pytest.mark.parametrize("policy", ["repair", "isotropic"])
def test_policies_replace_only_the_bad_edges_and_still_solve(synthetic, policy):
    gt, clean_graph, clean, bad = synthetic
    g = read_g2o(bad, information=policy)
    rules = {n: ("repair" if policy == "repair" and n in MILD else "isotropic") for n in BAD}
    assert repaired_edges(g) == {r: list(rules.values()).count(r) for r in set(rules.values())}
    ref = read_g2o(clean)
    for n, (e, c) in enumerate(zip(g.edges, ref.edges)):
        assert is_positive_definite(e.info)
        if n in BAD:
            assert e.info_policy == rules[n] and not is_positive_definite(e.info_raw)
            if n in GROSS:  # diagonal blocks as they were
                assert np.allclose(e.info_raw[:3, :3], c.info[:3, :3]) and np.allclose(e.info_raw[3:, 3:], c.info[3:, 3:])
            if rules[n] == "isotropic":
                assert np.count_nonzero(e.info - np.diag(np.diag(e.info))) == 0
            else:  # a slightly wrong matrix: the projection barely changes it
                assert np.linalg.norm(e.info - e.info_raw) < 1e-3 * np.linalg.norm(e.info_raw)
            # SE-Sync's weights come from the file's own diagonal blocks (what SE-Sync reads), not from the repair
            raw, used = np.array(isotropic_weights(e.info_raw)), np.array(isotropic_weights(e.info))
            assert se_sync_weights(e) == pytest.approx(np.where(raw > 0, raw, used), rel=1e-12)
            if n in GROSS:
                assert se_sync_weights(e) == pytest.approx(se_sync_weights(c), rel=1e-9)
        else:
            assert e.info_raw is None and np.array_equal(e.info, c.info)
    # the solution against the one with the true matrices, and against knowing nothing about the bad edges
    true = _positions(ref)
    dropped = copy.deepcopy(g)
    for n in BAD:
        dropped.edges[n].info = 1e-6 * np.eye(6)
    moved, moved_dropped = np.abs(_positions(g) - true).max(), np.abs(_positions(dropped) - true).max()
    print(f"{policy}: solution {moved:.3f} m from the one with the true matrices (bad edges ignored: "
          f"{moved_dropped:.3f} m)")
    # measured: repair 0.165 m, isotropic 0.457 m (the slightly wrong matrices lose their translation weight
    # entirely under isotropic), bad edges ignored 0.713 m
    assert moved < (0.35 if policy == "repair" else 0.8) * moved_dropped


def test_cli_information_policies(synthetic, tmp_path, capsys):
    from swarmsplat.slam.cli import main

    _, _, _, bad = synthetic
    out = tmp_path / "out.g2o"
    assert main(["graph", "solve", str(bad), "--out", str(out), "--information", "strict"]) == 2
    assert "not positive definite" in capsys.readouterr().err and not out.exists()
    assert main(["graph", "solve", str(bad), "--out", str(out)]) == 0  # default: repair
    cap = capsys.readouterr()
    warnings = [line for line in cap.err.splitlines() if line.startswith("warning")]
    assert len(warnings) == 1 and warnings[0].startswith(f"warning: {len(BAD)} of ")
    summary = json.loads(out.with_suffix(".json").read_text())
    assert summary["information"] == {"policy": "repair", "replaced": len(BAD),
                                      "by_rule": {"repair": len(MILD), "isotropic": len(GROSS)}}
    assert summary["converged"] and summary["iterations"] >= 1
    assert f"iterations {summary['iterations']}" in cap.out
    assert float(cap.out.split("final error ")[1].split()[0]) == pytest.approx(summary["final_error"], rel=1e-8)
    back = read_g2o(out, information="repair")  # the file's own matrices are written back
    assert repaired_edges(back) == {"repair": len(MILD), "isotropic": len(GROSS)}


def test_matrix_without_positive_part_is_refused_under_every_policy(tmp_path):
    p = tmp_path / "zero.g2o"
    p.write_text("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 100 0 0 100 0 50\n"
                 "EDGE_SE2 1 0 -1 0 0 0 0 0 0 0 0\n")
    for policy in ("repair", "isotropic", "strict"):
        with pytest.raises(InputError, match="not positive definite") as err:
            read_g2o(p, information=policy)
        assert f"{p}:4:" in str(err.value)
