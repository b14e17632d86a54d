"""The device self-check: one probe render at a run's working size on a backend/device, forward and backward,
compared with the twin, before the run's first frame.

A device whose driver loads can still compute wrongly (Mesa's software Vulkan driver stops any one invocation's
loops after 65535 iterations, silently; a new driver, a new GPU, a kernel change that only a GPU build sees). The
run would then map nothing, or garbage, and say "complete". `require(backend, device, width, height)` renders a
probe scene of realistic tile load (width x height / 8 Gaussians of 1-3.5 px at 1.5-6 m, its own tensors and
random generator: nothing of the run changes) and compares:

- four 16x16 tiles (the busiest, the first, the centre and the last one) with the float64 twin
  (kernels/_ref_raster.py, on those pixels only): colour, alpha and depth per pixel, and the gradients of a
  weighted loss over those pixels with respect to every Gaussian parameter and the viewmat;
- on a GPU device, the whole image with Warp on the CPU (held to the twin by the test suite), per pixel and on
  average.

Bounds: float32 codes agree with the twin to ~1e-5 per pixel except where rounding decides whether a Gaussian of
alpha ~1/255 is composited (it and the transmittance it takes: up to 2/255 of colour and alpha, of the farthest
depth for depth), which two such decisions at one pixel make 4/255 (PIXEL_BOUND); over the whole image such
pixels are a handful, so the mean difference stays below MEAN_BOUND. Gradients: relative L2 error per parameter
below GRAD_BOUND (measured ~1e-5 on a working device). Lost tile entries or cut-short loops move whole tiles by
tenths. A mismatch or a driver failure raises DeviceCheckError with one line naming backend, device, size and
what differed. Each (backend, device, size) is checked once per process.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from .backend import BACKENDS, Backend, active, use
from .errors import BackendError, DeviceCheckError

TILE = 16
PIXEL_BOUND = 4.0 / 255.0  # per pixel, colour and alpha (depth: times the farthest depth)
MEAN_BOUND = 1e-4  # mean absolute difference over the whole image
GRAD_BOUND = 1e-2  # relative L2 error of each parameter's gradient over the probe tiles
_PARAMS = ("means", "quats", "scales", "opacities", "colors")

_passed: set = set()  # (backend, device, width, height) that passed in this process


@dataclass(frozen=True)
class CheckResult:
    backend: str
    device: str
    width: int
    height: int
    ok: bool
    detail: str  # what differed, or the largest differences found
    seconds: float

    def line(self) -> str:
        return f"{self.backend}-{self.device} at {self.width}x{self.height}: {'ok' if self.ok else 'FAILED'}, " \
               f"{self.detail} ({self.seconds:.1f} s)"


def probe_scene(width: int, height: int, seed: int = 0) -> dict:
    """width x height / 8 Gaussians (at least 256) as `frustum_scene` spreads them."""
    return frustum_scene(max(256, width * height // 8), width, height, seed)


def frustum_scene(n: int, width: int, height: int, seed: int = 0) -> dict:
    """n Gaussians spread through the view frustum at 1.5-6 m, 1-3.5 px standard deviation on screen (scaled with
    the width from 640), identity viewmat, pinhole K with a ~58 degree field of view (also perf.raster's scenes)."""
    import torch

    g = torch.Generator().manual_seed(seed)
    f = 0.9 * width
    K = torch.tensor([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])
    z = 1.5 + 4.5 * torch.rand(n, generator=g)
    u, v = torch.rand(n, generator=g) * width, torch.rand(n, generator=g) * height
    means = torch.stack([(u - K[0, 2]) * z / f, (v - K[1, 2]) * z / f, z], 1)
    sigma_px = (1.0 + 2.5 * torch.rand(n, 1, generator=g)) * (width / 640.0)
    scales = sigma_px * z[:, None] / f * (0.5 + torch.rand(n, 3, generator=g))
    return dict(means=means, quats=torch.randn(n, 4, generator=g), scales=scales,
                opacities=0.2 + 0.75 * torch.rand(n, generator=g), colors=torch.rand(n, 3, generator=g),
                viewmat=torch.eye(4), K=K, width=width, height=height)


def _render(scene: dict, weights, torch_device: str):
    """kernels.rasterize on the active backend, then backward of the weighted loss; (output on the CPU, grads)."""

    from .raster import rasterize

    p = {k: scene[k].to(torch_device).clone().requires_grad_(True) for k in _PARAMS}
    vm = scene["viewmat"].to(torch_device).clone().requires_grad_(True)
    out = rasterize(**p, viewmat=vm, K=scene["K"].to(torch_device), width=scene["width"], height=scene["height"])
    w = weights.to(torch_device)
    ((out.color * w[..., None]).sum() + (out.depth * w).sum() + (out.alpha * w).sum()).backward()
    grads = {k: p[k].grad.cpu() for k in _PARAMS} | {"viewmat": vm.grad.cpu()}
    img = {k: getattr(out, k).detach().cpu() for k in ("color", "depth", "alpha")}
    return img, grads


def _windows(scene: dict):
    """(tiles [(tx, ty)], Gaussians whose tile rectangle covers one of them) from the float64 twin projection:
    the busiest tile, the first, the centre and the last."""
    import torch

    from ._ref_raster import project_reference

    w, h = scene["width"], scene["height"]
    ntx, nty = (w + TILE - 1) // TILE, (h + TILE - 1) // TILE
    *_, rect, vis = project_reference(*(scene[k].double() for k in ("means", "quats", "scales", "viewmat", "K")),
                                      w, h, 0.01, 100.0)
    r = rect[vis].long()
    load = torch.zeros(nty + 1, ntx + 1, dtype=torch.int64)  # 2-D difference array of the rectangles
    for (ys, xs), sign in (((r[:, 1], r[:, 0]), 1), ((r[:, 1], r[:, 2]), -1), ((r[:, 3], r[:, 0]), -1),
                           ((r[:, 3], r[:, 2]), 1)):
        load.index_put_((ys, xs), torch.full_like(ys, sign), accumulate=True)
    load = load.cumsum(0).cumsum(1)[:nty, :ntx]
    busiest = int(load.argmax())
    tiles = list(dict.fromkeys([(busiest % ntx, busiest // ntx), (0, 0), (ntx // 2, nty // 2), (ntx - 1, nty - 1)]))
    covers = torch.zeros(len(rect), dtype=torch.bool)
    for tx, ty in tiles:
        covers |= vis & (rect[:, 0] <= tx) & (tx < rect[:, 2]) & (rect[:, 1] <= ty) & (ty < rect[:, 3])
    return tiles, covers.nonzero().flatten()


def _twin_tiles(scene: dict, tiles, subset, weights):
    """The twin (float64) on each probe tile: ({tile: images}, grads of the weighted loss over those pixels, with
    respect to the subset's parameters and the viewmat)."""
    import torch

    from ._ref_raster import rasterize_reference

    w, h = scene["width"], scene["height"]
    p = {k: scene[k][subset].double().requires_grad_(True) for k in _PARAMS}
    vm = scene["viewmat"].double().requires_grad_(True)
    imgs, loss = {}, torch.zeros((), dtype=torch.float64)
    for tx, ty in tiles:
        box = (tx * TILE, ty * TILE, min(w, (tx + 1) * TILE), min(h, (ty + 1) * TILE))
        o = rasterize_reference(**p, viewmat=vm, K=scene["K"].double(), width=w, height=h, window=box)
        wt = weights[box[1]:box[3], box[0]:box[2]].double()
        loss = loss + (o.color * wt[..., None]).sum() + (o.depth * wt).sum() + (o.alpha * wt).sum()
        imgs[(tx, ty)] = (box, {k: getattr(o, k).detach() for k in ("color", "depth", "alpha")})
    loss.backward()
    return imgs, {k: p[k].grad for k in _PARAMS} | {"viewmat": vm.grad}


def _image_difference(a: dict, b: dict, zmax: float, what: str, origin=(0, 0)) -> str | None:
    """The first image whose per-pixel difference passes PIXEL_BOUND (depth: times zmax), as one phrase."""
    import torch

    for k in ("color", "alpha", "depth"):
        if not bool(torch.isfinite(a[k]).all()):
            return f"{k} has NaN or Inf pixels (compared with {what})"
        d = (a[k].double() - b[k].double()).abs()
        if d.dim() == 3:
            d = d.amax(-1)
        bound = PIXEL_BOUND * (zmax if k == "depth" else 1.0)
        if float(d.max()) > bound:
            y, x = divmod(int(d.argmax()), d.shape[1])
            return (f"{k} differs from {what} by {float(d.max()):.3g} at pixel (x={x + origin[0]}, "
                    f"y={y + origin[1]}) (bound {bound:.3g})")
    return None


def self_check(backend: str, device: str, width: int = 320, height: int = 240) -> CheckResult:
    """Run the probe on (backend, device) at width x height; the active pair is selected again afterwards.
    Raises BackendError when the pair does not load here at all (as kernels.use); any other failure is a
    CheckResult with ok False."""
    import torch

    t0 = time.perf_counter()
    before = active()
    scene = probe_scene(width, height)
    weights = torch.rand(height, width, generator=torch.Generator().manual_seed(1))
    tiles, subset = _windows(scene)
    mask = torch.zeros(height, width)
    for tx, ty in tiles:
        mask[ty * TILE:(ty + 1) * TILE, tx * TILE:(tx + 1) * TILE] = 1.0
    try:
        b = use(backend, device)
        try:
            img, grads = _render(scene, weights * mask, b.torch_device)
        except BackendError:
            raise
        except Exception as e:  # noqa: BLE001 - a driver or kernel failure is the answer
            msg = " ".join(str(e).split())[:300]
            return CheckResult(backend, device, width, height, False, f"the probe render failed: "
                               f"{type(e).__name__}: {msg}", time.perf_counter() - t0)
        whole = None
        if device != "cpu":
            try:
                use("warp", "cpu")
            except BackendError:  # no Warp here (e.g. a Taichi-only install): the twin's tiles only
                pass
            else:
                whole, _ = _render(scene, weights * mask, "cpu")
    finally:
        use(before.name, before.device)
    zmax = float(scene["means"][:, 2].max())
    twin, twin_grads = _twin_tiles(scene, tiles, subset, weights)
    problem = None
    worst = 0.0
    for (tx, ty), (box, ref) in twin.items():
        mine = {k: v[box[1]:box[3], box[0]:box[2]] for k, v in img.items()}
        problem = problem or _image_difference(mine, ref, zmax, f"the twin in tile ({tx}, {ty})", box[:2])
        worst = max(worst, float((mine["color"].double() - ref["color"]).abs().max()))
    if problem is None and whole is not None:
        problem = _image_difference(img, whole, zmax, "warp-cpu")
        if problem is None:
            mean = float((img["color"] - whole["color"]).abs().mean())
            if mean > MEAN_BOUND:
                problem = f"colour differs from warp-cpu by {mean:.3g} on average (bound {MEAN_BOUND:.3g})"
    grad_err = 0.0
    for k, g in twin_grads.items():
        mine = grads[k] if k == "viewmat" else grads[k][subset]
        rel = float((mine.double() - g).norm() / g.norm().clamp_min(1e-30))
        grad_err = max(grad_err, rel)
        if problem is None and not (rel <= GRAD_BOUND):
            problem = f"the gradient of {k} differs from the twin's by {rel:.3g} relative (bound {GRAD_BOUND:.3g})"
    detail = problem or f"colour within {worst:.1g} of the twin, gradients within {grad_err:.1g} relative"
    return CheckResult(backend, device, width, height, problem is None, detail, time.perf_counter() - t0)


def require(backend: str, device: str, width: int, height: int) -> None:
    """self_check once per process and (backend, device, size); raises DeviceCheckError (one line) on failure."""
    key = (backend, device, int(width), int(height))
    if key in _passed:
        return
    r = self_check(backend, device, int(width), int(height))
    if not r.ok:
        raise DeviceCheckError(f"kernel device self-check failed: {backend}-{device} at {width}x{height}: "
                               f"{r.detail}; this device would give wrong maps (use --device cpu)")
    _passed.add(key)


def check_all(width: int = 320, height: int = 240, pairs: list[Backend] | None = None) -> list[CheckResult]:
    """self_check on every pair that loads here (kernels.devices()), or on `pairs`."""
    from .backend import devices

    out = []
    for b in pairs if pairs is not None else devices():
        if b.name in BACKENDS:
            out.append(self_check(b.name, b.device, width, height))
    return out
