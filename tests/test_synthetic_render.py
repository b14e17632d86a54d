"""The synthetic generator's rendering: supersampled pixels, the texture and ray-shading kernels against their
NumPy twins, and brightness constancy between nearby views."""

from __future__ import annotations

import numpy as np
import pytest

from swarmsplat.kernels import se3
from swarmsplat.slam.synthetic import cast, dataset_camera


@pytest.mark.parametrize("s", [2, 3])
def test_supersampled_pixels_average_their_area_and_keep_the_centre_depth(default_world, s):
    """Colour is the mean of the pixel's s x s rays, depth / incidence / material the one-ray image's, and the
    mean is closer to the pixel's area integral (an 8 x 8 grid) than one ray through the centre is."""
    from swarmsplat.slam.synthetic.render import shade, supersampled, trace

    world, cfg, poses = default_world
    camera = dataset_camera(cfg).scaled(80, 60)
    T = poses[2][30]
    one = cast(world, T, camera)
    many = cast(world, T, camera, supersample=s)
    fine = supersampled(camera, s)
    assert (fine.width, fine.height) == (80 * s, 60 * s)
    raw = shade(world, trace(world, T, fine), fine)
    np.testing.assert_allclose(many.color[0], raw.color[0].reshape(60, s, 80, s, 3).mean(axis=(1, 3)), atol=1e-6)
    np.testing.assert_array_equal(many.depth, one.depth)
    np.testing.assert_array_equal(many.cos_incidence, one.cos_incidence)
    np.testing.assert_array_equal(many.material, one.material)
    area = cast(world, T, camera, supersample=8).color
    err1, err_s = ((one.color - area) ** 2).mean(), ((many.color - area) ** 2).mean()
    assert err_s < 0.3 * err1, (err1, err_s)


def test_texture_kernel_equals_its_numpy_twin(default_world):
    """The Warp texture kernel against TextureField.shade_numpy at the hits of a supersampled frame (every pattern
    of the world but one is in these views)."""
    from swarmsplat.slam.synthetic.render import _ray_lengths, supersampled, surface_coordinates, trace

    world, cfg, poses = default_world
    cam = supersampled(dataset_camera(cfg).scaled(160, 120), 2)
    tr = trace(world, np.stack([poses[a][20] for a in range(4)]), cam)
    tri, t = tr.prim.astype(np.int64), tr.t_hit
    assert np.isfinite(t).all()  # inside the closed world every ray hits
    s, tt = surface_coordinates(world, tr.rays, t, tri)
    fp = t * (np.tile(_ray_lengths(cam), 4) / np.float32(cam.fx))
    mat, light = world.tri_material[tri], world.tri_light[tri]
    assert len(np.unique(world.texture.materials.pattern[mat])) >= 4
    got = world.texture.shade(s, tt, mat, fp, light)
    want = world.texture.shade_numpy(s, tt, mat, fp, light)
    assert got.dtype == np.float32 and got.shape == want.shape
    err = np.abs(got - want).max(axis=1)
    tol = _texture_tolerance(world, s, tt, mat, fp, ulps=1)
    assert (err <= tol).all(), float((err / tol).max())
    assert np.abs(got - want).mean() < 2e-5  # 1/200 of an 8-bit level; a wrong formula gives ~1e-2


def _texture_tolerance(world, s, t, mat, fp, ulps):
    """Per sample: how far a float32 shading of the texture may be from its twin. Stripes, tiles and planks divide
    coordinates near 100 m by periods of centimetres, and the kernel may contract the multiply-add after the
    quotient (by CPU): the phase may differ by `ulps` ulps of q = s / period. Their soft edges (slope
    1 / footprint) turn one into period ulp(q) / fp of colour, up to 1.1e-3 at the nearest surfaces, and the plank
    grain sin(2 pi t / (0.23 period)) into 0.8 ulp(t / 0.23 period); 5e-4 covers the rest (float32 rounding, and
    the blotches' sin of ~130 rad: 2 ulps of it, 3e-5, times their edge slope <= 6.25)."""
    from swarmsplat.slam.synthetic.texture import PATTERNS

    period = world.texture.materials.period[mat]
    pat = world.texture.materials.pattern[mat]
    q = np.maximum(np.abs(s), np.abs(t)).astype(np.float32) / period
    soft = np.isin(pat, [PATTERNS.index(name) for name in ("stripes", "tiles", "planks")])
    edge = period.astype(np.float64) * np.spacing(q) / fp
    grain = np.where(pat == PATTERNS.index("planks"), 0.8 * np.spacing(q / np.float32(0.23)), 0.0)
    return 5e-4 + ulps * np.where(soft, edge + grain, 0.0)


def test_ray_shading_kernel_equals_its_numpy_twin(default_world):
    """render.shade_color (surface coordinates, footprint and texture in one Warp kernel) against
    render.shade_color_numpy on a supersampled batch, with two rays made misses (black in both)."""
    from swarmsplat.slam.synthetic.render import (Traced, _ray_lengths, shade_color, shade_color_numpy,
                                                  supersampled, surface_coordinates, trace)

    world, cfg, poses = default_world
    cam = supersampled(dataset_camera(cfg).scaled(80, 60), 2)
    tr = trace(world, np.stack([poses[a][25] for a in range(4)]), cam)
    t = tr.t_hit.copy()
    t[[7, 1234]] = [np.inf, 0.0]
    tr = Traced(tr.rays, t, tr.prim, tr.shape)
    got, want = shade_color(world, tr, cam), shade_color_numpy(world, tr, cam)
    assert got.shape == want.shape == (4, 120, 160, 3) and got.dtype == np.float32
    flat = got.reshape(-1, 3)
    assert not flat[[7, 1234]].any() and flat.mean() > 0.05
    # The point kernel's tolerances (above), with the surface coordinates computed in the kernel too: s = o + t d
    # near 100 m rounds to ulp(s), ~1.3 ulp(q) at the shortest period, so three ulps of q instead of one.
    hit = np.isfinite(t) & (t > 0)
    tri = tr.prim.reshape(-1)[hit].astype(np.int64)
    s, tt = surface_coordinates(world, tr.rays[hit], t[hit], tri)
    fp = t[hit] * (np.tile(_ray_lengths(cam), 4)[hit] / np.float32(cam.fx))
    err = np.abs(flat - want.reshape(-1, 3)).max(axis=1)
    tol = _texture_tolerance(world, s, tt, world.tri_material[tri], fp, ulps=3)
    assert (err[hit] <= tol).all() and (err[~hit] <= 5e-4).all(), float((err[hit] / tol).max())
    assert np.abs(got - want).mean() < 2e-5


def test_surfaces_look_the_same_from_nearby_views(default_world):
    """Brightness constancy, which photometric tracking relies on: warp frame a into frame b with the true depth
    and poses; corresponding pixels have (nearly) the same colour, while the images themselves differ."""
    world, cfg, poses = default_world
    camera = dataset_camera(cfg)
    Ta, Tb = poses[1][10], poses[1][13]
    hits = cast(world, np.stack([Ta, Tb]), camera)
    pts = camera.backproject(hits.depth[0]) @ (se3.inverse(Tb) @ Ta)[:3, :3].T + (se3.inverse(Tb) @ Ta)[:3, 3]
    uv, z = camera.project(pts)
    ok = camera.in_image(np.nan_to_num(uv, nan=-1e9), margin=1.0) & (z > 0)
    u, v = np.rint(uv[ok]).astype(int).T
    visible = np.abs(hits.depth[1][v, u] - z[ok]) < 0.01 * z[ok]
    diff = np.abs(hits.color[0][ok][visible] - hits.color[1][v[visible], u[visible]]).mean(axis=1)
    assert visible.sum() > 0.5 * ok.size
    assert np.median(diff) < 0.03  # nearest-pixel warping: small residuals from sub-pixel offsets only
    assert np.abs(hits.color[0] - hits.color[1]).mean(axis=-1).mean() > 3 * np.median(diff)  # it did move
