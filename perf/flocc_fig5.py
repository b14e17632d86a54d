"""FLOCC-SLAM's keyframe-distance study (Fig. 5) and the R_thr sweep, on generated monocular multi-robot data.

    python -m perf.flocc_fig5 --json perf/results/fig5-cpu.json --md perf/results/fig5-cpu.md [--quick]
        [--backends classical xfeat] [--agents 6] [--spacings 0.4 0.8]

Data: the monocular generator's world, paths and drifting metric odometry (`slam.synthetic`, as `swarmsplat
generate --mono` makes them, same seeds), rendered in memory for the frames that become keyframes only. Agents
walk `loop_turns` laps of their loop, so sparse spacings still leave keyframes. Four robots: with the generator's
slot layout 2, robots a-c look the same way around the main opening and robot d looks back at it from the other
room, so d's candidates are mostly false (the negatives the R_thr gate must reject).

For each keyframe spacing d, a robot takes a keyframe whenever its *odometry* path length crosses a multiple of
d (spacings that double are nested: every keyframe at 2d is one at d). Then, as `swarmsplat pairs` does:
BoW descriptors (vocabulary trained once, seed 0, on the finest keyframes) -> nearest neighbour in every other
robot above cosine 0.1 (the paper's value) -> pair registration and the query robot's odometry pair
(`slam.flocc.frontend.LoopFrontend`) -> ratio (eq. 1), gate R_thr and p (eq. 2, `graph.confidence`) -> the swarm's own
graph build and solve (`slam.flocc.swarm.optimiser.solve_group`: odometry + unit-translation loops, eq. 6 initial
scale) with base-LM, IS-LM and base-GNC.

Per spacing and backend: keyframes, candidates, accepted loops, how many are correct by the paper's criterion
(translation error <= 2 m after scaling the estimate with ground truth) and by a room-scale one (rotation error
<= 5 deg and translation error <= 0.3 m after the same scaling; in rooms a few metres across almost no pose can
miss by 2 m), ATE RMSE of the merged robots over *all* frames (each frame = its keyframe's estimate composed with
odometry), and the front-end time the spacing costs. Encodings and registrations are computed once per frame /
frame pair and shared by spacings (each spacing is charged the measured time of every call it uses).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import dataclass

import numpy as np

from .flocc_fig5_data import DEFAULT_ROWS, CachedRegistrar, FrameCache, Scene, keyframes, registrars  # (re-exported)

DESCRIPTION = "FLOCC Fig. 5: loops and ATE vs keyframe spacing per registration backend; R_thr sweep"
OUTLIER_M = 2.0  # the paper's criterion (Fig. 3 / §IV-B)
STRICT_ROT_DEG, STRICT_T_M = 5.0, 0.3  # room-scale criterion
FORMULATIONS = (("base-LM", "base", "lm"), ("IS-LM", "is", "lm"), ("base-GNC", "base", "gnc"))
R_THR_SWEEP = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4)
R_THR_STUDY = {"classical": 0.15, "xfeat": 0.25}  # R_thr of the Fig. 5 rows per backend (slam.flocc.frontend.default_r_thr)


@dataclass(frozen=True)
class StudyConfig:
    seeds: tuple[int, ...] = (1, 2)  # generator seeds (worlds); rows are summed / averaged over them
    agents: int = 4  # with the generator's layout 2, robot d faces robots a-c: a source of false candidates
    frames: int = 300
    loop_turns: float = 3.0
    width: int = 320
    height: int = 240
    # metres of odometry path between keyframes; a lap is 2.4-3.2 m, so beyond ~2 m consecutive keyframes meet
    # again on the next lap (3.2 m measured: the odometry pair overlaps as much as at 0.4 m) and the trend breaks
    spacings: tuple[float, ...] = (0.2, 0.4, 0.6, 0.8, 1.2, 1.6)
    threshold: float = 0.1  # place-recognition cosine threshold (paper §IV)
    r_thr: float | None = None  # None: R_THR_STUDY[backend]
    vocabulary: int = 256
    gnc: bool = True

    @classmethod
    def quick(cls, **kw) -> "StudyConfig":
        return cls(**{**dict(seeds=(1,), frames=200, loop_turns=2.0, spacings=(0.2, 0.4, 0.8, 1.6)), **kw})


@dataclass
class Candidate:
    """One registered candidate with its ground-truth verdicts (query = lower robot, as the swarm registers)."""

    query: tuple[str, int]  # (robot, keyframe index)
    match: tuple[str, int]
    frames: tuple[int, int]
    similarity: float
    success: bool
    n_corr: int
    ratio: float | None
    T: np.ndarray  # T_query_match, unit translation
    odom_scale: float  # eq. 6
    gt_distance_m: float = float("nan")
    rot_err_deg: float = float("nan")
    t_err_m: float = float("nan")

    @property
    def correct_2m(self) -> bool:
        return self.success and self.t_err_m <= OUTLIER_M

    @property
    def correct_strict(self) -> bool:
        return self.success and self.rot_err_deg <= STRICT_ROT_DEG and self.t_err_m <= STRICT_T_M


@dataclass
class SpacingRun:
    spacing: float
    kf: dict[str, list[int]]
    candidates: list[Candidate]
    frontend_s: float
    encoding_bytes: int
    descriptor_bytes: int


def run_spacing(scene: Scene, cache: FrameCache, recognizer, spacing: float, cfg: StudyConfig,
                registrar_cls=None) -> SpacingRun:
    """Place recognition + registration + ratio for every candidate at one spacing (no gate: ratios kept).
    `registrar_cls` (default CachedRegistrar) lets a test wrap the registrations (e.g. inject wrong poses)."""
    from swarmsplat.graph.confidence import correspondence_ratio
    from swarmsplat.registration.place_recognition import PlaceDatabase
    from swarmsplat.slam.flocc.frontend import LoopFrontend
    from swarmsplat.slam.run.pairs import gt_errors

    kf = {c: keyframes(scene.odometry[c], spacing) for c in scene.robots}
    frame_of = {}
    db, desc = PlaceDatabase(recognizer.dim), {}
    for c in scene.robots:
        scene.render(c, kf[c])
        desc[c] = np.stack([recognizer.describe(scene.image(c, f)) for f in kf[c]])
        db.add_many(c, range(len(kf[c])), desc[c])
    seen, cands = set(), []
    for a in scene.robots:
        for b in scene.robots:
            if b != a:
                for m in db.candidates(a, range(len(kf[a])), desc[a], threshold=cfg.threshold, k=1, agents=[b]):
                    q, t = sorted([(m.query_agent, m.query_index), (m.agent, m.index)])  # lower robot queries
                    if (q, t) not in seen:
                        seen.add((q, t))
                        cands.append((q, t, m.similarity))
    reg = (registrar_cls or CachedRegistrar)(cache, frame_of)
    front = LoopFrontend(reg, lambda c, i: scene.image(c, kf[c][i]), lambda c: scene.camera, lambda c: len(kf[c]),
                         r_thr=0.0)
    for c in scene.robots:
        for i, f in enumerate(kf[c]):
            e = cache.encoding(c, f)
            frame_of[id(e)] = (c, f)
            front.put_encoding((c, i), e)
    out = []
    for q, t, sim in sorted(cands):
        meas = front.evaluate(q, t, sim)
        fq, ft = kf[q[0]][q[1]], kf[t[0]][t[1]]
        ratio = None
        if meas.odom is not None and meas.odom.n_correspondences > 0:
            ratio = correspondence_ratio(meas.loop.n_correspondences, meas.odom.n_correspondences)
        scale = 1.0
        if meas.odom_pair is not None:
            o = scene.odometry[q[0]]
            i0, i1 = (kf[q[0]][j] for j in meas.odom_pair)
            t_net = float(np.linalg.norm(meas.odom.t)) if meas.odom is not None else 0.0
            scale = float(np.linalg.norm((np.linalg.inv(o[i0]) @ o[i1])[:3, 3])) / t_net if t_net > 0 else 1.0
        cand = Candidate(q, t, (fq, ft), float(sim), bool(meas.loop.success), int(meas.loop.n_correspondences),
                         ratio, meas.T_query_match, max(scale, 1e-6))
        T_gt = np.linalg.inv(scene.gt[q[0]][fq]) @ scene.gt[t[0]][ft]
        err = gt_errors(cand.T, T_gt)
        cand.gt_distance_m = err["gt_distance_m"]
        if cand.success:
            cand.rot_err_deg, cand.t_err_m = err["rot_err_deg"], err["t_err_m_gt_scale"]
        out.append(cand)
    used = reg.used
    enc_keys = {(c, f) for c in scene.robots for f in kf[c]}
    fe_s = sum(cache.enc_s.get(k, 0.0) for k in enc_keys) + sum(cache.pair_s.get(k, 0.0) for k in used)
    return SpacingRun(spacing, kf, out, fe_s, int(sum(cache.enc[k].nbytes for k in enc_keys)),
                      recognizer.descriptor_bytes * len(enc_keys))


def accepted(cands: list[Candidate], r_thr: float, k: float | None = None) -> list[tuple[Candidate, float]]:
    """Candidates passing eq. 1's gate at `r_thr`, each with its eq. 2 confidence p (graph.confidence)."""
    from swarmsplat.graph.confidence import K_DEFAULT, loop_confidence

    out = []
    for c in cands:
        if c.success and c.ratio is not None:
            p = loop_confidence(c.ratio, k=K_DEFAULT if k is None else k, r_thr=r_thr)
            if p is not None:
                out.append((c, p))
    return out


def solve(scene: Scene, run: SpacingRun, loops: list[tuple[Candidate, float]], formulation: str, solver: str) -> dict:
    """Pose graph of all robots (the swarm optimiser's build and solve); ATE over every frame of the robots in
    the component that joins the most robots."""
    from swarmsplat.graph.pose_graph import key_robot
    from swarmsplat.slam.flocc.swarm.messages import GraphSubmission
    from swarmsplat.slam.flocc.swarm.optimiser import SolveConfig, solve_group

    rid = {c: r for r, c in enumerate(scene.robots)}
    subs = {}
    for c in scene.robots:
        mine = [(cd, p) for cd, p in loops if cd.query[0] == c]
        subs[rid[c]] = GraphSubmission(
            robot=rid[c], version=[len(run.kf[c]), 0], odometry=scene.odometry[c][run.kf[c]],
            query_robot=np.array([rid[c]] * len(mine), np.int64),
            query_index=np.array([cd.query[1] for cd, _ in mine], np.int64),
            match_robot=np.array([rid[cd.match[0]] for cd, _ in mine], np.int64),
            match_index=np.array([cd.match[1] for cd, _ in mine], np.int64),
            T_query_match=np.array([cd.T for cd, _ in mine]).reshape(-1, 4, 4),
            confidence=np.array([p for _, p in mine], float), odom_scale=np.array([cd.odom_scale for cd, _ in mine]))
    sol = solve_group(subs, SolveConfig(formulation=formulation, solver=solver))
    comp = max(sol.graph.components(), key=lambda ks: (len({key_robot(k) for k in ks}), len(ks)))
    joined = sorted({key_robot(k) for k in comp})
    est, off = {}, 0
    for c, n in zip(scene.robots, sol.counts):
        est[c] = sol.poses[off:off + n]
        off += n
    return {"ate_rmse_m": dense_ate_rmse(scene, run.kf, {c: est[c] for c in joined}), "robots_joined": len(joined),
            "joined": "".join(joined), "time_s": sol.time_s}


def dense_ate_rmse(scene: Scene, kf: dict[str, list[int]], est: dict[str, np.ndarray]) -> float:
    """ATE RMSE (m) over every frame of the robots in `est` (robot -> [K, 4, 4] keyframe estimates): each frame is
    its last keyframe's estimate composed with odometry since; one rigid alignment for all (evo's APE --align)."""
    from swarmsplat.graph.metrics import ate

    P, G = {}, {}
    for r, c in enumerate(sorted(est)):
        odo, frames = scene.odometry[c], kf[c]
        for f in range(len(odo)):
            j = int(np.searchsorted(frames, f, side="right")) - 1
            P[(r << 32) | f] = est[c][j] @ np.linalg.inv(odo[frames[j]]) @ odo[f]
            G[(r << 32) | f] = scene.gt[c][f]
    mean, std = ate(P, G)
    return float(math.hypot(mean, std))


def odometry_reference_ate(scene: Scene, robots: str) -> float:
    """ATE RMSE of the robots' raw odometry, each started at its true first pose (perfect merge, no loops)."""
    est = {c: scene.gt[c][0] @ scene.odometry[c] for c in robots}
    kf = {c: list(range(len(scene.odometry[c]))) for c in robots}
    return dense_ate_rmse(scene, kf, est)


def train_recognizer(scene: Scene, cfg: StudyConfig):
    """BoW vocabulary from ~60 of the finest spacing's keyframes spread over all robots (seed 0), as `pairs`."""
    from swarmsplat.registration.place_recognition.vlad import BoWRecognizer

    d = min(cfg.spacings)
    every = [(c, f) for c in scene.robots for f in keyframes(scene.odometry[c], d)]
    for c in scene.robots:
        scene.render(c, [f for r, f in every if r == c])
    rec = BoWRecognizer(n_clusters=cfg.vocabulary)
    rec.fit([scene.image(c, f) for c, f in every[:: max(1, len(every) // 60)]], seed=0)
    return rec


def fig5_row(scene: Scene, run: SpacingRun, backend: str, r_thr: float, cfg: StudyConfig) -> dict:
    reg = [c for c in run.candidates if c.success]
    acc = accepted(run.candidates, r_thr)
    n_odom = [c.n_corr / c.ratio for c in run.candidates if c.ratio]
    wrong = [c.ratio for c in reg if c.ratio is not None and not c.correct_strict]
    row = {"backend": backend, "spacing_m": run.spacing, "keyframes": sum(map(len, run.kf.values())),
           "candidates": len(run.candidates), "registered": len(reg), "r_thr": r_thr, "loops": len(acc),
           "correct_2m": sum(c.correct_2m for c, _ in acc), "correct_strict": sum(c.correct_strict for c, _ in acc),
           "n_odom_median": float(np.median(n_odom)) if n_odom else float("nan"),
           "ratio_wrong_max": max(wrong) if wrong else float("nan"),
           "frontend_s": run.frontend_s, "kB_per_robot": run.encoding_bytes / 1e3 / len(scene.robots),
           "descriptor_kB_per_robot": run.descriptor_bytes / 1e3 / len(scene.robots)}
    for key, sel in (("wrong_by_pair", [c for c, _ in acc if not c.correct_strict]),
                     ("correct_by_pair", [c for c, _ in acc if c.correct_strict])):
        pairs = ["".join(sorted(c.query[0] + c.match[0])) for c in sel]  # unordered robot pair, e.g. "ad"
        row[key] = " ".join(f"{k}:{pairs.count(k)}" for k in sorted(set(pairs))) or "-"
    row["outliers_2m"] = row["loops"] - row["correct_2m"]
    row["outliers_strict"] = row["loops"] - row["correct_strict"]
    for label, form, solver in FORMULATIONS:
        if solver == "gnc" and not cfg.gnc:
            continue
        s = solve(scene, run, acc, form, solver)
        row[f"ate_{label}"], row[f"time_{label}"] = s["ate_rmse_m"], s["time_s"]
        row["joined"] = s["joined"]
    row["ate_odometry"] = odometry_reference_ate(scene, row["joined"])
    return row


def sweep_rows(scene: Scene, runs: list[SpacingRun], backend: str) -> list[dict]:
    """R_thr vs loops, precision, recall (pooled over spacings; recall against every correctly registered
    candidate, room-scale criterion) and IS-LM ATE per spacing."""
    pool = [c for r in runs for c in r.candidates if c.success and c.ratio is not None]
    n_true = sum(c.correct_strict for c in pool)
    rows = []
    for thr in R_THR_SWEEP:
        acc = [c for r in runs for c, _ in accepted(r.candidates, thr)]
        ok, ok2 = sum(c.correct_strict for c in acc), sum(c.correct_2m for c in acc)
        row = {"backend": backend, "r_thr": thr, "loops": len(acc), "correct_strict": ok, "correct_2m": ok2,
               "n_true": n_true, "precision_strict": ok / len(acc) if acc else float("nan"),
               "recall_strict": ok / max(n_true, 1), "precision_2m": ok2 / len(acc) if acc else float("nan")}
        for r in runs:
            row[f"ate_IS-LM@{r.spacing:g}m"] = solve(scene, r, accepted(r.candidates, thr), "is", "lm")["ate_rmse_m"]
        rows.append(row)
    return rows


def ratio_distribution(runs: list[SpacingRun]) -> dict:
    """Percentiles (10, 50, 90, max) of eq. 1's ratio for correct and wrong registrations (room-scale criterion)."""
    pool = [c for r in runs for c in r.candidates if c.success and c.ratio is not None]
    out = {}
    for name, sel in (("correct", [c.ratio for c in pool if c.correct_strict]),
                      ("wrong", [c.ratio for c in pool if not c.correct_strict])):
        out[name] = {"n": len(sel), **({f"p{q}": float(np.percentile(sel, q)) for q in (10, 50, 90)} if sel else {}),
                     "max": float(max(sel)) if sel else float("nan")}
    return out


def study(cfg: StudyConfig, backends=DEFAULT_ROWS, log=print) -> dict:
    """The whole study over `cfg.seeds`: {"fig5": rows, "r_thr": rows, "ratios": backend -> seed -> percentiles,
    "scenes": seed -> path lengths, "config", "render_s"}; rows carry their "seed"."""
    out = {"fig5": [], "r_thr": [], "ratios": {}, "scenes": {}, "render_s": 0.0,
           "config": cfg.__dict__ | {"spacings": list(cfg.spacings), "seeds": list(cfg.seeds)}}
    missing = {}
    for seed in cfg.seeds:
        scene = Scene(cfg, seed)
        rec = train_recognizer(scene, cfg)
        out["scenes"][seed] = {"path_m": {c: float(np.linalg.norm(np.diff(scene.gt[c][:, :3, 3], axis=0),
                                                                 axis=1).sum()) for c in scene.robots},
                               "generator": scene.gen.model_dump(mode="json")}
        for name, reg, why in registrars(backends):
            if reg is None:
                missing[name] = why
                continue
            cache = FrameCache(reg, scene)
            r_thr = cfg.r_thr if cfg.r_thr is not None else R_THR_STUDY.get(name.split("-")[0], 0.3)
            runs = []
            for d in cfg.spacings:
                runs.append(run_spacing(scene, cache, rec, d, cfg))
                row = {"seed": seed, **fig5_row(scene, runs[-1], name, r_thr, cfg)}
                out["fig5"].append(row)
                log(f"[fig5] seed {seed} {name} d={d:g} m: {row['keyframes']} kf, {row['candidates']} cand, "
                    f"{row['loops']} loops ({row['outliers_strict']} wrong), ATE IS-LM {row['ate_IS-LM']:.3f} m, "
                    f"front-end {row['frontend_s']:.1f} s")
            out["r_thr"] += [{"seed": seed, **r} for r in sweep_rows(scene, runs, name)]
            out["ratios"].setdefault(name, {})[seed] = ratio_distribution(runs)
        out["render_s"] += scene.render_s
    for name, why in missing.items():
        out["fig5"].append({"backend": name, "status": f"not available: {why}"})
        log(f"[fig5] {name}: not available: {why}")
    return out

COLUMNS = ["backend", "seed", "spacing_m", "keyframes", "candidates", "registered", "r_thr", "loops", "outliers_2m",
           "outliers_strict", "ate_base-LM", "ate_IS-LM", "ate_base-GNC", "ate_odometry", "frontend_s", "status"]


def run(*, backends: list[str], device: str, quick: bool) -> dict:
    """`python -m perf fig5` entry: the Fig. 5 rows (kernel backends and device do not affect OpenCV/GTSAM)."""
    cfg = StudyConfig.quick() if quick else StudyConfig()
    res = study(cfg, log=lambda m: print(m, file=sys.stderr))
    return {"rows": res["fig5"], "columns": COLUMNS,
            "notes": [f"load average at end {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; kernel backends "
                      f"{backends} / device {device!r} unused (OpenCV + GTSAM on the CPU)",
                      "R_thr sweep: python -m perf.flocc_fig5 --json OUT --md OUT"]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m perf.flocc_fig5", description=__doc__.splitlines()[0])
    p.add_argument("--json", dest="json_out", help="write the results here")
    p.add_argument("--md", dest="md_out")
    p.add_argument("--from-json", help="only re-render the Markdown of an earlier --json file")
    p.add_argument("--quick", action="store_true", help="one seed, 2 laps of 200 frames, spacings 0.2-1.6 m")
    p.add_argument("--seeds", type=int, nargs="+")
    p.add_argument("--agents", type=int, help="robots per team (default 4; slots 3+ of the generator's layout look "
                                              "the opposite way, 4 and 5 face each other)")
    p.add_argument("--spacings", type=float, nargs="+", help="keyframe spacings in metres of odometry path")
    p.add_argument("--r-thr", type=float, help="gate of the Fig. 5 rows (default per backend: classical 0.15)")
    p.add_argument("--orb", action="store_true", help="also run the classical backend with ORB features")
    p.add_argument("--backends", nargs="+", metavar="NAME",
                   help="rows to run: classical, classical-orb, xfeat, lightglue-disk, mast3r (default: classical, "
                        "with --orb also classical-orb; learned rows need their package or weights)")
    p.add_argument("--no-gnc", action="store_true")
    args = p.parse_args(argv)

    from swarmsplat.kernels.errors import InputError
    from .common import machine_info, write_results
    from .flocc_fig5_report import header, markdown

    if args.from_json:
        with open(args.from_json) as f:
            res = json.load(f)
    else:
        if not args.json_out:
            raise InputError("--json OUT is required (or --from-json IN to re-render the Markdown)")
        kw = {k: v for k, v in dict(seeds=tuple(args.seeds) if args.seeds else None, r_thr=args.r_thr,
                                    agents=args.agents,
                                    spacings=tuple(args.spacings) if args.spacings else None).items() if v is not None}
        cfg = (StudyConfig.quick if args.quick else StudyConfig)(**kw, gnc=not args.no_gnc)
        load0 = os.getloadavg()
        t0, c0 = time.perf_counter(), time.process_time()
        names = tuple(args.backends) if args.backends else (DEFAULT_ROWS[:1] + ("classical-orb",) * args.orb
                                                             + DEFAULT_ROWS[1:])
        res = study(cfg, names, log=lambda m: print(m, file=sys.stderr))
        res.update(machine=machine_info(), wall_s=time.perf_counter() - t0, cpu_s=time.process_time() - c0,
                   command="python -m perf.flocc_fig5 " + " ".join(argv if argv is not None else sys.argv[1:]),
                   load_start=load0[0], load_end=os.getloadavg()[0])
        write_results(args.json_out, None, res)
    text = header(res) + markdown(res)
    print(text)
    write_results(None, args.md_out, res, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
