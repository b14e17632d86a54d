"""ATE / RPE against evo (the published numbers in PROVENANCE and the installed package), alignment, association,
and the image metrics against independent formulations."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from conftest import shared_data
from swarmsplat.kernels import se3
from swarmsplat.kernels.errors import InputError
from swarmsplat.slam.io.datasets.associate import associate_unique, match_nearest
from swarmsplat.slam.metrics import ate, ate_multi, depth_l1, psnr, rpe, ssim, umeyama
from swarmsplat.slam.io.trajectory import read_tum

EVO = "tum_trajectories_evo"


def _tum(name):
    return read_tum(shared_data(EVO, name))


# ---- against the numbers evo 1.38.1 printed (PROVENANCE.txt, rounded to 6 decimals) -------------------------

@pytest.mark.parametrize(
    "gt, est, align, n_matched, rmse, mean, maxv",
    [
        ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt", "se3", 785, 0.013470, 0.012024, 0.034760),
        ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-ORB_kf_mono.txt", "sim3", 32, 0.009755, 0.008219, 0.027924),
        ("fr2_desk_groundtruth.txt", "fr2_desk_ORB.txt", "se3", None, 0.008119, 0.007492, 0.024300),
    ],
)
def test_ate_equals_evo_published(gt, est, align, n_matched, rmse, mean, maxv):
    r = ate(*_tum(gt), *_tum(est), align=align, max_diff=0.01)
    # The references carry 6 decimals: agreement within rounding (5e-7) is agreement to 1e-6 m.
    assert r.rmse == pytest.approx(rmse, abs=1e-6)
    assert r.stats.mean == pytest.approx(mean, abs=1e-6)
    assert r.stats.max == pytest.approx(maxv, abs=1e-6)
    if n_matched is not None:
        assert r.matched == n_matched


def test_sim3_scale_equals_evo_published():
    r = ate(*_tum("freiburg1_xyz-groundtruth.txt"), *_tum("freiburg1_xyz-ORB_kf_mono.txt"), align="sim3")
    assert r.transform.scale == pytest.approx(1.1056223637370346, abs=1e-9)


def test_rpe_equals_evo_published():
    r = rpe(*_tum("freiburg1_xyz-groundtruth.txt"), *_tum("freiburg1_xyz-rgbdslam.txt"), delta=1)
    assert r.rmse == pytest.approx(0.005764, abs=1e-6)
    assert r.trans.mean == pytest.approx(0.004816, abs=1e-6)


# ---- against the installed evo package (test-only dependency) ------------------------------------------------

def _evo_ape(gt_path, est_path, align, max_diff=0.01):
    evo_fi = pytest.importorskip("evo.tools.file_interface")
    from evo.core import metrics, sync

    ref = evo_fi.read_tum_trajectory_file(str(gt_path))
    est = evo_fi.read_tum_trajectory_file(str(est_path))
    ref, est = sync.associate_trajectories(ref, est, max_diff=max_diff)
    est = copy.deepcopy(est)
    if align != "none":
        est.align(ref, correct_scale=(align == "sim3"))
    m = metrics.APE(metrics.PoseRelation.translation_part)
    m.process_data((ref, est))
    return m, ref.num_poses


def _evo_rpe(gt_path, est_path, delta, align):
    evo_fi = pytest.importorskip("evo.tools.file_interface")
    from evo.core import metrics, sync

    ref = evo_fi.read_tum_trajectory_file(str(gt_path))
    est = evo_fi.read_tum_trajectory_file(str(est_path))
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
    if align == "sim3":
        est.align(ref, correct_scale=True)
    m = metrics.RPE(metrics.PoseRelation.translation_part, delta=delta, delta_unit=metrics.Unit.frames)
    m.process_data((ref, est))
    return m


@pytest.mark.parametrize(
    "gt, est, align",
    [
        ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt", "se3"),
        ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam_drift.txt", "se3"),
        ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam_drift.txt", "none"),
        ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-ORB_kf_mono.txt", "sim3"),
        ("fr2_desk_groundtruth.txt", "fr2_desk_ORB_kf_mono.txt", "sim3"),
    ],
)
def test_ate_equals_installed_evo(gt, est, align):
    g, e = shared_data(EVO, gt), shared_data(EVO, est)
    m, n = _evo_ape(g, e, align)
    r = ate(*read_tum(g), *read_tum(e), align=align)
    assert r.matched == n
    from evo.core.metrics import StatisticsType as S

    for ours, theirs in [(r.rmse, S.rmse), (r.stats.mean, S.mean), (r.stats.median, S.median),
                         (r.stats.std, S.std), (r.stats.max, S.max), (r.stats.sse, S.sse)]:
        assert ours == pytest.approx(m.get_statistic(theirs), abs=1e-9)
    np.testing.assert_allclose(r.errors, m.error, atol=1e-9)


@pytest.mark.parametrize("delta, align", [(1, "none"), (5, "none"), (2, "sim3")])
def test_rpe_equals_installed_evo(delta, align):
    est_name = "freiburg1_xyz-ORB_kf_mono.txt" if align == "sim3" else "freiburg1_xyz-rgbdslam_drift.txt"
    g, e = shared_data(EVO, "freiburg1_xyz-groundtruth.txt"), shared_data(EVO, est_name)
    m = _evo_rpe(g, e, delta, align)
    r = rpe(*read_tum(g), *read_tum(e), delta=delta, align=align)
    np.testing.assert_allclose(r.errors_trans, m.error, atol=1e-9)


def test_match_nearest_equals_evo_on_random_stamps():
    sync = pytest.importorskip("evo.core.sync")
    rng = np.random.default_rng(3)
    for trial in range(20):
        a = np.sort(rng.uniform(0, 10, rng.integers(5, 80)))
        b = np.sort(rng.uniform(0, 10, rng.integers(5, 80)))
        if trial % 4 == 0:
            b = rng.permutation(b)  # unsorted: evo's linear fallback
        if trial % 5 == 0:
            b = np.concatenate([b, a[:3] + 0.005])  # exact ties at the tolerance border
        got = match_nearest(a, b, 0.05)
        want = sync.matching_time_indices(a, b, 0.05)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])


def test_associate_unique_is_greedy_one_to_one():
    rng = np.random.default_rng(4)
    a = np.sort(rng.uniform(0, 3, 60))
    b = np.sort(rng.uniform(0, 3, 50))
    i, j = associate_unique(a, b, 0.03)
    assert len(set(i)) == len(i) and len(set(j)) == len(j)
    assert np.all(np.abs(a[i] - b[j]) <= 0.03)
    # Brute force, TUM associate.py's rule: all pairs in tolerance, closest first, each stamp once.
    pairs = sorted((abs(x - y), p, q) for p, x in enumerate(a) for q, y in enumerate(b) if abs(x - y) <= 0.03)
    ua, ub, want = set(), set(), []
    for _, p, q in pairs:
        if p not in ua and q not in ub:
            ua.add(p)
            ub.add(q)
            want.append((p, q))
    assert sorted(want) == list(zip(i.tolist(), j.tolist()))


# ---- alignment and multi-agent ATE on synthetic trajectories ------------------------------------------------

def _random_traj(rng, n=60):
    xi = np.cumsum(rng.normal(0, 0.05, (n, 6)), axis=0)
    return np.arange(n) * 0.1, se3.exp(xi)


def _sim3(rng, s):
    R = se3.so3_exp(rng.normal(0, 1, 3))
    return R, rng.normal(0, 2, 3), s


def _apply(T, R, t, s):
    out = T.copy()
    out[:, :3, :3] = R @ T[:, :3, :3]
    out[:, :3, 3] = s * T[:, :3, 3] @ R.T + t
    return out


def test_umeyama_recovers_known_similarity():
    rng = np.random.default_rng(0)
    x = rng.normal(0, 1, (40, 3))
    R, t, s = _sim3(rng, 0.37)
    S = umeyama(x, s * x @ R.T + t, with_scale=True)
    np.testing.assert_allclose(S.R, R, atol=1e-10)
    np.testing.assert_allclose(S.t, t, atol=1e-10)
    assert S.scale == pytest.approx(s, rel=1e-10)


def test_ate_zero_after_alignment_and_positive_without():
    rng = np.random.default_rng(1)
    t, T = _random_traj(rng)
    R, tt, s = _sim3(rng, 2.5)
    est = _apply(T, R, tt, s)  # the estimate is a similarity image of the ground truth
    assert ate(t, T, t, est, align="sim3").rmse < 1e-9
    assert ate(t, T, t, est, align="se3").rmse > 0.01
    rigid = _apply(T, R, tt, 1.0)
    assert ate(t, T, t, rigid, align="se3").rmse < 1e-9
    none = ate(t, T, t, rigid, align="none")
    np.testing.assert_allclose(none.errors, np.linalg.norm(rigid[:, :3, 3] - T[:, :3, 3], axis=1))


def test_rpe_invariant_to_rigid_alignment_and_detects_drift():
    rng = np.random.default_rng(2)
    t, T = _random_traj(rng)
    R, tt, _ = _sim3(rng, 1.0)
    assert rpe(t, T, t, _apply(T, R, tt, 1.0)).rmse < 1e-9
    drift = T.copy()
    drift[:, 0, 3] += 0.01 * np.arange(len(T))  # 1 cm per frame along world x
    r = rpe(t, T, t, drift)
    assert r.rmse == pytest.approx(0.01, rel=1e-9)


def test_ate_multi_team_frame_vs_per_agent():
    rng = np.random.default_rng(5)
    (ta, Ta), (tb, Tb) = _random_traj(rng), _random_traj(rng)
    R, tt, _ = _sim3(rng, 1.0)
    # Both estimates in one common frame: per agent and joint are all ~0.
    same = ate_multi({"a": (ta, Ta), "b": (tb, Tb)}, {"a": (ta, _apply(Ta, R, tt, 1)), "b": (tb, _apply(Tb, R, tt, 1))})
    assert same.joint.rmse < 1e-9 and max(r.rmse for r in same.per_agent.values()) < 1e-9
    assert same.joint.matched == len(ta) + len(tb)
    # Agent b in its own frame: each agent alone aligns perfectly, the team frame does not.
    R2, t2, _ = _sim3(rng, 1.0)
    split = ate_multi({"a": (ta, Ta), "b": (tb, Tb)}, {"a": (ta, _apply(Ta, R, tt, 1)), "b": (tb, _apply(Tb, R2, t2, 1))})
    assert max(r.rmse for r in split.per_agent.values()) < 1e-9
    assert split.joint.rmse > 0.1
    with pytest.raises(InputError, match="no ground truth"):
        ate_multi({"a": (ta, Ta)}, {"c": (ta, Ta)})


def test_ate_multi_scores_an_unalignable_agent_under_the_joint_alignment():
    rng = np.random.default_rng(7)
    (ta, Ta), (tb, Tb) = _random_traj(rng), _random_traj(rng)
    tb, Tb = tb[:2], Tb[:2]  # two poses: too few to align agent b on its own
    R, tt, _ = _sim3(rng, 1.0)
    Eb = _apply(Tb, R, tt, 1)
    Eb[1, :3, 3] += [0.03, 0.0, 0.04]  # 5 cm off in the common frame
    with pytest.raises(InputError):
        ate(tb, Tb, tb, Eb)
    r = ate_multi({"a": (ta, Ta), "b": (tb, Tb)}, {"a": (ta, _apply(Ta, R, tt, 1)), "b": (tb, Eb)})
    assert r.per_agent["a"].align == "se3" and r.per_agent["b"].align == "joint"
    assert r.per_agent["b"].errors[0] < 0.01 and r.per_agent["b"].errors[1] == pytest.approx(0.05, abs=0.01)


def test_bad_trajectories_are_input_errors():
    rng = np.random.default_rng(6)
    t, T = _random_traj(rng, 10)
    bad = T.copy()
    bad[3, 0, 3] = np.nan
    with pytest.raises(InputError, match="pose 3"):
        ate(t, T, t, bad)
    with pytest.raises(InputError, match="no matching timestamps"):
        ate(t, T, t + 100.0, T)
    with pytest.raises(InputError, match="equal length"):
        ate(t, T, t[:5], T[:5], by_index=True)
    with pytest.raises(InputError, match="unknown alignment"):
        ate(t, T, t, T, align="affine")
    with pytest.raises(InputError, match="collinear"):
        line = np.tile(np.eye(4), (10, 1, 1))
        line[:, 0, 3] = np.arange(10)
        ate(t, line, t, line, align="se3")


# ---- image metrics --------------------------------------------------------------------------------------------

def _ssim_reference(x, y):
    """Independent SSIM: full 2-D Gaussian kernel via scipy, 'valid' crop, per channel."""
    from scipy.ndimage import correlate

    g = np.exp(-((np.arange(11) - 5.0) ** 2) / (2 * 1.5**2))
    k = np.outer(g, g) / np.outer(g, g).sum()
    vals = []
    for c in range(x.shape[2]):
        a, b = x[..., c], y[..., c]
        f = lambda z: correlate(z, k, mode="constant")[5:-5, 5:-5]  # noqa: E731
        ma, mb = f(a), f(b)
        va, vb, cab = f(a * a) - ma**2, f(b * b) - mb**2, f(a * b) - ma * mb
        c1, c2 = 0.01**2, 0.03**2
        vals.append(((2 * ma * mb + c1) * (2 * cab + c2)) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


def test_ssim_matches_independent_formulation():
    rng = np.random.default_rng(7)
    x = rng.uniform(0, 1, (40, 52, 3))
    y = np.clip(x + rng.normal(0, 0.1, x.shape), 0, 1)
    assert ssim(x, y) == pytest.approx(_ssim_reference(x, y), abs=1e-10)
    assert ssim(x, x) == pytest.approx(1.0, abs=1e-12)
    # channels-first torch input gives the same number
    assert ssim(torch.from_numpy(x).permute(2, 0, 1), torch.from_numpy(y).permute(2, 0, 1)) == pytest.approx(ssim(x, y), abs=1e-12)
    assert ssim(x, np.clip(x + rng.normal(0, 0.3, x.shape), 0, 1)) < ssim(x, y)


def test_ssim_cpu_filter_equals_the_torch_convolutions():
    """The CPU path (OpenCV's separable float64 filter, cropped to the valid region) against the torch convolutions
    that GPU tensors take: the same maps to rounding, for odd and even windows, one and three channels."""
    from swarmsplat.slam.metrics.image import _gaussian_window, _ssim_map_cpu, _ssim_map_torch

    g = torch.Generator().manual_seed(3)
    for c, h, w, window in ((3, 37, 45, 11), (1, 24, 30, 11), (3, 20, 26, 8), (1, 11, 12, 11)):
        x = torch.rand(c, h, w, generator=g, dtype=torch.float64)
        y = (x + 0.1 * torch.randn(c, h, w, generator=g, dtype=torch.float64)).clamp(0, 1)
        k = _gaussian_window(window, 1.5, "cpu")
        a = _ssim_map_cpu(x, y, k)
        b = _ssim_map_torch(x, y, k).permute(1, 2, 0).numpy()
        assert a.shape == b.shape == (h - window + 1, w - window + 1, c)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-13)
        m = torch.rand(h, w, generator=g) > 0.4  # masked: the map's mean over the window centres on masked pixels
        r = window // 2
        m[r, r] = True
        mc = m[r : r + h - window + 1, r : r + w - window + 1].numpy()
        assert ssim(x, y, mask=m, window=window) == pytest.approx(float(b[mc].mean()), abs=1e-13)
        assert ssim(x, y, window=window) == pytest.approx(float(b.mean()), abs=1e-13)


def test_psnr_values_dtypes_and_mask():
    x = np.full((20, 30, 3), 0.5)
    assert psnr(x + 0.1, x) == pytest.approx(20.0, abs=1e-9)  # MSE 0.01
    u8 = np.full((20, 30, 3), 100, dtype=np.uint8)
    assert psnr(u8, u8 + np.uint8(10)) == pytest.approx(-10 * np.log10((10 / 255) ** 2), abs=1e-9)
    assert psnr(x, x) == float("inf")
    y = x.copy()
    y[:5] = 0.0  # corrupt the top rows; the mask excludes them
    mask = np.ones((20, 30), bool)
    mask[:5] = False
    assert psnr(y, x, mask=mask) == float("inf")
    assert psnr(y, x) < 20
    with pytest.raises(InputError, match="differ in shape"):
        psnr(x, x[:10])


def test_depth_l1_ignores_invalid_ground_truth():
    gt = np.full((10, 12), 2.0, np.float32)
    gt[:, :6] = 0.0  # invalid half
    pred = np.full((10, 12), 2.5, np.float32)
    pred[:, :6] = 100.0  # garbage where gt is invalid must not count
    assert depth_l1(pred, gt) == pytest.approx(0.5)
    assert depth_l1(torch.from_numpy(pred), torch.from_numpy(gt)) == pytest.approx(0.5)
    with pytest.raises(InputError, match="no pixel"):
        depth_l1(pred, np.zeros_like(gt))
