"""Colour calibration between cameras/rigs: affine fit in linear light, ΔE76 / ΔE2000."""

from __future__ import annotations

import numpy as np
import pytest

from volcap_core.calibration.colour import (apply_colour_matrix, calibrate_colour, chart_patches_in_view,
                                            colour_residuals, delta_e2000, fit_colour_matrix, linear_rgb_to_lab)
from volcap_core.calibration.geometry import look_at_rotation, pose_matrix

# linear sRGB reflectances of a ColorChecker (24 patches, approximate)
CHART = np.array([
    [0.172, 0.084, 0.058], [0.539, 0.305, 0.223], [0.122, 0.195, 0.337], [0.095, 0.150, 0.056],
    [0.235, 0.216, 0.440], [0.136, 0.509, 0.402], [0.674, 0.205, 0.024], [0.084, 0.106, 0.388],
    [0.528, 0.085, 0.121], [0.112, 0.045, 0.141], [0.339, 0.506, 0.049], [0.761, 0.359, 0.020],
    [0.030, 0.047, 0.287], [0.068, 0.297, 0.068], [0.436, 0.030, 0.040], [0.835, 0.567, 0.010],
    [0.495, 0.084, 0.295], [0.000, 0.241, 0.375], [0.883, 0.882, 0.858], [0.584, 0.589, 0.587],
    [0.358, 0.362, 0.361], [0.198, 0.199, 0.199], [0.089, 0.090, 0.090], [0.031, 0.032, 0.032]])


def test_ciede2000_matches_published_pairs():
    # Sharma, Wu & Dalal (2005), test data pairs 1, 7, 17, 25
    lab1 = np.array([[50.0, 2.6772, -79.7751], [50.0, 0.0, 0.0], [50.0, 2.5, 0.0], [60.2574, -34.0099, 36.2677]])
    lab2 = np.array([[50.0, 0.0, -82.7485], [50.0, -1.0, 2.0], [73.0, 25.0, -18.0], [60.4626, -34.1751, 39.4387]])
    np.testing.assert_allclose(delta_e2000(lab1, lab2), [2.0425, 2.3669, 27.1492, 1.2644], atol=1e-4)


def test_lab_of_white_and_black():
    np.testing.assert_allclose(linear_rgb_to_lab(np.ones(3)), [100, 0, 0], atol=1e-3)
    np.testing.assert_allclose(linear_rgb_to_lab(np.zeros(3)), [0, 0, 0], atol=1e-9)


def test_fit_recovers_matrix_and_offset_and_reduces_delta_e():
    rng = np.random.default_rng(0)
    M = np.eye(3) + rng.normal(0, 0.08, (3, 3))
    b = rng.normal(0, 0.01, 3)
    src = CHART * 0.7
    ref = apply_colour_matrix(src, M, b)
    Mf, bf = fit_colour_matrix(src, ref)
    np.testing.assert_allclose(Mf, M, atol=1e-9)
    np.testing.assert_allclose(bf, b, atol=1e-9)
    noisy = ref + rng.normal(0, 0.002, ref.shape)
    noisy[3] += 0.2                                              # one bad patch (glare)
    res = calibrate_colour(src, noisy, robust_iterations=3)
    assert res["before"]["delta_e2000_mean"] > 5
    good = np.arange(24) != 3
    after = colour_residuals(src[good], noisy[good], res["matrix"], res["offset"])
    assert after["delta_e2000_mean"] < 0.6
    assert after["delta_e76_mean"] < 1.5


def test_fit_needs_enough_patches():
    with pytest.raises(ValueError, match=">= 4"):
        fit_colour_matrix(CHART[:3], CHART[:3])


def test_chart_patches_are_sampled_through_a_calibrated_view():
    # a flat chart at x = 0 seen from x = 3: each patch a uniform colour
    h, w, f = 240, 320, 400.0
    C = np.array([3.0, 0.0, 1.0])
    R = look_at_rotation(C, (0.0, 0.0, 1.0))
    W = pose_matrix(R, -R @ C)
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    centres = np.array([[0.0, -0.25 + 0.1 * (i % 6), 1.15 - 0.1 * (i // 6)] for i in range(24)])
    v, u = np.mgrid[0:h, 0:w]
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ R
    t = -C[0] / rays[..., 0]
    P = C + t[..., None] * rays
    img = np.zeros((h, w, 3))
    for i, c in enumerate(centres):
        inside = (np.abs(P[..., 1] - c[1]) < 0.045) & (np.abs(P[..., 2] - c[2]) < 0.045)
        img[inside] = CHART[i]
    cols, ok = chart_patches_in_view(img, K, W, centres, 0.09)
    assert ok.all()
    np.testing.assert_allclose(cols, CHART, atol=1e-9)
