"""The rasteriser's tile binning: every tile's list, front to back with ties by index; the GPU devices' parallel
binning against each backend's CPU binning, bit for bit; invalid Gaussians counted."""

from __future__ import annotations

import pytest
import torch

from swarmsplat import kernels
from swarmsplat.kernels import raster

from raster_scenes import H, K, W, poison, scene  # noqa: F401 (poison: autouse)

# Tiny tensors: torch's intra-op threads only add wake-up latency on a busy 2-core machine.
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _binning(s, viewmat, w, h):
    """Run the projection and the binning kernels of the active backend; returns what they wrote."""
    b = kernels.active()
    project, sort, _ = raster._impls(b)
    n = s["means"].shape[0]
    proj, radius, rect = torch.empty(n, raster.PACKED), torch.empty(n, dtype=torch.int32), torch.empty(n, 4, dtype=torch.int32)
    ntiles, pthr = torch.empty(n, dtype=torch.int32), torch.empty(n)
    args = [s[k].contiguous() for k in ("means", "quats", "scales", "opacities", "colors")] + [viewmat]
    project.project_forward(*args, (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])), w, h, 0.01, 100.0,
                            proj, radius, rect, ntiles, pthr, b.device)
    ntx, nty = (w + 15) // 16, (h + 15) // 16
    n_entries, n_bad, tile_start, entries, emit_start, emit_pos = raster._bin(sort, proj, ntiles, rect, n, ntx, nty,
                                                                              "cpu", b.device)
    return proj, rect, ntiles, n_entries, n_bad, tile_start, entries, emit_start, emit_pos


@pytest.mark.parametrize("tiny_capacity", [False, True])
def test_binning_lists_every_tile_front_to_back(backend, tiny_capacity):
    # Per tile: exactly the Gaussians whose tile rectangle covers it, by camera depth with ties by index (many
    # exact ties here), and emit_pos finds every entry of every Gaussian. tiny_capacity forces the regrow path.
    if backend.torch_device != "cpu":
        pytest.skip("reads the lists on the host")
    s = scene(13, n_plain=120, hard=True)
    s["means"][::3, 2] = 2.5  # a third of them at exactly the same depth
    w, h = 80, 56
    if tiny_capacity:
        raster._capacity[(s["means"].shape[0], 5, 4)] = 1
    proj, rect, ntiles, n_entries, n_bad, tile_start, entries, emit_start, emit_pos = _binning(s, torch.eye(4), w, h)
    assert n_bad == 0 and n_entries == int(ntiles.clamp(min=0).sum()) > 0
    z = proj[:, 9]
    for t in range(5 * 4):
        tx, ty = t % 5, t // 5
        want = [g for g in range(len(z)) if ntiles[g] > 0 and rect[g, 0] <= tx < rect[g, 2] and rect[g, 1] <= ty < rect[g, 3]]
        want.sort(key=lambda g: (float(z[g]), g))
        assert entries[tile_start[t]:tile_start[t + 1]].tolist() == want, t
    assert int(tile_start[-1]) == n_entries
    for g in range(len(z)):
        for k in range(int(ntiles[g])):
            assert int(entries[emit_pos[emit_start[g] + k]]) == g


@pytest.mark.parametrize("name", ["warp", "taichi"])
@pytest.mark.parametrize("tiny_capacity", [False, True])
def test_gpu_binning_equals_the_cpu_binning(monkeypatch, name, tiny_capacity):
    """The GPU archs' parallel binning (kernels/binning.py around each backend's key scatter), run on the CPU,
    against the backend's own CPU binning: the same status, scan, lists and entry positions bit for bit, with
    many exact depth ties (the stable order decides) and through the buffer-regrow path."""
    from swarmsplat.kernels._taichi import sort as taichi_sort
    from swarmsplat.kernels._warp import sort as warp_sort

    kernels.use(name, "cpu")
    s = scene(15, n_plain=400, hard=True)
    s["means"][::3, 2] = 2.5
    w, h = 80, 56
    out = {}
    for mode in ("cpu", "gpu"):
        monkeypatch.setattr(warp_sort, "CPU_SORT", "native" if mode == "cpu" else "warp")
        monkeypatch.setattr(taichi_sort, "CPU_BIN", "serial" if mode == "cpu" else "parallel")
        if tiny_capacity:
            raster._capacity[(s["means"].shape[0], 5, 4)] = 1
        _, _, _, n_entries, n_bad, tile_start, entries, emit_start, emit_pos = _binning(s, torch.eye(4), w, h)
        n = s["means"].shape[0]
        out[mode] = (n_entries, n_bad, tile_start, entries[:n_entries], emit_start[:n], emit_pos[:n_entries])
    assert out["cpu"][0] > 0 and out["cpu"][1] == 0
    for a, b in zip(out["cpu"], out["gpu"]):
        assert a == b if isinstance(a, int) else torch.equal(a, b)


def test_binning_counts_invalid_gaussians(backend):
    if backend.torch_device != "cpu":
        pytest.skip("reads the status on the host")
    s = scene(14, n_plain=20, hard=False)
    s["scales"][3, 1] = float("inf")
    s["quats"][7] = 0.0
    s["opacities"][9] = -0.5
    out = _binning(s, torch.eye(4), W, H)
    assert out[4] == 3
