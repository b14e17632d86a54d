"""Read a run folder (what `swarmsplat run` or `swarmsplat demo` wrote) into a slam.view.scene.Scene.

Layouts (see slam.run.sequence and slam.run.team_results):
  one agent   metrics.json ("agent"), map.ply, trajectory.txt, keyframes.txt, loops.csv
  team        metrics.json ("agents"), map.ply (+ map_<agent>.ply per other component), trajectories/,
              trajectories_no_lc/, pose_graph_optimized.g2o (keyframe poses), loops.csv
  demo        the team layout in RUN/results (RUN/dataset beside it)

Ground truth comes from the dataset recorded in metrics.json ("dataset"), when it is still there: it is brought
into the map frame by the inverse of the SE(3) alignment the metrics use (one alignment per component), so what
is drawn is what the ATE measured. Tracking-only trajectories (their agent's own frame) are aligned the same way,
or, without ground truth, anchored at the first pose of the loop-closed trajectory.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from swarmsplat.kernels.errors import InputError

from .panel import metrics_markdown
from .scene import (GLOBAL, GT_COLOR, NOMINAL_FOV, Frusta, Scene, Track, agent_color, lighten, loop_edges,
                    splats_from_params, vertical_fov)

GT_MAX_DIFF = 0.01  # seconds, as the team's metrics associate


def find_run(folder: str | Path) -> Path:
    """The folder holding metrics.json: `folder` itself or its results/ (the demo layout)."""
    p = Path(folder)
    if not p.exists():
        raise InputError(f"run folder not found: {p}")
    if not p.is_dir():
        raise InputError(f"{p} is not a folder (expected the folder `swarmsplat run` or `swarmsplat demo` wrote)")
    for cand in (p, p / "results"):
        if (cand / "metrics.json").is_file():
            return cand
    raise InputError(f"{p} is not a run folder: no metrics.json in it or in {p / 'results'} (expected the folder "
                     f"`swarmsplat run --out` or `swarmsplat demo --out` wrote)")


def read_metrics(run: Path) -> dict:
    path = run / "metrics.json"
    try:
        m = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: not readable JSON ({e})") from None
    if not isinstance(m, dict) or not ("agents" in m or "agent" in m):
        raise InputError(f"{path}: not a swarmsplat metrics file (no 'agent' or 'agents' key)")
    return m


def map_files(run: Path, metrics: dict) -> list[Path]:
    """map.ply first, then every other component's map; InputError when the run has none."""
    names = ["map.ply"] + sorted(n for n in (metrics.get("maps") or {}) if n != "map.ply")
    names += sorted(p.name for p in run.glob("map_*.ply") if p.name not in names)
    found = [run / n for n in names if (run / n).is_file()]
    if not found:
        raise InputError(f"{run}: the run has no map (no map.ply; it is written when a run finishes)")
    return found


def check_run(folder: str | Path) -> tuple[Path, dict, list[Path]]:
    """(the folder with metrics.json, its metrics, its map files); InputError when it is not a run with a map."""
    run = find_run(folder)
    m = read_metrics(run)
    return run, m, map_files(run, m)


def load_scene(folder: str | Path) -> Scene:
    """Everything the viewer shows for a run folder. Bad input raises InputError naming what is wrong."""
    from swarmsplat.slam.dense.ply import load_ply

    run, m, maps = check_run(folder)
    scene = Scene(title=f"swarmsplat: {Path(folder).resolve().name}")
    team = "agents" in m
    names = [a["name"] for a in m["agents"]] if team else [m.get("agent") or "agent"]
    groups = _components(m, names)
    frame_of = {n: (GLOBAL if root == names[0] else root) for root, ms in groups.items() for n in ms}
    for p in maps:
        owner = p.stem[len("map_"):] if p.stem.startswith("map_") else names[0]
        sp = splats_from_params(p.stem, load_ply(p))
        sp.frame = frame_of.get(owner, GLOBAL)
        scene.splats.append(sp)
    est = _read_estimates(run, names, team)
    gt, cams, note = _ground_truth(run, m, names)
    if note:
        scene.notes.append(note)
    kf_poses = _keyframe_poses(run, names, team)
    for root, members in groups.items():
        _add_tracks(scene, names, members, est, gt, frame_of)
    for i, name in enumerate(names):
        poses = kf_poses.get(name)
        if poses is not None and len(poses):
            fov, aspect = vertical_fov(cams[name]) if name in cams else NOMINAL_FOV
            scene.frusta.append(Frusta(f"keyframes_{name}", name, poses, agent_color(i), fov, aspect,
                                       frame_of.get(name, GLOBAL)))
    if not kf_poses:
        scene.notes.append("no keyframe poses in the run folder (keyframes.txt / pose_graph_optimized.g2o)")
    scene.edges = loop_edges(_loops(run, names, kf_poses, frame_of))
    others = [f for f in scene.frames() if f != GLOBAL]
    if others:
        scene.notes.append(f"agents outside the global frame (shown under 'own frame' layers, off at first): "
                           f"{', '.join(n for n in names if frame_of.get(n) != GLOBAL)}")
    scene.panel = metrics_markdown(m, names, scene)
    return scene


# ---- trajectories -----------------------------------------------------------------------------------------------

def _read_estimates(run: Path, names: list[str], team: bool) -> dict:
    """{agent: {"slam": (t, T), "no_lc": (t, T)}} for the files that exist."""
    from swarmsplat.slam.io.trajectory import read_tum

    out = {}
    for n in names:
        files = ({"slam": run / "trajectories" / f"{n}.txt", "no_lc": run / "trajectories_no_lc" / f"{n}.txt"}
                 if team else {"slam": run / "trajectory.txt"})
        out[n] = {k: read_tum(p) for k, p in files.items() if p.is_file()}
    return out


def _components(m: dict, names: list[str]) -> dict[str, list[str]]:
    comps = m.get("components")
    if isinstance(comps, dict) and comps:
        return {str(r): [str(x) for x in ms] for r, ms in comps.items()}
    return {names[0]: list(names)}


def _alignment(gt: tuple, est: tuple) -> np.ndarray:
    """4x4 taking estimated poses onto ground truth (rigid, least squares over matched positions); with too few
    or collinear poses, the transform that puts the first matched estimate on its ground truth."""
    from swarmsplat.slam.metrics import ate
    from swarmsplat.slam.metrics.align import associate_poses

    try:
        return ate(*gt, *est, align="se3", max_diff=GT_MAX_DIFF).transform.matrix
    except InputError:
        pairs = associate_poses(*gt, *est, max_diff=GT_MAX_DIFF)
        if not pairs.matched:
            raise
        return pairs.T_gt[0] @ np.linalg.inv(pairs.T_est[0])


def _add_tracks(scene: Scene, names: list[str], members: list[str], est: dict, gt: dict, frame_of: dict) -> None:
    """Loop-closed, tracking-only and ground-truth trajectories of one component's agents, in its frame."""
    from swarmsplat.slam.metrics import ate_multi

    have = [n for n in members if n in gt and "slam" in est.get(n, {})]
    S_inv = {}
    if have:
        try:
            j = ate_multi({n: gt[n] for n in have}, {n: est[n]["slam"] for n in have}, align="se3",
                          max_diff=GT_MAX_DIFF)
            S = j.joint.transform.matrix
            S_inv = {n: np.linalg.inv(S) for n in have}
        except InputError:  # too few poses for one alignment: each agent on its own
            S_inv = {}
            for n in have:
                try:
                    S_inv[n] = np.linalg.inv(_alignment(gt[n], est[n]["slam"]))
                except InputError:
                    pass
    for n in members:
        i = names.index(n)
        c, fr = agent_color(i), frame_of.get(n, GLOBAL)
        e = est.get(n, {})
        if "slam" in e:
            scene.tracks.append(Track(f"{n}_slam", n, "slam", e["slam"][1][:, :3, 3], c, fr))
        if "no_lc" in e:
            T = e["no_lc"][1]
            if n in S_inv:
                try:
                    T = S_inv[n] @ _alignment(gt[n], e["no_lc"])[None] @ T
                except InputError:
                    T = _anchor(T, e.get("slam"))
            else:
                T = _anchor(T, e.get("slam"))
            scene.tracks.append(Track(f"{n}_no_lc", n, "no_lc", T[:, :3, 3], lighten(c), fr))
        if n in S_inv:
            from swarmsplat.slam.metrics.align import associate_poses

            pairs = associate_poses(*gt[n], *e["slam"], max_diff=GT_MAX_DIFF)
            T_gt = S_inv[n][None] @ pairs.T_gt
            scene.tracks.append(Track(f"{n}_gt", n, "gt", T_gt[:, :3, 3], GT_COLOR, fr))


def _anchor(T: np.ndarray, ref: tuple | None) -> np.ndarray:
    """Tracking-only poses moved so their first pose is the loop-closed trajectory's first pose."""
    if ref is None or not len(ref[1]):
        return T
    return (ref[1][0] @ np.linalg.inv(T[0]))[None] @ T


def _ground_truth(run: Path, m: dict, names: list[str]) -> tuple[dict, dict, str]:
    """({agent: (t, T_world_cam)}, {agent: camera}, note) from the run's dataset, when it can be found."""
    from swarmsplat.slam.io.datasets import load_dataset

    recorded = m.get("dataset")
    cands = [Path(recorded)] if recorded else []
    cands += [run.parent / "dataset", run / "dataset"]  # the demo's cache beside results/
    root = next((c for c in cands if c.is_dir()), None)
    if root is None:
        where = f"the dataset {recorded} is not there" if recorded else "metrics.json names no dataset"
        return {}, {}, f"no ground truth or calibration: {where} (nominal frusta)"
    try:
        ds = load_dataset(root)
    except InputError as e:
        return {}, {}, f"no ground truth or calibration: {e}"
    seqs = {s.name: s for s in ds.agents}
    if len(ds.agents) == 1:  # one sequence (a single run, or a sequence split into agents)
        seqs = {n: ds.agents[0] for n in names}
    gt, cams = {}, {}
    for n in names:
        s = seqs.get(n)
        if s is None:
            continue
        cams[n] = s.camera
        G = s.gt_poses
        if G is not None:
            ok = np.all(np.isfinite(G.reshape(len(G), -1)), axis=1)
            if ok.any():
                gt[n] = (s.timestamps[ok], G[ok])
    return gt, cams, "" if gt else f"the dataset {root} has no ground truth"


# ---- keyframes and loops ---------------------------------------------------------------------------------------

def _keyframe_poses(run: Path, names: list[str], team: bool) -> dict[str, np.ndarray]:
    """{agent: [K, 4, 4]} keyframe poses in id order (team: the optimised pose graph; one agent: keyframes.txt)."""
    if not team:
        from swarmsplat.slam.io.trajectory import read_tum

        p = run / "keyframes.txt"
        return {names[0]: read_tum(p)[1]} if p.is_file() else {}
    p = run / "pose_graph_optimized.g2o"
    if not p.is_file():
        return {}
    from swarmsplat.graph.g2o import read_g2o
    from swarmsplat.graph.pose_graph import key_index, key_robot

    g = read_g2o(p)
    per: dict[str, dict[int, np.ndarray]] = {}
    for key, T in g.poses.items():
        r = key_robot(key)
        a = ord(r) - ord("a") if r else 0
        if 0 <= a < len(names):
            per.setdefault(names[a], {})[key_index(key)] = np.asarray(T, dtype=np.float64)
    return {n: _by_id(d) for n, d in per.items()}


def _by_id(d: dict[int, np.ndarray]) -> np.ndarray:
    """[max id + 1, 4, 4] with NaN rows for ids absent (never, in our files; kept safe for hand-edited ones)."""
    out = np.full((max(d) + 1, 4, 4), np.nan)
    for k, T in d.items():
        out[k] = T
    return out


def _loops(run: Path, names: list[str], kf: dict[str, np.ndarray], frame_of: dict) -> list[tuple]:
    """(kind, T_a, T_b, frame) of every accepted loop in loops.csv whose two keyframe poses are known."""
    p = run / "loops.csv"
    if not p.is_file() or not kf:
        return []
    out = []
    with open(p, newline="") as f:
        for lineno, row in enumerate(csv.DictReader(f), 2):
            if str(row.get("accepted", "")).strip().lower() not in ("true", "1"):
                continue
            try:
                qa = row.get("query_agent") or names[0]
                ma = row.get("match_agent") or names[0]
                qk, mk = int(row["query_kf"]), int(row["match_kf"])
            except (KeyError, TypeError, ValueError):
                raise InputError(f"{p}:{lineno}: expected integer query_kf and match_kf columns") from None
            kind = row.get("kind") or ("intra" if qa == ma else "inter")
            A, B = kf.get(qa), kf.get(ma)
            if A is None or B is None or qk >= len(A) or mk >= len(B):
                continue
            if np.all(np.isfinite(A[qk])) and np.all(np.isfinite(B[mk])):
                out.append((kind, A[qk], B[mk], frame_of.get(qa, GLOBAL)))
    return out
