"""Markdown for the Fig. 5 study (perf/flocc_fig5.py): the results file's header, the keyframe-spacing table and
the R_thr table, from the study's result dict (also re-rendered from its JSON with `--from-json`)."""

from __future__ import annotations

import math

import numpy as np

from .flocc_fig5 import FORMULATIONS, OUTLIER_M, STRICT_ROT_DEG, STRICT_T_M


def _f(v, nd=3) -> str:
    return "—" if v is None or (isinstance(v, float) and not math.isfinite(v)) else (
        f"{v:.{nd}f}" if isinstance(v, float) else str(v))


def markdown(res: dict) -> str:
    """The Fig. 5 table (one row per backend x spacing, summed / averaged over seeds) and the R_thr table."""
    forms = [f for f, _, s in FORMULATIONS if s != "gnc" or res["config"]["gnc"]]
    head = ["backend", "spacing (m)", "keyframes", "candidates", "registered", "odometry-pair corr. (median)",
            "wrong ratio (max)", "R_thr", "loops",
            "wrong (2 m / strict)", *[f"ATE {f} (m)" for f in forms], "ATE odometry*", "front-end (s)",
            "solve (s) " + " / ".join(forms), "encodings kB/robot", "joined", "wrong loops by robot pair",
            "correct loops by robot pair"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    groups: dict[tuple, list[dict]] = {}
    for r in res["fig5"]:
        groups.setdefault((r["backend"], r.get("spacing_m")), []).append(r)
    for (b, d), rs in groups.items():
        if "status" in rs[0]:
            lines.append(f"| {b} | {rs[0]['status']} |" + " |" * (len(head) - 2))
            continue
        s = lambda k: sum(r[k] for r in rs)  # noqa: E731
        m = lambda k: _ms([r[k] for r in rs])  # noqa: E731
        lines.append("| " + " | ".join([b, f"{d:g}", str(s("keyframes")), str(s("candidates")), str(s("registered")),
                                        f"{np.median([r['n_odom_median'] for r in rs]):.0f}",
                                        _f(max([r["ratio_wrong_max"] for r in rs if r["ratio_wrong_max"] >= 0],
                                               default=float("nan")), 2),
                                        f"{rs[0]['r_thr']:g}", str(s("loops")),
                                        f"{s('outliers_2m')} / {s('outliers_strict')}",
                                        *[m(f"ate_{f}") for f in forms], m("ate_odometry"), f"{s('frontend_s'):.1f}",
                                        " / ".join(f"{s(f'time_{f}'):.2f}" for f in forms),
                                        f"{np.mean([r['kB_per_robot'] for r in rs]):.0f}",
                                        " / ".join(r["joined"] for r in rs),
                                        " / ".join(r.get("wrong_by_pair", "?") for r in rs),
                                        " / ".join(r.get("correct_by_pair", "?") for r in rs)]) + " |")
    sw_keys = sorted({k for r in res["r_thr"] for k in r if k.startswith("ate_")},
                     key=lambda k: float(k.split("@")[1][:-1]))
    h2 = ["backend", "R_thr", "loops", "precision (strict)", "recall (strict)", "precision (2 m)", *sw_keys]
    l2 = ["| " + " | ".join(h2).replace("ate_IS-LM@", "ATE IS-LM @") + " |", "|" + "---|" * len(h2)]
    sw: dict[tuple, list[dict]] = {}
    for r in res["r_thr"]:
        sw.setdefault((r["backend"], r["r_thr"]), []).append(r)
    nan = float("nan")
    for (b, t), rs in sw.items():
        loops, ok, ok2, true = (sum(r[k] for r in rs) for k in ("loops", "correct_strict", "correct_2m", "n_true"))
        l2.append("| " + " | ".join([b, f"{t:g}", str(loops), _f(ok / loops if loops else nan),
                                     _f(ok / true if true else nan), _f(ok2 / loops if loops else nan),
                                     *[_ms([r[k] for r in rs if k in r]) for k in sw_keys]]) + " |")
    dist = []
    for b, per_seed in res["ratios"].items():
        for seed, d in per_seed.items():
            dist.append(f"- {b}, seed {seed}: ratio of correct registrations (n={d['correct']['n']}) p10/p50/p90 "
                        f"{_f(d['correct'].get('p10'))}/{_f(d['correct'].get('p50'))}/{_f(d['correct'].get('p90'))}; "
                        f"wrong (n={d['wrong']['n']}) {_f(d['wrong'].get('p10'))}/{_f(d['wrong'].get('p50'))}/"
                        f"{_f(d['wrong'].get('p90'))}")
    return ("#### Keyframe spacing (Fig. 5)\n\n" + "\n".join(lines) +
            "\n\n*ATE odometry: each robot's raw odometry started at its true first pose (a perfect merge with no "
            "loop correction), for the robots the IS-LM graph joins.*\n\n#### Correspondence-ratio gate R_thr "
            "(pooled over spacings; ATE IS-LM per spacing)\n\n" + "\n".join(l2) + "\n\n" + "\n".join(dist) + "\n")


def _ms(v: list[float]) -> str:
    v = [x for x in v if x is not None and math.isfinite(x)]
    if not v:
        return "—"
    return f"{np.mean(v):.3f}" if len(v) == 1 else f"{np.mean(v):.3f} ± {np.std(v):.3f}"


def header(res: dict) -> str:
    """The results file's first paragraph: command, time, load and the setting (from the result dict)."""
    c, paths = res["config"], [m for v in res["scenes"].values() for m in v["path_m"].values()]
    return (f"`{res['command']}`: {res['wall_s'] / 60:.1f} min wall, {res['cpu_s'] / 60:.1f} min process CPU "
            f"(rendering {res['render_s']:.0f} s), 1-minute load average {res['load_start']:.1f} at start / "
            f"{res['load_end']:.1f} at end on {res['machine']['cpu_count']} CPUs. Seeds {c['seeds']}, {c['agents']} "
            f"robots x {c['frames']} frames ({c['loop_turns']:g} laps, {c['width']}x{c['height']}), "
            f"BoW-{c['vocabulary']} place recognition at cosine >= {c['threshold']:g}; path per robot "
            f"{min(paths):.1f}-{max(paths):.1f} m. Wrong loop: translation error > {OUTLIER_M:g} m after scaling "
            f"with ground truth (paper) / rotation error > {STRICT_ROT_DEG:g} deg or translation error > "
            f"{STRICT_T_M:g} m (strict). ATE: RMSE over every frame of the robots the graph joins (column "
            f"'joined', per seed), mean ± std over seeds. Front-end time: the encode + register calls the "
            f"spacing needs (each measured once).\n\n")
