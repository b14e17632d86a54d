"""The viser web viewer: draws a slam.view.scene.Scene (splats, trajectories, keyframe frusta, loop edges, a
metrics panel) and redraws it when a new Scene comes (live view).

    viewer = Viewer(port=8080)          # one-line InputError when the port is taken
    viewer.show(load_scene("runs/demo"))
    viewer.wait()                       # until Ctrl-C

Scene tree: /<frame>/<layer>/<item>, frame "global" or an agent outside it (its own frame), layer one of LAYERS
(map, slam, no_lc, gt, keyframes, intra, inter). The panel has a checkbox per layer (all frames) and one per
frame other than the global one (off at first: those frames are not aligned with the global one). Frames use
OpenCV axes, so the scene's up direction is -y.
"""

from __future__ import annotations

import contextlib
import errno
import io
import socket
import threading
import time

import numpy as np

from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError, SwarmsplatError

from .scene import GLOBAL, Scene, view_from_points

LAYERS = {  # layer -> checkbox label
    "map": "Gaussian map",
    "slam": "trajectories with loop closures",
    "no_lc": "trajectories, tracking only",
    "gt": "ground truth",
    "keyframes": "keyframe frusta",
    "intra": "intra-agent loops",
    "inter": "inter-agent loops",
}
LINE_PX = 3.0  # trajectory and loop line width, screen pixels
FRUSTUM_PX = 1.5


def import_viser():
    try:
        import viser
    except ImportError:
        raise SwarmsplatError("the viewer needs the 'viser' package: pip install -e '.[view]'") from None
    return viser


def check_port_free(host: str, port: int) -> None:
    """InputError naming the port when something already listens on it (viser would silently take the next one)."""
    if port == 0:
        return
    if not 0 < port < 65536:
        raise InputError(f"--port must be between 1 and 65535, got {port}")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind((host, port))
        except OSError as e:
            if e.errno in (errno.EADDRINUSE, errno.EACCES):
                why = "is in use" if e.errno == errno.EADDRINUSE else "needs more privileges"
                raise InputError(f"--port {port} {why} on {host}; choose another with --port") from None
            raise InputError(f"cannot listen on {host}:{port}: {e.strerror}") from None


class Viewer:
    """A viser server on host:port (port 0: any free port) showing one Scene at a time."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080):
        check_port_free(host, port)
        viser = import_viser()
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner; we print our own line
            self.server = viser.ViserServer(host=host, port=port, label="swarmsplat", verbose=False)
        if port and self.server.get_port() != port:  # lost a race for the port: viser moved on to another
            got = self.server.get_port()
            self.close()
            raise InputError(f"--port {port} is in use on {host} (viser took {got} instead); choose another")
        self.host, self.port = host, self.server.get_port()
        self.server.scene.set_up_direction("-y")
        self.server.gui.configure_theme(control_width="large", show_share_button=False)
        self._lock = threading.Lock()
        self._nodes: dict[str, object] = {}  # leaf scene nodes by name
        self._frames: dict[str, object] = {}  # /<frame> nodes
        self._groups: dict[str, object] = {}  # /<frame>/<layer> nodes
        self._layer_on: dict[str, bool] = {}
        self._checks: dict[str, object] = {}  # "layer:<layer>" / "frame:<frame>" -> checkbox
        self._frames_gui = None
        self._poses: dict[str, np.ndarray] = {}  # frustum node -> the pose it was drawn at
        self._framed = False
        self._layers = self.server.gui.add_folder("Layers", order=1)
        self._panel = self.server.gui.add_markdown("", order=3)
        self.scene: Scene | None = None

    @property
    def url(self) -> str:
        host = "localhost" if self.host in ("0.0.0.0", "") else self.host
        return f"http://{host}:{self.port}"

    # ---- drawing -----------------------------------------------------------------------------------------------

    def show(self, scene: Scene, *, reframe: bool = False) -> None:
        """Draw `scene`, replacing what was drawn; nodes the new scene lacks are removed. The initial camera is
        set from the global frame's extent the first time it has points (or when `reframe`)."""
        with self._lock, self.server.atomic():
            keep: set[str] = set()
            pts = scene.points()
            extent = float(np.linalg.norm(np.ptp(pts, axis=0))) if len(pts) else 1.0
            for s in scene.splats:
                g = self._group(s.frame, "map")
                self._put(f"{g}/{s.name}", keep, lambda n, s=s: self.server.scene.add_gaussian_splats(
                    n, centers=s.centers, covariances=s.covariances, rgbs=s.rgbs, opacities=s.opacities))
            for t in scene.tracks:
                if len(t.points) < 2:
                    continue
                g = self._group(t.frame, t.kind)
                seg = np.stack([t.points[:-1], t.points[1:]], axis=1).astype(np.float32)
                self._put(f"{g}/{t.agent}", keep, lambda n, seg=seg, c=t.color: self.server.scene.add_line_segments(
                    n, seg, c, thickness=LINE_PX, thickness_units="screen"))
            fscale = float(np.clip(0.03 * extent, 0.03, 0.3))
            for f in scene.frusta:
                g = self._group(f.frame, "keyframes")
                for k, T in enumerate(f.poses):
                    if not np.all(np.isfinite(T)):
                        continue
                    name = f"{g}/{f.agent}/{k}"
                    if name in self._nodes and np.array_equal(self._poses.get(name), T):
                        keep.add(name)  # unchanged since the last scene: nothing to send
                        continue
                    self._poses[name] = T.copy()
                    q = se3.matrix_to_quat_wxyz(T[:3, :3])
                    self._put(name, keep, lambda n, f=f, T=T, q=q: self.server.scene.add_camera_frustum(
                        n, fov=f.fov, aspect=f.aspect, scale=fscale, color=f.color, wxyz=q, position=T[:3, 3],
                        thickness=FRUSTUM_PX, thickness_units="screen"))
            for e in scene.edges:
                g = self._group(e.frame, e.kind)
                self._put(f"{g}/edges", keep, lambda n, e=e: self.server.scene.add_line_segments(
                    n, e.segments, e.color, thickness=LINE_PX, thickness_units="screen"))
            for name in [n for n in self._nodes if n not in keep]:
                self._nodes.pop(name).remove()
                self._poses.pop(name, None)
            self._panel.content = f"## {scene.title}\n\n{scene.panel}"
            if len(pts) and (reframe or not self._framed):
                cam = view_from_points(pts)
                ic = self.server.initial_camera
                ic.position, ic.look_at, ic.up = cam["position"], cam["look_at"], cam["up"]
                self._framed = True
            self.scene = scene

    def _put(self, name: str, keep: set, make) -> None:
        """Add (or replace: viser swaps a node of the same name) one leaf node."""
        self._nodes[name] = make(name)
        keep.add(name)

    def _group(self, frame: str, layer: str) -> str:
        """The group node /<frame>/<layer>, made once with its frame and checkboxes (re-adding a frame node
        would drop its children)."""
        if frame not in self._frames:
            self._frames[frame] = self.server.scene.add_frame(f"/{frame}", show_axes=False,
                                                              visible=frame == GLOBAL)
            if frame != GLOBAL:
                with self._frame_folder():
                    box = self.server.gui.add_checkbox(f"{frame}'s own frame", initial_value=False)
                box.on_update(lambda _e, f=frame, b=box: self.set_frame_visible(f, b.value))
                self._checks[f"frame:{frame}"] = box
        if layer not in self._layer_on:
            self._layer_on[layer] = True
            with self._layers:
                box = self.server.gui.add_checkbox(LAYERS.get(layer, layer), initial_value=True,
                                                   order=list(LAYERS).index(layer) if layer in LAYERS else None)
            box.on_update(lambda _e, l=layer, b=box: self.set_layer_visible(l, b.value))
            self._checks[f"layer:{layer}"] = box
        name = f"/{frame}/{layer}"
        if name not in self._groups:
            self._groups[name] = self.server.scene.add_frame(name, show_axes=False, visible=self._layer_on[layer])
        return name

    def _frame_folder(self):
        if self._frames_gui is None:
            self._frames_gui = self.server.gui.add_folder("Frames not joined to the global one", order=2)
        return self._frames_gui

    def set_layer_visible(self, layer: str, visible: bool) -> None:
        """Show or hide a layer ("map", "slam", "no_lc", "gt", "keyframes", "intra", "inter") in every frame."""
        self._layer_on[layer] = bool(visible)
        for name, h in self._groups.items():
            if name.endswith(f"/{layer}"):
                h.visible = bool(visible)
        self._sync_check(f"layer:{layer}", visible)

    def set_frame_visible(self, frame: str, visible: bool) -> None:
        if frame in self._frames:
            self._frames[frame].visible = bool(visible)
        self._sync_check(f"frame:{frame}", visible)

    def _sync_check(self, key: str, visible: bool) -> None:
        box = self._checks.get(key)
        if box is not None and box.value != bool(visible):
            box.value = bool(visible)

    def layers(self) -> list[str]:
        return list(self._layer_on)

    def groups(self) -> list[str]:
        return list(self._groups)

    def nodes(self) -> list[str]:
        return list(self._nodes)

    # ---- lifetime ----------------------------------------------------------------------------------------------

    def clients(self) -> int:
        return len(self.server.get_clients())

    def wait_for_client(self, timeout: float) -> bool:
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            if self.clients():
                return True
            time.sleep(0.1)
        return False

    def wait(self) -> None:
        """Serve until Ctrl-C."""
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            pass

    def close(self) -> None:
        with contextlib.redirect_stdout(io.StringIO()):  # "(viser) Server stopped"
            self.server.stop()

    def __enter__(self) -> "Viewer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
