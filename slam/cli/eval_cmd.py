"""`swarmsplat eval`: ATE and RPE of an estimated trajectory against ground truth, as a table, JSON and a plot."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser(
        "eval",
        help="trajectory accuracy (ATE, RPE) of an estimate against ground truth",
        description="Compute ATE RMSE (after SE(3)/Sim(3) Umeyama alignment) and RPE of an estimated trajectory "
                    "against ground truth. Numbers equal evo's evo_ape/evo_rpe with the same settings.",
    )
    p.add_argument("--gt", required=True, metavar="FILE",
                   help="ground-truth trajectory file, or a dataset / folder of <agent>.txt files for a team")
    p.add_argument("--est", required=True, metavar="FILE",
                   help="estimated trajectory file, or a results folder of <agent>.txt files for a team")
    # Formats and alignment are validated by the library (one-line InputError) rather than argparse choices.
    p.add_argument("--format", default="auto", metavar="FMT",
                   help="trajectory format of both files: tum, kitti, euroc, log or auto (default: auto)")
    p.add_argument("--gt-format", default=None, metavar="FMT", help="format of --gt only (overrides --format)")
    p.add_argument("--est-format", default=None, metavar="FMT", help="format of --est only (overrides --format)")
    p.add_argument("--align", default="se3", metavar="MODE", help="se3, sim3 (monocular) or none (default: se3)")
    p.add_argument("--max-diff", type=float, default=0.01, metavar="S",
                   help="timestamp association tolerance in seconds (default: 0.01, as evo)")
    p.add_argument("--delta", type=int, default=1, metavar="N", help="RPE frame distance (default: 1)")
    p.add_argument("--json", default=None, metavar="OUT", help="write the metrics as JSON here (and a plot beside it)")
    p.add_argument("--plot", default=None, metavar="PNG", help="trajectory plot path (default: OUT with .png)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from swarmsplat.kernels.errors import InputError
    from swarmsplat.kernels.fileio import atomic_write_text, output_file

    for flag, path in (("--json", args.json), ("--plot", args.plot)):
        if path:
            output_file(path, flag, create=False)
    team = Path(args.gt).is_dir() or Path(args.est).is_dir()
    if team and not (Path(args.gt).is_dir() and Path(args.est).is_dir()):
        raise InputError("--gt and --est must both be files (one trajectory) or both folders (a team)")
    ev = _evaluate_team(args) if team else _evaluate_one(args)
    print(ev.table())
    plot = Path(args.plot) if args.plot else (Path(args.json).with_suffix(".png") if args.json else None)
    report = ev.to_dict()
    if plot is not None:
        ev.plot(plot)
        report["plot"] = str(plot)
        print(f"plot: {plot}")
    if args.json:
        atomic_write_text(args.json, json.dumps(report, indent=2) + "\n")
        print(f"metrics: {args.json}")
    return 0


def _evaluate_one(args):
    from swarmsplat.slam.metrics.evaluate import evaluate_trajectories
    from swarmsplat.slam.io.trajectory import read_trajectory

    gt = read_trajectory(args.gt, args.gt_format or args.format)
    est = read_trajectory(args.est, args.est_format or args.format)
    return evaluate_trajectories(gt, est, align=args.align, max_diff=args.max_diff, delta=args.delta)


def _evaluate_team(args):
    from swarmsplat.slam.metrics.team import evaluate_team, find_team_trajectories

    gt, est = find_team_trajectories(args.gt, args.est, args.est_format or args.format)
    return evaluate_team(gt, est, align=args.align, max_diff=args.max_diff, delta=args.delta)
