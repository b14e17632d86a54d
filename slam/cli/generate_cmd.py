"""`swarmsplat generate --out DIR [--preset NAME] [--agents N] [--frames N] ...`: write a synthetic dataset."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("generate", help="write a synthetic multi-agent RGB-D (or monocular) dataset",
                       description="Render a procedural indoor world seen by several agents and write it in "
                                   "swarmsplat's folder format (dataset.yaml + one folder per agent).")
    p.add_argument("--out", help="output folder (created; an existing dataset there is replaced)")
    p.add_argument("--preset", default="default", help="settings preset: tiny, default or large (default: default)")
    p.add_argument("--agents", type=int, help="number of agents, 1-6")
    p.add_argument("--frames", type=int, help="frames per agent")
    p.add_argument("--width", type=int, help="image width in pixels")
    p.add_argument("--height", type=int, help="image height in pixels")
    p.add_argument("--fps", type=float, help="frame rate (sets timestamps)")
    p.add_argument("--seed", type=int, help="random seed: the same seed and settings give identical files")
    p.add_argument("--supersample", type=int, metavar="S",
                   help="rays per pixel side, 1-8: colour is the mean of S x S rays over the pixel, depth the "
                        "centre ray's (default 2; 1 = one ray through the pixel centre, which aliases)")
    p.add_argument("--mono", action="store_true", default=None,
                   help="monocular variant: images + drifting metric odometry, no depth")
    p.add_argument("--preview", metavar="PNG", help="also save a top-down picture of the world and the paths")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def run(args) -> int:
    import sys

    from swarmsplat.kernels.errors import InputError
    from swarmsplat.kernels.fileio import output_dir, output_file
    from swarmsplat.slam.synthetic import GeneratorConfig, agent_poses, generate, generate_world
    from swarmsplat.slam.io.progress import bar
    from swarmsplat.slam.synthetic.writer import check_output_dir

    if not args.out and not args.preview:
        raise InputError("give --out DIR (and/or --preview PNG)")
    config = GeneratorConfig.preset(args.preset, agents=args.agents, frames=args.frames, width=args.width,
                                    height=args.height, fps=args.fps, seed=args.seed, mono=args.mono,
                                    supersample=args.supersample)
    if args.out:  # a file in the way or an unwritable place: one line before any rendering
        output_dir(args.out, "--out", create=False)
    if args.preview:
        output_file(args.preview, "--preview", create=False)
        from swarmsplat.slam.synthetic.preview import plot_world

        world = generate_world(config.seed, config.world)
        plot_world(world, agent_poses(world, config), args.preview)
        print(f"wrote {args.preview}", file=sys.stderr)
    if args.out:
        check_output_dir(args.out)  # before the progress bar, so a refusal is one clean line
        total = config.agents * config.frames
        with bar(total, f"[generate] {config.kind} frames", unit="frame", enabled=not args.quiet) as b:
            out = generate(args.out, config, progress=b.update)
        print(f"wrote {config.kind} dataset '{config.name}' with {config.agents} agents x {config.frames} frames "
              f"({config.width}x{config.height}, seed {config.seed}) to {out}")
    return 0
