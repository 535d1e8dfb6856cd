"""Tracking-camera refinement on an analytic pan/tilt/zoom camera (no rendering: fast).

A camera at a fixed centre pans and zooms (focal +-15 %) over 24 frames. It sees a textured back
wall: a few noisy 2D-3D matches per frame (plus outliers), many 2D-2D matches between its own
frames (plus an "actor" that stays still in the image). Its lens encoder reads focal with a gain
and offset error and noise. With the priors the focal must be within 1 % and the frame-to-frame
jitter under 1 px; without them it must be visibly worse.

Tolerances are the measured figures times a stated margin. The scene is seeded (seed 0 in the tests,
seed 1 for the encoder smoother), so each test is deterministic; the spread over seeds 0-9, measured
at the same time (2026-11-23, commit a48be80 plus the working tree of that day), is quoted beside each
figure to show how far a different noise draw moves it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from volcap_core.calibration.geometry import look_at_rotation, rotation_angle_deg
from volcap_core.calibration.tracking.calibrate import TrackingProblem, dolly_zoom_start, solve_tracking
from volcap_core.calibration.tracking.lens import smooth_encoder_focal
from volcap_core.calibration.tracking.observe import TrackingObservations
from volcap_core.calibration.tracking.options import TrackingOptions
from volcap_core.calibration.tracking.solve import initialise_tracking, refine_tracking

T, W, H = 24, 320, 180
CX, CY = (W - 1) / 2, (H - 1) / 2


def tracking_observations(rng, proj, seen, wall, n3: int = 8, sigma3: float = 1.0) -> TrackingObservations:
    """The tracking solve's matches of a camera that sees ``wall`` [N, 3] through ``proj(t, X) ->
    (uv [N, 2], depth [N])`` where ``seen(t, X)`` [N] bool: per frame ``n3`` 2D-3D matches with
    ``sigma3`` px of noise plus 30 outliers (wrong 3D points), and 2D-2D matches between frames 1,
    2 and 4 apart: up to 150 wall points (0.3 px noise) and 40 points of a still 'actor' the camera
    follows."""
    f3, uv3, X3, vis = [], [], [], []
    for t in range(T):
        uv, _ = proj(t, wall)
        vis.append(np.flatnonzero(seen(t, wall)))
        pick = rng.choice(vis[-1], min(n3, len(vis[-1])), replace=False)
        f3.append(np.full(len(pick), t))
        uv3.append(uv[pick] + rng.normal(0, sigma3, (len(pick), 2)))
        X3.append(wall[pick])
        out = rng.choice(len(wall), 30)   # outliers: wrong 3D points
        f3.append(np.full(30, t))
        uv3.append(rng.uniform([0, 0], [W, H], (30, 2)))
        X3.append(wall[out])
    i2, j2, ui2, uj2 = [], [], [], []
    for k in (1, 2, 4):
        for i in range(T - k):
            j = i + k
            common = np.intersect1d(vis[i], vis[j])
            pick = rng.choice(common, min(150, len(common)), replace=False)
            a, _ = proj(i, wall[pick])
            b, _ = proj(j, wall[pick])
            actor = rng.uniform([120, 60], [200, 140], (40, 2))
            i2.append(np.full(len(pick) + 40, i))
            j2.append(np.full(len(pick) + 40, j))
            ui2.append(np.r_[a + rng.normal(0, 0.3, a.shape), actor])
            uj2.append(np.r_[b + rng.normal(0, 0.3, b.shape), actor + rng.normal(0, 0.3, actor.shape)])
    return TrackingObservations(T, W, H, np.concatenate(f3), np.concatenate(uv3), np.concatenate(X3),
                                np.concatenate(i2), np.concatenate(j2), np.concatenate(ui2), np.concatenate(uj2))


def _scene(seed=0):
    rng = np.random.default_rng(seed)
    C = np.array([4.9, -2.3, 1.9])
    f = 1800 * np.exp(0.15 * np.sin(2 * np.pi * np.arange(T) / 40 + 0.3))
    targets = np.stack([np.array([0.0, -0.6 + 0.05 * t, 1.6 + 0.01 * math.sin(t / 3)]) for t in range(T)])
    R = np.stack([look_at_rotation(C, targets[t]) for t in range(T)])
    wall = np.stack([np.full(20000, -3.5), rng.uniform(-7, 7, 20000), rng.uniform(0, 4, 20000)], 1)

    def proj(t, X):
        p = (X - C) @ R[t].T
        return f[t] * p[:, :2] / p[:, 2:3] + [CX, CY], p[:, 2]

    def seen(t, X):
        uv, z = proj(t, X)
        return (z > 0) & (uv[:, 0] > 0) & (uv[:, 0] < W - 1) & (uv[:, 1] > 0) & (uv[:, 1] < H - 1)

    obs = tracking_observations(rng, proj, seen, wall)
    enc = f * 1.008 + 6.0 + rng.normal(0, 0.002 * f)            # encoder in px: gain, offset, noise
    mount = C + np.array([0.01, -0.012, 0.008])
    return obs, C, R, f, enc, mount


def _errors(sol, C, R, f, head=np.array([0.0, -0.3, 1.6])):
    fe = np.abs(sol.K[:, 0, 0] / f - 1) * 100
    re = np.array([rotation_angle_deg(sol.world_to_camera[t, :3, :3], R[t]) for t in range(T)])
    Ce = -np.einsum("tji,tj->ti", sol.world_to_camera[:, :3, :3], sol.world_to_camera[:, :3, 3])

    def p(K, Rt, Ct, X):
        q = Rt @ (X - Ct)
        return K[0, 0] * q[:2] / q[2]

    jit = []
    for t in range(T - 1):
        de = p(sol.K[t + 1], sol.world_to_camera[t + 1, :3, :3], Ce[t + 1], head) - \
            p(sol.K[t], sol.world_to_camera[t, :3, :3], Ce[t], head)
        dg = p(np.diag([f[t + 1]] * 3), R[t + 1], C, head) - p(np.diag([f[t]] * 3), R[t], C, head)
        jit.append(np.linalg.norm(de - dg))
    return fe.max(), re.max(), np.linalg.norm(Ce - C, axis=1).max(), np.mean(jit)


def test_smooth_encoder_focal_is_robust_to_a_glitch():
    t = np.arange(48)
    true = 60 * np.exp(0.15 * np.sin(2 * np.pi * t / 50))
    rng = np.random.default_rng(1)
    read = true + rng.normal(0, 0.002 * true)
    read[20] += 8.0
    sm = smooth_encoder_focal(t, read, 48)
    # measured 0.25 % (seed 1; 0.13-0.45 % over seeds 0-9, 2026-11-23); 1.6x margin. A smoother
    # that is not robust (one unweighted pass) is bent 3.0-3.3 % by the glitch
    assert np.max(np.abs(sm / true - 1)) < 0.004
    # missing readings are filled
    sm2 = smooth_encoder_focal(t[::2], read[::2], 48)
    # measured 0.29 % (seed 1; 0.29-0.57 % over seeds 0-9, 2026-11-23); 2x margin
    assert np.max(np.abs(sm2 / true - 1)[1:-1]) < 0.006


@pytest.fixture(scope="module")
def solved():
    obs, C, R, f, enc, mount = _scene()
    prior = smooth_encoder_focal(np.arange(T), enc, T, 4.0)
    Ri, Ci, fi, info = initialise_tracking(obs, prior, mount, (CX, CY))
    out = {"truth": (C, R, f), "init": (Ri, Ci, fi), "info": info, "prior": prior}
    for mode in ("priors", "free", "independent"):
        out[mode] = refine_tracking([obs], [(Ri, Ci, fi)], [prior], np.array([[CX, CY]]), [mount],
                                    TrackingOptions(mode=mode))[0]
    return out


def test_initialisation_finds_the_orientation(solved):
    C, R, f = solved["truth"]
    Ri = solved["init"][0]
    # measured 0.14 deg (seed 0; 0.11-0.17 deg over seeds 0-9, 2026-11-23); 2x margin
    assert max(rotation_angle_deg(Ri[t], R[t]) for t in range(T)) < 0.3
    # measured: all 8 T = 192 true matches are inliers (seeds 0-9; 193 at seed 8, where one outlier
    # happens to agree); a loss of 5 % fails
    assert solved["info"]["ransac_inliers"] >= 0.95 * 8 * T


def test_priors_give_focal_within_1pct_and_sub_pixel_jitter(solved):
    C, R, f = solved["truth"]
    fe, re, ce, jit = _errors(solved["priors"], C, R, f)
    # measured at seed 0 (range over seeds 0-9), 2026-11-23; without the priors ("free") the same
    # figures are 2.4-3.2 %, 0.62-1.24 deg, 0.42-0.55 m and 1.3-2.6 px
    # focal: 0.33 % (0.09-0.41 %); 2.1x margin
    assert fe < 0.7, f"focal error {fe:.2f} %"
    # jitter: 0.57 px (0.56-0.73 px); 1.75x margin (the 1 px of the test's name)
    assert jit < 1.0, f"jitter {jit:.2f} px"
    # rotation: 0.23 deg (0.12-0.29 deg); 2x margin (1.5x the worst seed)
    assert re < 0.45, f"rotation error {re:.3f} deg"
    # centre: 6.3 cm (3.9-6.8 cm; the zoom/dolly valley, not noise); 1.6x margin
    assert ce < 0.1, f"centre error {ce * 100:.1f} cm"

    # The encoder reads 1.008 f + 6 px (+ 0.2 % noise), so the true correction of the smoothed
    # encoder focal s is gain 1/1.008 = 0.99206 and offset -6/1.008 = -5.95 px.
    sol = solved["priors"]
    # The combined correction is what the data determine: the corrected curve gain * s + offset
    # matches the true focal on average to 0.26 % (seed 0; 0.05-0.34 % over seeds 0-9); 2.3x margin.
    # The uncorrected encoder (gain 1, offset 0) is 1.19 % off (1.03-1.19 %) and fails.
    corrected = sol.gain * solved["prior"] + sol.offset
    assert abs(np.mean(corrected / f) - 1) < 0.006, (sol.gain, sol.offset)
    assert abs(np.mean(solved["prior"] / f) - 1) > 0.006                     # the check can fail
    # The gain alone is pulled towards 1 (the weak 1 % gain prior, along the gain/offset trade-off
    # that a 1630-2110 px zoom range with 0.2 % encoder noise leaves): measured 0.99491, 0.287 %
    # above 1/1.008, at seed 0; 2x margin, so 1.0 (no correction, 0.80 % above) fails. Other seeds
    # land 0.29-0.74 % above (0.9994 at seed 6): this bound holds for seed 0's data only.
    assert sol.gain == pytest.approx(1 / 1.008, rel=0.0057)
    assert not 1.0 == pytest.approx(1 / 1.008, rel=0.0057)


def test_without_priors_it_is_worse(solved):
    C, R, f = solved["truth"]
    with_p = _errors(solved["priors"], C, R, f)
    free = _errors(solved["free"], C, R, f)
    indep = _errors(solved["independent"], C, R, f)
    # ratios measured at seed 0 (range over seeds 0-9), 2026-11-23
    # jitter, free / priors: 3.1 (2.2-4.0); 1.55x margin (1.1x at the worst seed)
    assert free[3] > 2 * with_p[3], (free, with_p)
    # focal, free / priors: 8.6 (6.0-28); 2.1x margin
    assert free[0] > 4 * with_p[0], (free, with_p)
    # jitter, independent / priors: 95 (61-95); 2.4x margin
    assert indep[3] > 40 * with_p[3], (indep, with_p)
    # focal, independent / priors: 18 (18-78); 2x margin
    assert indep[0] > 9 * with_p[0], (indep, with_p)


def test_dolly_zoom_start_keeps_the_scene_its_size():
    # a start 3 % further along the zoom/dolly valley: the 2D-3D points in view (the oblique back
    # wall, so not one distance) keep their spread in the image within 0.7 %, where zooming alone
    # grows it by 3 % and a dolly the wrong way by about 6 % (a shift of the whole pattern is left
    # to the rotations). Only the points the camera sees: the outliers' 3D points lie anywhere on
    # the 14 m wall, far outside the view (with them the figure was 0.99-1.58 % over seeds 0-9,
    # above the old 1.5 % bound at seeds 2 and 3).
    obs, C, R, f, enc, mount = _scene()
    init = (R, np.repeat(C[None], T, 0), f)
    Rs, Cs, fs = dolly_zoom_start(init, obs, 1.03)
    np.testing.assert_allclose(fs, 1.03 * f)
    assert np.allclose(Rs, R)

    def spread(X, Ct, ft, Rt):
        q = (X - Ct) @ Rt.T
        uv = ft * q[:, :2] / q[:, 2:]
        return np.sqrt(((uv - uv.mean(0)) ** 2).sum(1).mean())

    for t in (0, T // 2, T - 1):
        X = obs.m3_X[obs.m3_frame == t]
        q = (X - C) @ R[t].T
        uv = f[t] * q[:, :2] / q[:, 2:] + [CX, CY]
        X = X[(q[:, 2] > 0) & (uv[:, 0] > 0) & (uv[:, 0] < W - 1) & (uv[:, 1] > 0) & (uv[:, 1] < H - 1)]
        assert len(X) >= 8
        # measured 0.32 % (seed 0, worst of the three frames; 0.19-0.35 % over seeds 0-9,
        # 2026-11-23); 2.2x margin
        assert abs(spread(X, Cs[t], fs[t], R[t]) / spread(X, C, f[t], R[t]) - 1) < 0.007


def test_solve_tracking_keeps_the_lowest_cost_start():
    obs, C, R, f, enc, mount = _scene()
    prior = smooth_encoder_focal(np.arange(T), enc * 1.02, T, 4.0)          # a 2.8 % encoder error
    Ri, Ci, fi, _ = initialise_tracking(obs, prior, mount, (CX, CY))
    problem = TrackingProblem(["S"], [obs], [(Ri, Ci, fi)], [prior], np.array([[CX, CY]]), [mount], {"S": {}})
    starts = (0.97, 0.98, 0.99, 1.0, 1.01, 1.02, 1.03)
    one = solve_tracking(problem)["S"]                                        # the default: one start
    scan = solve_tracking(problem, TrackingOptions(focal_scale_starts=starts))["S"]
    assert scan.stats["focal_scale_start"] in starts
    assert scan.stats["cost"] <= one.stats["cost"] + 1e-6
    # measured 0.72 % (seed 0; 0.54-0.72 % over seeds 0-5, 2026-11-23); 1.4x margin (the weak 1 %
    # gain prior holds the focal back from the 2.8 % correction: the gain ends at 0.984, not 0.973)
    assert _errors(scan, C, R, f)[0] < 1.0


def test_the_solve_slides_along_the_zoom_dolly_valley_past_a_match_behind_the_camera():
    """Started 3 % too long or too short along the zoom/dolly valley, the solve ends where the
    start at the encoder's focal ends, although one wrong 2D-3D match per frame lies behind the
    camera (the static reference holds the whole stage: a tracker's SIFT can match a point behind
    it). Such a match once gave the normal equations a slope of ~1e6 x f on its frame's focal (its
    residual is a constant, its 1/z Jacobian at the clamped depth was not), so every start stayed
    where it began and the covariance called the focal known to 0.05 %. The spread the solve
    reports (``focal_sigma_pct``, from the covariance) covers the error it makes."""
    obs, C, R, f, enc, mount = _scene()
    behind = C - 3.0 * R[:, 2, :]                      # 3 m behind it, along its view axis
    obs.m3_frame = np.r_[obs.m3_frame, np.arange(T)]
    obs.m3_uv = np.r_[obs.m3_uv, np.tile([[CX + 40.0, CY - 20.0]], (T, 1))]
    obs.m3_X = np.r_[obs.m3_X, behind]
    prior = smooth_encoder_focal(np.arange(T), enc, T, 4.0)
    Ri, Ci, fi, _ = initialise_tracking(obs, prior, mount, (CX, CY))
    problem = TrackingProblem(["S"], [obs], [(Ri, Ci, fi)], [prior], np.array([[CX, CY]]), [mount], {"S": {}})
    sols = {s: solve_tracking(problem, TrackingOptions(focal_scale_starts=(s,)))["S"] for s in (0.97, 1.0, 1.03)}
    focal = {s: float(np.mean(v.K[:, 0, 0] / f - 1) * 100) for s, v in sols.items()}
    # measured (2026-11-27): +0.26 % from each of the three starts, costs equal to 1e-8; before the
    # fix they ended at -1.86 %, +1.08 % and +4.15 %
    assert abs(focal[0.97] - focal[1.0]) < 0.05 and abs(focal[1.03] - focal[1.0]) < 0.05, focal
    assert abs(sols[0.97].stats["cost"] - sols[1.0].stats["cost"]) < 1e-3 * sols[1.0].stats["cost"]
    sigma = sols[1.0].stats["focal_sigma_pct"]
    # measured sigma 0.52 % (the 1 % encoder gain prior and 1 cm mount error leave the valley open
    # to about that), the error 0.26 %
    assert 0 < sigma and abs(focal[1.0]) < 3 * sigma, (focal, sigma)


def test_a_tracker_the_solve_cannot_support_is_an_error_naming_it_or_left_out():
    """Support (issue 13: never returned as calibrated): the analytic camera, with its 2D-3D
    matches, is supported; with only the wrong matches left in three frames it has no 2D-3D
    inliers and the priors alone would place it: an error naming the capture, the camera and the
    reason, or, allowed, the solution marked ``unsupported``."""
    from volcap_core.calibration.errors import CalibrationInputError
    from volcap_core.calibration.tracking_step import check_tracking_support
    from volcap_core.calibration.tracking.solve import tracking_support

    obs, C, R, f, enc, mount = _scene()
    prior = smooth_encoder_focal(np.arange(T), enc, T, 4.0)
    Ri, Ci, fi, _ = initialise_tracking(obs, prior, mount, (CX, CY))
    problem = TrackingProblem(["S"], [obs], [(Ri, Ci, fi)], [prior], np.array([[CX, CY]]), [mount], {"S": {}})
    good = solve_tracking(problem)["S"]
    # measured (2026-11-27): 192 inliers, orientation sigma 0.27° (bounds 8 and 2°)
    assert tracking_support(good) is None, good.stats
    assert check_tracking_support("cap", "S", good) is good and good.unsupported is None

    # the same take with the 2D-3D matches of frames 0-2 only, all of them wrong (random pixels):
    # a camera that matched nothing true against the static model
    keep = obs.m3_frame < 3
    noise = np.random.default_rng(5).uniform([0, 0], [W, H], (int(keep.sum()), 2))
    bad_obs = TrackingObservations(T, W, H, obs.m3_frame[keep], noise, obs.m3_X[keep],
                                   obs.m2_i, obs.m2_j, obs.m2_ui, obs.m2_uj, obs.H)
    bad = solve_tracking(TrackingProblem(["S"], [bad_obs], [(Ri, Ci, fi)], [prior], np.array([[CX, CY]]), [mount],
                                         {"S": {}}))["S"]
    why = tracking_support(bad)   # measured: 1 inlier
    assert why is not None and "2D-3D inliers" in why and "needs at least 8" in why, (why, bad.stats)
    with pytest.raises(CalibrationInputError) as err:
        check_tracking_support("night-take", "S011", bad)
    msg = str(err.value)
    assert msg.startswith("capture night-take: tracking camera S011 cannot be calibrated: ") and why in msg
    assert "--allow-unregistered" in msg
    left = check_tracking_support("night-take", "S011", bad, TrackingOptions(allow_unsupported=True))
    assert left.unsupported == why
    # the orientation bound: the good solve against a bound tighter than its covariance
    why = tracking_support(good, TrackingOptions(max_rotation_sigma_deg=1e-4))
    assert why is not None and why.startswith("its orientation is determined to "), why
