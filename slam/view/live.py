"""Live view: the observer `run_sequence(observer=...)` / `run_team(observer=...)` call with the agent or team
after every frame / round. It redraws the viewer at most every `interval` seconds, and only when something
changed (frames, keyframes, Gaussians, loops), so a long run spends little time on it.

    viewer = Viewer(port=8080)
    live = LiveView(viewer)
    run_team(data, out, cfg, observer=live)
    live.finish(out)          # the finished run, read back from its folder (ground truth, metrics panel)
"""

from __future__ import annotations

import sys
import time

from .state import scene_from_state


def _signature(state) -> tuple:
    """What changes when there is something new to draw."""
    if hasattr(state, "server"):
        srv = state.server
        return (sum(state.frames_done), sum(len(a.keyframes) for a in state.agents),
                sum(len(a.gmap) for a in state.agents), len(srv.records), srv.optimisations)
    return (len(state.poses), len(state.keyframes), len(state.gmap), len(state.loops.log))


class LiveView:
    def __init__(self, viewer, *, interval: float = 2.0, title: str = "swarmsplat: live"):
        self.viewer, self.interval, self.title = viewer, interval, title
        self.updates = 0
        self._last = -float("inf")
        self._sig = None
        self._broken = False

    def __call__(self, state, *, force: bool = False) -> bool:
        """Redraw from `state` (a Team or an Agent) when due; True when it did."""
        now = time.monotonic()
        if self._broken or (not force and now - self._last < self.interval):
            return False
        sig = _signature(state)
        if sig == self._sig and not force:
            return False
        try:
            self.viewer.show(scene_from_state(state, self.title))
        except Exception as e:  # noqa: BLE001 - the run matters more than its picture
            self._broken = True
            print(f"live view stopped: {type(e).__name__}: {e}", file=sys.stderr)
            return False
        self._last, self._sig = time.monotonic(), sig
        self.updates += 1
        return True

    def finish(self, run_folder) -> None:
        """Show the finished run as `swarmsplat view` would (read back from the files it wrote)."""
        from .run_folder import load_scene

        self.viewer.show(load_scene(run_folder))

    def serve_result(self, run_folder) -> None:
        """finish(run_folder), then serve until Ctrl-C and close the viewer."""
        try:
            self.finish(run_folder)
            print(f"viewer: {self.viewer.url}  shows the finished run; Ctrl-C to stop", file=sys.stderr, flush=True)
            self.viewer.wait()
        finally:
            self.viewer.close()
