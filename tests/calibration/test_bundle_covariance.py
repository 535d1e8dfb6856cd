"""The bundle adjustment states how well it determines each camera (``bundle_adjust(...).sigma``),
and what it states is what repeated captures show: a principal point the adjustment refines widens
its camera's rotation, since a shift of the principal point by d px and a turn by d / f rad move the
image alike but for the second order of the projection."""

from __future__ import annotations

import numpy as np

from scipy.spatial.transform import Rotation

from tests.calibration.test_bundle_lens_groups import _arc_scene
from volcap_core.calibration.bundle import BundleOptions, bundle_adjust

F, CENTRE, NOISE, PRIOR_PX, MOUNT_M = 300.0, np.array([159.5, 89.5]), 0.1, 0.5, 0.002


def _scene():
    """200 points in a 6 x 5 x 3 m box and six cameras [6, 4, 4] on an arc 3.5 m around it (320x180,
    f 300): the lens-group tests' scene."""
    X, poses = _arc_scene(np.random.default_rng(0), 200)
    return X, np.stack(poses)


def _capture(X, poses, rng, principal):
    """Observations [M] of the six cameras with principal points ``principal`` [6, 2], NOISE px."""
    oc, op, uv = [], [], []
    for i, W in enumerate(poses):
        p = X @ W[:3, :3].T + W[:3, 3]
        x = p[:, :2] / p[:, 2:] * F + principal[i]
        vis = np.flatnonzero((p[:, 2] > 0.1) & (x[:, 0] > 0) & (x[:, 0] < 319) & (x[:, 1] > 0) & (x[:, 1] < 179))
        oc.append(np.full(len(vis), i))
        op.append(vis)
        uv.append(x[vis] + rng.normal(0, NOISE, (len(vis), 2)))
    return map(np.concatenate, (oc, op, uv))


def _adjust(X, poses, obs, mounts, principal_sigma_px):
    oc, op, uv = obs
    options = BundleOptions(pixel_sigma=NOISE, focal_sigma_rel=0.03, centre_sigma_m=MOUNT_M,
                            principal_sigma_px=principal_sigma_px, outlier_px=(3.0,))
    return bundle_adjust(poses, np.full(6, F), np.tile(CENTRE, (6, 1)), X, oc, op, uv, centre_prior=mounts,
                         options=options)


def test_the_stated_sigma_is_the_spread_over_repeated_captures():
    # 60 captures of the same scene, each with its own noise, each camera's true principal point
    # drawn around the assumed one with the prior's sigma and its mount surveyed to MOUNT_M; the
    # spread of the adjusted rotations and principal points around the truth against what the
    # adjustment says of each capture
    X, poses = _scene()
    rng = np.random.default_rng(1)
    rot, pp, stated_rot, stated_pp, rot_held, stated_held = [], [], [], [], [], []
    centres = np.stack([-W[:3, :3].T @ W[:3, 3] for W in poses])
    for _ in range(60):
        truth = CENTRE + rng.normal(0, PRIOR_PX, (6, 2))
        obs = tuple(_capture(X, poses, rng, truth))
        mounts = centres + rng.normal(0, MOUNT_M, (6, 3))
        out = _adjust(X, poses, obs, mounts, PRIOR_PX)
        rot.append(_turns(out, poses))
        # the principal point held where the prior says it is
        held = _adjust(X, poses, obs, mounts, None)
        rot_held.append(_turns(held, poses))
        stated_held.append(held.sigma.rotation_deg)
        pp.append(out.principal - truth)
        stated_rot.append(out.sigma.rotation_deg)
        stated_pp.append(out.sigma.principal_px)
    rot, pp, rot_held = np.array(rot), np.array(pp), np.array(rot_held)   # [60, 6, 3], [60, 6, 2], [60, 6, 3]

    def largest_sd(samples):                                                # [60, k] -> the largest sd
        return np.sqrt(np.linalg.eigvalsh(samples.T @ samples / len(samples)).max())

    measured_rot = np.degrees([largest_sd(rot[:, i]) for i in range(6)])
    measured_pp = np.array([largest_sd(pp[:, i]) for i in range(6)])
    stated_rot, stated_pp = np.mean(stated_rot, 0), np.mean(stated_pp, 0)
    print("rotation sd (deg) measured", measured_rot.round(4), "stated", stated_rot.round(4))
    print("principal point sd (px) measured", measured_pp.round(3), "stated", stated_pp.round(3))
    # 60 samples give each sd to ~10 %; over the six cameras to ~4 %
    assert 0.8 < (measured_rot / stated_rot).mean() < 1.25
    assert 0.8 < (measured_pp / stated_pp).mean() < 1.25
    assert np.all(stated_pp < PRIOR_PX)                                     # the footage adds to the prior

    # held, the adjustment cannot see the principal points' errors: it states a rotation tighter
    # than the turns that absorb them
    measured_held = np.degrees([largest_sd(rot_held[:, i]) for i in range(6)])
    stated_held = np.mean(stated_held, 0)
    print("principal point held: rotation sd (deg) measured", measured_held.round(4), "stated", stated_held.round(4))
    assert np.all(np.isnan(held.sigma.principal_px))
    assert (measured_held / stated_held).mean() > 1.4


def _turns(out, poses):
    """Each camera's rotation error [6, 3] (axis-angle, rad)."""
    return [Rotation.from_matrix(out.world_to_camera[i, :3, :3] @ poses[i, :3, :3].T).as_rotvec()
            for i in range(len(poses))]


def test_an_adjustment_without_rounds_states_its_start():
    # no outlier rounds and no scan: nothing is refined, and the sigma is that of the start
    X, poses = _scene()
    oc, op, uv = _capture(X, poses, np.random.default_rng(2), np.tile(CENTRE, (6, 1)))
    out = bundle_adjust(poses, np.full(6, F), np.tile(CENTRE, (6, 1)), X, oc, op, uv,
                        options=BundleOptions(pixel_sigma=NOISE, outlier_px=()))
    np.testing.assert_allclose(out.world_to_camera, poses, atol=1e-12)
    assert np.all(np.isfinite(out.sigma.rotation_deg)) and np.all(out.sigma.rotation_deg > 0)
