"""`swarmsplat pairs DATASET --out CSV`: loop-closure candidates of a multi-agent dataset, registered and scored."""

from __future__ import annotations

import argparse


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
    p.add_argument("--backend", default="classical", metavar="NAME",
                   help="pair registration: classical, xfeat, mast3r or lightglue (default: classical)")
    p.add_argument("--place", default="bow", metavar="NAME",
                   help="place recognition: bow, vlad, xfeat-vlad, cosplace or netvlad (default: bow, vocabulary "
                        "trained on the dataset)")
    p.add_argument("--checkpoint", default=None, metavar="PATH", help="weights of the pair backend (mast3r)")
    p.add_argument("--place-checkpoint", default=None, metavar="PATH",
                   help="weights of cosplace/netvlad, or a bow/vlad vocabulary .npz")
    p.add_argument("--save-vocabulary", default=None, metavar="NPZ", help="save the bow/vlad/xfeat-vlad vocabulary trained here")
    p.add_argument("--threshold", type=float, default=0.1,
                   help="cosine similarity threshold (default: 0.1, the paper's permissive value)")
    p.add_argument("--top-k", type=int, default=1, help="neighbours per keyframe (default: 1)")
    p.add_argument("--stride", type=int, default=1, help="every N-th frame is a keyframe (default: 1)")
    p.add_argument("--r-thr", type=float, default=None, help="correspondence-ratio gate R_thr of eq. 1 (default per pair backend: classical 0.15, xfeat 0.25, measured in perf/results/fig5-*.md; mast3r and others 0.3 as the paper)")
    p.add_argument("--k", type=float, default=None, help="logistic steepness k of eq. (2) (default: graph's)")
    p.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help="torch device of learned backends")
    p.add_argument("--trust-checkpoint", action="store_true",
                   help="let the MASt3R loader unpickle more than tensors (only for a checkpoint from a trusted source)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--strict", action="store_true",
                   help="stop at the first unreadable keyframe image (default: leave it out with a warning; "
                        "pairs.csv -> pairs.metrics.json lists it under skipped_frames)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from swarmsplat.slam.run.pairs import run_pairs

    summary = run_pairs(args.dataset, args.out, backend=args.backend, place=args.place, checkpoint=args.checkpoint,
                        place_checkpoint=args.place_checkpoint, threshold=args.threshold, top_k=args.top_k,
                        stride=args.stride, r_thr=args.r_thr, k=args.k, vocabulary_out=args.save_vocabulary,
                        device=args.device, trust_checkpoint=args.trust_checkpoint, progress=not args.quiet,
                        strict=args.strict)
    print(summary.line())
    return 0
