"""`swarmsplat swarm DATASET --out DIR [--config YAML] [--preset NAME] [--formulation is|ss|base|shared]
[--solver lm|gnc] [--schedule YAML] [--processes]`: every robot of a monocular dataset, exchanging descriptors,
encodings, loops, graphs and estimates on a rendezvous schedule — in one process (simulated network) or one process
per robot over Zenoh. The settings are the config tree's `swarm` section; config.yaml in DIR records them."""

from __future__ import annotations

from swarmsplat.slam.cli.config_flags import add_config_flags


def add_swarm_options(p) -> None:
    """Options shared by `swarm` and `robot`: each overrides its key of the config file's swarm section."""
    p.add_argument("dataset", help="monocular multi-agent dataset root (dataset.yaml)")
    p.add_argument("--out", required=True, help="output folder")
    add_config_flags(p)
    p.add_argument("--formulation", choices=["is", "ss", "base", "shared"],
                   help="pose-graph formulation for up-to-scale loops (default: is)")
    p.add_argument("--solver", choices=["lm", "gnc", "distributed"],
                   help="Levenberg-Marquardt or GNC on the elected robot (default: lm), or distributed: every robot "
                        "solves its own part")
    p.add_argument("--uniform-noise", action="store_true", default=None,
                   help="Swarm-SLAM-like baseline: one noise for every factor, confidences ignored")
    p.add_argument("--schedule", metavar="YAML", help="rendezvous schedule (default: pairs meet while recording, "
                                                       "everyone at the end)")
    p.add_argument("--stride", type=int, help="every stride-th frame is a keyframe (default: 4)")
    p.add_argument("--place", help="place recognition: bow, vlad, xfeat-vlad, cosplace, netvlad (default: bow)")
    p.add_argument("--place-checkpoint", metavar="PATH", help="weights, or a bow/vlad vocabulary .npz")
    p.add_argument("--backend", help="pair registration: classical, xfeat, mast3r, lightglue (default: classical)")
    p.add_argument("--r-thr", type=float, help="correspondence-ratio gate R_thr of eq. 1 (default per pair backend: "
                                               "classical 0.15, xfeat 0.25; mast3r and others 0.3 as the paper)")
    p.add_argument("--k", type=float, help="logistic steepness k of eq. 2 (default 5)")
    p.add_argument("--strict", action="store_true", default=None,
                   help="stop at the first unreadable keyframe image (default: skip it with a warning; "
                        "metrics.json lists it under skipped_frames)")
    p.add_argument("--port-base", type=int, help="Zenoh: robot K listens on port-base + K (default: 17447)")


def swarm_config(args):
    """The config tree of `swarm` / `robot`: --preset, then --config, then the swarm flags given."""
    from swarmsplat.slam.cli.config_flags import load_config, section_flags

    flags = section_flags(args, "swarm", ("formulation", "solver", "uniform_noise", "schedule", "stride", "place",
                                          "place_checkpoint", "backend", "r_thr", "k", "strict", "port_base"))
    return load_config(args.config, flags, preset=args.preset, sets=args.config_set)


def register(sub) -> None:
    p = sub.add_parser("swarm", help="decentralised FLOCC-SLAM loop closing over all robots of a mono dataset")
    add_swarm_options(p)
    p.add_argument("--processes", action="store_true", help="one robot process each, over Zenoh on this machine")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def run(args) -> int:
    cfg = swarm_config(args)
    if args.processes:
        from swarmsplat.slam.run.swarm_processes import launch

        m = launch(args.dataset, args.out, cfg)
    else:
        from swarmsplat.slam.run.swarm import run_swarm

        m = run_swarm(args.dataset, args.out, cfg, progress=not args.quiet)
    ate, odo = m.get("ate", {}), m.get("odometry_only_ate", {})
    loops = m.get("loop_closures", {}).get("count", 0)
    sent = {k: v["sent_total"] for k, v in m["bytes"].items()}
    if ate:
        print(f"merged ATE {ate['merged_rmse']:.4f} m (odometry only {odo['merged_rmse']:.4f} m), {loops} loops")
    print("bytes sent per robot: " + ", ".join(f"{k} {v}" for k, v in sent.items()))
    for name, end in (m.get("end") or {}).items():
        if end and end["status"] != "complete":
            print(f"{name}: the end protocol timed out (swarm.end_timeout); robots not heard from: "
                  f"{end['missing'] or 'none'}")
    print(f"wrote {args.out}")
    return 0
