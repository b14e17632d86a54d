"""`swarmsplat view RUN [--port 8080] [--host 127.0.0.1] [--screenshot PNG]`: a browser viewer of a run folder
(merged Gaussian map as splats, trajectories, keyframe frusta, loop edges, metrics); with --screenshot, a PNG of
the page from headless Chromium instead of serving."""

from __future__ import annotations

import sys


def add_viewer_flags(p, *, default_port: int | None = 8080) -> None:
    """--port / --host, shared by `view` and the --view flag of `run` and `demo`."""
    p.add_argument("--port", type=int, default=default_port,
                   help="viewer port (default: 8080" + ("; with --screenshot any free port)" if default_port is None
                                                         else ")"))
    p.add_argument("--host", default="127.0.0.1",
                   help="address the viewer listens on (default: 127.0.0.1; 0.0.0.0 for every interface)")


def add_live_view_flags(p) -> None:
    """--view (with --port / --host) for the commands that run SLAM."""
    p.add_argument("--view", action="store_true",
                   help="show the growing map, poses and loops in a browser viewer during the run (the view extra); "
                        "it keeps serving the finished run until Ctrl-C")
    add_viewer_flags(p)


def live_view(args):
    """The live-view observer for `--view`, or None. Starts the viewer now, so a taken port fails first."""
    if not getattr(args, "view", False):
        return None
    from swarmsplat.slam.view.live import LiveView
    from swarmsplat.slam.view.server import Viewer

    viewer = Viewer(args.host, args.port)
    print(f"viewer: {viewer.url}  (live; Ctrl-C after the run to stop)", file=sys.stderr, flush=True)
    return LiveView(viewer)


def serve_result(live, out) -> int:
    """After a `--view` run: show the finished run from `out` and serve it until Ctrl-C. Returns 0."""
    if live is not None:
        sys.stdout.flush()  # the summary, before serving for as long as the user likes
        live.serve_result(out)
    return 0


def register(sub) -> None:
    p = sub.add_parser("view", help="browse a run's Gaussian map, trajectories and loop closures (viser)",
                       description="Serve a web viewer of a run folder (what `run` or `demo` wrote): the merged "
                                   "Gaussian map as splats (map.ply), per-agent trajectories with and without loop "
                                   "closures and ground truth when the dataset is still there, keyframe frusta, "
                                   "accepted intra- and inter-agent loop edges, and the run's metrics. Needs the "
                                   "view extra (pip install -e '.[view]').")
    p.add_argument("run", metavar="RUN", help="run folder (with metrics.json and map.ply, or a demo folder with "
                                              "results/)")
    add_viewer_flags(p, default_port=None)
    p.add_argument("--screenshot", metavar="PNG",
                   help="load the page in headless Chromium, wait until the splats are drawn, write PNG and exit")
    p.add_argument("--timeout", type=float, default=300.0, help="seconds --screenshot waits for the page "
                                                                "(default: 300)")
    p.set_defaults(func=run)


def run(args) -> int:
    from swarmsplat.slam.view.run_folder import check_run, load_scene
    from swarmsplat.slam.view.server import Viewer

    check_run(args.run)  # a folder that is not a run, or has no map, fails first
    if args.screenshot:
        from swarmsplat.slam.view.screenshot import require_browser, take_screenshot

        require_browser()  # before a server starts
        with Viewer(args.host, args.port if args.port is not None else 0) as viewer:
            viewer.show(load_scene(args.run))
            out = take_screenshot(viewer, args.screenshot, timeout=args.timeout)
        print(out)
        return 0
    viewer = Viewer(args.host, args.port if args.port is not None else 8080)
    try:
        scene = load_scene(args.run)
        viewer.show(scene)
        s = scene.summary()
        print(f"viewer: {viewer.url}  ({s['gaussians']} Gaussians, {s['keyframes']} keyframes; Ctrl-C to stop)",
              file=sys.stderr, flush=True)
        viewer.wait()
    finally:
        viewer.close()
    return 0
