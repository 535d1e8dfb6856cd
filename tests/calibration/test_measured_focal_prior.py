"""A measured focal needs evidence to move (``focal_prior.adjust_with_held_focals``, issue 31).

Analytic cameras (no images, ~2 s): five cameras on an arc around a room of points, observed with
0.3 px noise. Each camera's rig carries a measured focal; one of them is 3 % wrong (a lens calibration
from another unit). The adjustment holds the right ones at the tight prior and releases the wrong
one, whose footage shows it, to the loose prior, which then recovers it; the decision and its
evidence are returned per camera. A camera with only a nominal focal keeps the loose prior and gets
no decision.
"""

from __future__ import annotations

import numpy as np

from volcap_core.calibration.bundle import BundleOptions, bundle_adjust
from volcap_core.calibration.focal_prior import MEASURED_FOCAL_SIGMA_REL, RELEASE_CHI2, adjust_with_held_focals
from volcap_core.calibration.geometry import look_at_rotation, pose_matrix, so3_exp

F = 300.0
PP = np.array([159.5, 89.5])


def _scene(seed: int = 0, noise_px: float = 0.3):
    rng = np.random.default_rng(seed)
    X = np.stack([rng.uniform(-3, 3, 1500), rng.uniform(1, 6, 1500), rng.uniform(0, 2.5, 1500)], 1)
    centres = [np.array([4.0 * np.cos(a), 4.0 * np.sin(a) - 2.5, 1.5]) for a in np.linspace(-1.0, 1.0, 5)]
    truth, start, oc, op, uv = [], [], [], [], []
    for c, C in enumerate(centres):
        R = look_at_rotation(C, (0.0, 3.0, 1.0))
        truth.append(pose_matrix(R, -R @ C))
        R0 = so3_exp(rng.normal(0, 0.005, 3)) @ R
        C0 = C + rng.normal(0, 0.02, 3)
        start.append(pose_matrix(R0, -R0 @ C0))
        p = X @ R.T - R @ C
        x = p[:, :2] / p[:, 2:] * F + PP
        vis = np.flatnonzero((p[:, 2] > 0.1) & (x[:, 0] > 0) & (x[:, 0] < 319) & (x[:, 1] > 0) & (x[:, 1] < 179))
        oc.append(np.full(len(vis), c))
        op.append(vis)
        uv.append(x[vis] + rng.normal(0, noise_px, (len(vis), 2)))
    oc, op, uv = map(np.concatenate, (oc, op, uv))
    return np.stack(truth), np.stack(start), np.array(centres), X + rng.normal(0, 0.02, X.shape), oc, op, uv


def test_a_wrong_lens_calibration_is_released_and_right_ones_held():
    truth, start, centres, X0, oc, op, uv = _scene()
    measured = np.array([F, F, F * 1.03, F, F])    # camera 2's lens calibration is 3 % long
    options = BundleOptions(focal_sigma_rel=0.03, centre_sigma_m=0.03, sigma_from_residuals=True)

    def adjust(focal_sigma):
        return bundle_adjust(start, measured, np.tile(PP, (5, 1)), X0, oc, op, uv, focal_prior=measured,
                             centre_prior=centres, focal_sigma=focal_sigma, options=options)

    res, decided = adjust_with_held_focals(adjust, [True, True, True, True, False], measured, oc,
                                           loose_sigma_rel=0.03)
    print({i: d for i, d in decided.items()})
    assert sorted(decided) == [0, 1, 2, 3]         # camera 4's focal is nominal: no decision, loose prior
    assert not decided[2].held and decided[2].evidence_chi2 > RELEASE_CHI2
    assert all(decided[i].held and decided[i].evidence_chi2 < RELEASE_CHI2 for i in (0, 1, 3)), decided
    # released, the wrong focal comes back to the truth; held, the right ones stay within the tight prior
    assert abs(res.focal[2] / F - 1) < 0.01, res.focal
    assert np.all(np.abs(res.focal[[0, 1, 3]] / F - 1) < MEASURED_FOCAL_SIGMA_REL), res.focal


def test_without_measured_focals_it_is_the_one_loose_adjustment():
    truth, start, centres, X0, oc, op, uv = _scene(seed=1)
    options = BundleOptions(focal_sigma_rel=0.03, centre_sigma_m=0.03)
    calls = []

    def adjust(focal_sigma):
        calls.append(np.array(focal_sigma))
        return bundle_adjust(start, np.full(5, F), np.tile(PP, (5, 1)), X0, oc, op, uv, centre_prior=centres,
                             focal_sigma=focal_sigma, options=options)

    res, decided = adjust_with_held_focals(adjust, [False] * 5, np.full(5, F), oc, loose_sigma_rel=0.03)
    assert decided == {} and len(calls) == 1 and np.all(calls[0] == 0.03)
    # the per-camera sigma at the options' value is the adjustment without it, to the bit
    plain = bundle_adjust(start, np.full(5, F), np.tile(PP, (5, 1)), X0, oc, op, uv, centre_prior=centres,
                          options=options)
    np.testing.assert_array_equal(res.world_to_camera, plain.world_to_camera)
    np.testing.assert_array_equal(res.focal, plain.focal)
