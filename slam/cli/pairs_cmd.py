"""`swarmsplat pairs DATASET --out CSV [--config YAML] [--preset NAME]`: loop-closure candidates of a multi-agent
dataset, registered and scored. The settings are the config tree's `pairs` section (flags override the file); the
tree used is written beside the CSV (pairs.csv -> pairs.config.yaml)."""

from __future__ import annotations

import argparse

from swarmsplat.slam.cli.config_flags import add_config_flags


def register(sub) -> None:
    p = sub.add_parser(
        "pairs",
        help="place recognition + image-pair registration over a dataset, every candidate to CSV",
        description="For every keyframe of every agent, find its nearest neighbour among the other agents' "
                    "keyframes (cosine similarity of global descriptors), register the pair and the query's "
                    "odometry pair, and write similarity, correspondence counts, ratio, confidence p, the relative "
                    "pose (unit translation) and, with ground truth, its errors, as CSV.",
    )
    p.add_argument("dataset", help="dataset root (dataset.yaml) or a folder of agent sequences")
    p.add_argument("--out", required=True, metavar="CSV", help="where to write the candidates")
    add_config_flags(p)
    p.add_argument("--backend", metavar="NAME",
                   help="pair registration: classical, xfeat, mast3r or lightglue (default: classical)")
    p.add_argument("--place", metavar="NAME",
                   help="place recognition: bow, vlad, xfeat-vlad, cosplace or netvlad (default: bow, vocabulary "
                        "trained on the dataset)")
    p.add_argument("--checkpoint", metavar="PATH", help="weights of the pair backend (mast3r)")
    p.add_argument("--place-checkpoint", metavar="PATH",
                   help="weights of cosplace/netvlad, or a bow/vlad vocabulary .npz")
    p.add_argument("--save-vocabulary", default=None, metavar="NPZ", help="save the bow/vlad/xfeat-vlad vocabulary trained here")
    p.add_argument("--threshold", type=float,
                   help="cosine similarity threshold (default: 0.1, the paper's permissive value)")
    p.add_argument("--top-k", type=int, help="neighbours per keyframe (default: 1)")
    p.add_argument("--stride", type=int, help="every N-th frame is a keyframe (default: 1)")
    p.add_argument("--r-thr", type=float, help="correspondence-ratio gate R_thr of eq. 1 (default per pair backend: "
                                               "classical 0.15, xfeat 0.25; mast3r and others 0.3 as the paper)")
    p.add_argument("--k", type=float, help="logistic steepness k of eq. (2) (default: graph's)")
    p.add_argument("--device", choices=["cpu", "cuda"], help="torch device of learned backends (default: cpu)")
    p.add_argument("--trust-checkpoint", action="store_true",
                   help="let the MASt3R loader unpickle more than tensors (only for a checkpoint from a trusted source)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--strict", action="store_true", default=None,
                   help="stop at the first unreadable keyframe image (default: leave it out with a warning; "
                        "pairs.csv -> pairs.metrics.json lists it under skipped_frames)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from swarmsplat.slam.cli.config_flags import load_config, section_flags
    from swarmsplat.slam.run.pairs import run_pairs

    flags = section_flags(args, "pairs", ("backend", "place", "checkpoint", "place_checkpoint", "threshold", "top_k",
                                          "stride", "r_thr", "k", "device", "strict"))
    cfg = load_config(args.config, flags, preset=args.preset, sets=args.config_set)
    summary = run_pairs(args.dataset, args.out, cfg, vocabulary_out=args.save_vocabulary,
                        trust_checkpoint=args.trust_checkpoint, progress=not args.quiet)
    print(summary.line())
    return 0
