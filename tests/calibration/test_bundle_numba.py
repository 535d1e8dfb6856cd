"""The compiled Schur complement of the bundle adjustment (calibration/bundle_numba.py) against the
torch code it replaces: the same reduced camera system bit for bit, and so the same adjustment, with
shared lens-group unknowns and with lens corrections (n = 11 parameters a camera) too."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("numba")

from tests.calibration.test_bundle_lens_groups import _adjust, _problem, _rectified_views  # noqa: E402
from volcap_core.calibration import bundle  # noqa: E402
from volcap_core.calibration.bundle import BundleOptions, bundle_adjust  # noqa: E402
from volcap_core.calibration.bundle_numba import add_observation_blocks, subtract_point_blocks  # noqa: E402


def _both(monkeypatch, run):
    """``run()`` through the compiled blocks, then through the torch code."""
    ours = run()
    monkeypatch.setattr(bundle, "_compiled_normal_equations", lambda: None)
    return ours, run()


def test_the_blocks_are_the_torch_products_bit_for_bit():
    g = torch.Generator().manual_seed(0)
    ncam, npt, n = 4, 30, 11
    op = torch.randint(0, npt, (200,), generator=g)
    oc = torch.randint(0, ncam, (200,), generator=g)
    Hcp = torch.randn(200, n, 3, generator=g, dtype=torch.float64)
    A = torch.randn(npt, 3, 3, generator=g, dtype=torch.float64)
    Hpp_inv = A @ A.transpose(1, 2) + torch.eye(3, dtype=torch.float64)
    a, b = bundle._observation_pairs(op, npt)
    ref = torch.zeros(ncam * ncam, n, n, dtype=torch.float64)
    ref.index_add_(0, oc[a] * ncam + oc[b], -(Hcp[a] @ Hpp_inv[op[a]] @ Hcp[b].transpose(1, 2)))
    ours = torch.zeros_like(ref)
    subtract_point_blocks(ours.numpy(), Hcp.numpy(), Hpp_inv.numpy(), oc.numpy(), op.numpy(), a.numpy(), b.numpy(),
                          ncam)
    assert len(a) > 200 and torch.equal(ours, ref)


def test_the_observation_blocks_are_the_torch_sums_bit_for_bit():
    g = torch.Generator().manual_seed(1)
    ncam, npt, n, M = 3, 20, 9, 300
    oc, op = torch.randint(0, ncam, (M,), generator=g), torch.randint(0, npt, (M,), generator=g)
    Jc, Jp, rw = (torch.randn(*shape, generator=g, dtype=torch.float64) for shape in ((M, 2, n), (M, 2, 3), (M, 2)))
    ref = [torch.zeros(ncam, n, n, dtype=torch.float64), torch.zeros(ncam, n, dtype=torch.float64),
           torch.zeros(npt, 3, 3, dtype=torch.float64), torch.zeros(npt, 3, dtype=torch.float64)]
    ref[0].index_add_(0, oc, Jc.transpose(1, 2) @ Jc)
    ref[1].index_add_(0, oc, (Jc.transpose(1, 2) @ rw[..., None])[..., 0])
    ref[2].index_add_(0, op, Jp.transpose(1, 2) @ Jp)
    ref[3].index_add_(0, op, (Jp.transpose(1, 2) @ rw[..., None])[..., 0])
    ours = [torch.zeros_like(t) for t in ref]
    Hcp = add_observation_blocks(Jc.numpy(), Jp.numpy(), rw.numpy(), oc.numpy(), op.numpy(), *(t.numpy() for t in ours))
    assert torch.equal(torch.from_numpy(Hcp), Jc.transpose(1, 2) @ Jp)
    assert all(torch.equal(a, b) for a, b in zip(ours, ref))


def test_an_adjustment_is_the_same_through_both_paths(monkeypatch):
    problem, mounts = _problem(3)
    ours, ref = _both(monkeypatch, lambda: _adjust(problem, mounts, share_group_principal=True,
                                                   principal_sigma_px=2.0))
    assert np.array_equal(ours.world_to_camera, ref.world_to_camera)
    assert np.array_equal(ours.focal, ref.focal) and np.array_equal(ours.principal, ref.principal)
    assert ours.stats["cost_per_round"] == ref.stats["cost_per_round"]
    assert np.isfinite(ours.sigma.rotation_deg).all() and np.array_equal(ours.sigma.rotation_deg, ref.sigma.rotation_deg)


def test_an_adjustment_with_lens_corrections_is_the_same_through_both_paths(monkeypatch):
    rng = np.random.default_rng(4)
    rig_k = (0.10, -0.018, -0.0006, 0.0001)
    poses, X, oc, op, uv = _rectified_views(rng, rig_k, (0.104, -0.016, -0.0006, 0.0001))
    from volcap_core.calibration.distortion import Distortion
    from volcap_core.calibration.sfm import Intrinsics
    from volcap_core.calibration.static import _radial_lens

    lens = _radial_lens(Intrinsics(300.0, 300.0, 159.5, 89.5, 320, 180),
                        Intrinsics(300.0, 300.0, 159.5, 89.5, 320, 180, Distortion("OPENCV", rig_k)))
    centres = np.stack([-W[:3, :3].T @ W[:3, 3] for W in poses])

    def run():
        return bundle_adjust(np.stack(poses), np.full(6, 300.0), np.tile([159.5, 89.5], (6, 1)), X, oc, op, uv,
                             focal_prior=np.full(6, 300.0), centre_prior=centres, lens=[lens] * 6,
                             options=BundleOptions(distortion_sigma=0.01, outlier_px=(3.0,)))

    ours, ref = _both(monkeypatch, run)
    assert ours.distortion is not None and np.array_equal(ours.distortion, ref.distortion)
    assert np.array_equal(ours.world_to_camera, ref.world_to_camera)
