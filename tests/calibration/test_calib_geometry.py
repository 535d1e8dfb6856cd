"""Geometry helpers, lidar alignment and lifting, the torch bundle adjuster, COLMAP export."""

from __future__ import annotations

import cv2  # noqa: F401  (before pycolmap)
import numpy as np
import pycolmap
import pytest

from volcap_core.calibration.bundle import BundleOptions, bundle_adjust
from volcap_core.calibration.colmap_export import export_colmap
from volcap_core.calibration.geometry import (NEAR_PARALLEL_UP_COS, Similarity, intrinsic_matrix,
                                              look_at_rotation, pose_matrix, project, robust_umeyama,
                                              rotation_angle_deg, so3_exp, triangulate_points, umeyama)
from volcap_core.calibration.lidar import LidarScan, align_to_lidar, decode_ply_points, lift_to_lidar


def _cam(C, look=(0.0, 0.0, 1.0)):
    R = look_at_rotation(C, look)
    return pose_matrix(R, -R @ np.asarray(C, float))


def _room(spacing=0.1, seed=0):
    """Lidar-like samples of a box room (walls, floor) plus a crate, with normals."""
    rng = np.random.default_rng(seed)
    pts, nrm = [], []
    for axis, val, n in ((0, -4.0, (1, 0, 0)), (0, 4.0, (-1, 0, 0)), (1, -5.0, (0, 1, 0)), (1, 5.0, (0, -1, 0)),
                         (2, 0.0, (0, 0, 1))):
        k = int(80 / spacing ** 2 / 10)
        p = np.stack([rng.uniform(-4, 4, k), rng.uniform(-5, 5, k), rng.uniform(0, 3, k)], 1)
        p[:, axis] = val
        pts.append(p)
        nrm.append(np.tile(n, (k, 1)))
    k = 2000
    for cx in (-1.5, 1.5):                         # two crates: front faces (-y) and side faces (+-x)
        front = np.stack([cx + rng.uniform(-0.5, 0.5, k), np.full(k, 1.0), rng.uniform(0, 1, k)], 1)
        side = np.stack([np.full(k, cx - np.sign(cx) * 0.5), rng.uniform(1.0, 2.0, k), rng.uniform(0, 1, k)], 1)
        pts += [front, side]
        nrm += [np.tile((0, -1, 0), (k, 1)), np.tile((-np.sign(cx), 0, 0), (k, 1))]
    return LidarScan(np.concatenate(pts), np.concatenate(nrm).astype(float))


def test_look_at_is_an_opencv_world_to_camera_rotation():
    # From -y looking along +y with z up: world +x is image right, world -z image down (exactly).
    np.testing.assert_array_equal(look_at_rotation((0.0, -5.0, 1.0), (0.0, 0.0, 1.0)),
                                  [[1, 0, 0], [0, 0, -1], [0, 1, 0]])
    C, target = np.array([3.0, -2.0, 1.5]), np.array([0.2, 0.4, 1.0])
    R = look_at_rotation(C, target)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    K = intrinsic_matrix(500.0, 500.0, 320.0, 240.0)
    uv, z = project(K, pose_matrix(R, -R @ C), [target, target + [0.0, 0.0, 0.2]])
    np.testing.assert_allclose(uv[0], [320.0, 240.0], atol=1e-9)  # the target is the image centre
    assert z[0] == pytest.approx(np.linalg.norm(target - C))
    assert uv[1, 0] == pytest.approx(320.0) and uv[1, 1] < 240.0  # world up is image up, no tilt
    # roll turns the axes about the optical axis: at 90 degrees, old image-right is image-up
    Rr = look_at_rotation(C, target, 90.0)
    np.testing.assert_allclose(Rr[2], R[2], atol=1e-15)
    np.testing.assert_allclose(Rr[1], -R[0], atol=1e-15)


@pytest.mark.parametrize("direction", [(0.0, 0.0, -1.0), (0.0, 0.0, 1.0)])
def test_look_at_straight_down_or_up_puts_world_x_at_the_image_top(direction):
    C = np.array([0.5, 0.2, 4.0])
    R = look_at_rotation(C, C + 3 * np.asarray(direction))
    np.testing.assert_allclose(R, [[0, np.sign(direction[2]), 0], [-1, 0, 0], direction], atol=1e-15)
    # The fallback holds in a cone around the vertical, not only exactly on it; just outside it,
    # the image top is world +z projected onto the image plane again.
    inside, outside = NEAR_PARALLEL_UP_COS + 2e-4, NEAR_PARALLEL_UP_COS - 2e-4
    sin = np.sqrt(1 - inside**2)
    R = look_at_rotation(C, C + np.array([0.0, sin, -inside]))
    np.testing.assert_allclose(-R[1], [1.0, 0.0, 0.0], atol=1e-12)
    sin = np.sqrt(1 - outside**2)
    R = look_at_rotation(C, C + np.array([0.0, sin, -outside]))
    np.testing.assert_allclose(-R[1], [0.0, outside, sin], atol=1e-12)
    # Any up: the world axis most perpendicular to it, the first on ties (+y for up = +x).
    R = look_at_rotation(C, C + (2.0, 0.0, 0.0), up=(5.0, 0.0, 0.0))
    np.testing.assert_allclose(-R[1], [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(look_at_rotation(C, C + (0.0, -2.0, 0.0), up=(0.0, 1.0, 0.0))[1],
                               [-1.0, 0.0, 0.0], atol=1e-15)


@pytest.mark.parametrize("position, target, up, message", [
    ((1.0, 2.0, 3.0), (1, 2, 3), (0.0, 0.0, 1.0),
     r"camera at \[1.0, 2.0, 3.0\] looking at \[1, 2, 3\]: no optical axis"),
    ((0.0, 0.0, np.nan), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), r"camera at \[0.0, 0.0, nan\].*no optical axis"),
    ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 0.0), r"up \[0.0, 0.0, 0.0\] is not a direction"),
    ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, np.inf, 0.0), r"up \[0.0, inf, 0.0\] is not a direction"),
])
def test_look_at_without_a_direction_names_the_vectors(position, target, up, message):
    with pytest.raises(ValueError, match=message):
        look_at_rotation(position, target, up=up)


def test_similarity_pose_mapping_keeps_projections():
    rng = np.random.default_rng(0)
    T = Similarity(1.7, so3_exp([0.1, -0.3, 0.2]), np.array([0.5, -1.0, 2.0]))
    W = _cam([3.0, 1.0, 1.5])
    X = rng.normal(0, 1, (20, 3))
    Xc_old = X @ W[:3, :3].T + W[:3, 3]
    W2 = T.apply_pose(W)
    Xc_new = T.apply(X) @ W2[:3, :3].T + W2[:3, 3]
    np.testing.assert_allclose(Xc_new, T.s * Xc_old, atol=1e-9)   # same image, depths scaled


def test_umeyama_and_robust_variant():
    rng = np.random.default_rng(1)
    T = Similarity(0.8, so3_exp([0.2, 0.1, -0.4]), np.array([1.0, 2.0, 3.0]))
    src = rng.normal(0, 2, (30, 3))
    dst = T.apply(src)
    U = umeyama(src, dst)
    assert U.s == pytest.approx(0.8) and np.allclose(U.R, T.R) and np.allclose(U.t, T.t)
    dst[:5] += rng.normal(0, 3, (5, 3))
    V, inl = robust_umeyama(src, dst, threshold=0.1)
    assert inl[5:].all() and not inl[:5].any()
    assert V.s == pytest.approx(0.8, abs=1e-6)


def test_triangulation_dlt():
    rng = np.random.default_rng(2)
    X = rng.normal(0, 0.5, (50, 3)) + [0, 0, 1]
    K = np.array([[400.0, 0, 160], [0, 400, 120], [0, 0, 1]])
    Ws = [_cam([4 * np.cos(a), 4 * np.sin(a), 1.5]) for a in (0.0, 0.5, 1.0)]
    P = np.stack([K @ W[:3] for W in Ws])
    obs_p, obs_c, obs_xy = [], [], []
    for c in range(3):
        x = np.c_[X, np.ones(50)] @ P[c].T
        obs_p.append(np.arange(50))
        obs_c.append(np.full(50, c))
        obs_xy.append(x[:, :2] / x[:, 2:])
    Y = triangulate_points(P, np.concatenate(obs_p), np.concatenate(obs_c), np.concatenate(obs_xy), 51)
    np.testing.assert_allclose(Y[:50], X, atol=1e-8)
    assert np.isnan(Y[50]).all()


def test_ply_decoding(tmp_path):
    pts = np.random.default_rng(3).normal(size=(10, 3)).astype(np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (10, 1))
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 10\n" + "".join(
        f"property float {n}\n" for n in ("x", "y", "z", "nx", "ny", "nz")) + "end_header\n"
    data = header.encode() + np.concatenate([pts, nrm], 1).astype("<f4").tobytes()
    p, n = decode_ply_points(data)
    np.testing.assert_allclose(p, pts, atol=1e-7)
    np.testing.assert_allclose(n, nrm)


def test_icp_recovers_a_similarity_onto_the_scan():
    scan = _room()
    rng = np.random.default_rng(4)
    true = scan.points[rng.choice(len(scan.points), 800, replace=False)]
    T = Similarity(1.03, so3_exp([0.02, -0.03, 0.05]), np.array([0.2, -0.15, 0.1]))
    model = (true - T.t) @ T.R / T.s                       # T maps model -> stage
    U, st = align_to_lidar(model, scan, init=Similarity())
    np.testing.assert_allclose(U.apply(model), true, atol=5e-3)
    assert st["rms_plane_m"] < 2e-3


def test_lift_to_lidar_hits_the_nearest_surface():
    scan = _room(spacing=0.05)
    K = np.array([[300.0, 0, 159.5], [0, 300, 89.5], [0, 0, 1]])
    W = _cam([0.0, -4.5, 1.5], (0.0, 5.0, 1.0))
    uv = np.array([[159.5, 89.5], [40.0, 60.0], [300.0, 170.0]])
    X, ok = lift_to_lidar(K, W, uv, scan, 320, 180)
    assert ok.all()
    assert abs(X[0, 1] - 5.0) < 0.02                                  # the far wall, between the crates
    assert abs(X[1, 1] - 5.0) < 0.02 or abs(X[1, 0] + 4.0) < 0.02
    p = X @ W[:3, :3].T + W[:3, 3]
    np.testing.assert_allclose(p[:, :2] / p[:, 2:] @ K[:2, :2].T + K[:2, 2], uv, atol=1e-6)


def _room_views(X, principal, noise_px, rng, focal=300.0):
    """Five cameras on an arc looking into the room at (0, 3, 1) and their noisy observations of
    ``X`` [P, 3] (principal points [5, 2], 320x180): (world_to_camera list, obs_camera, obs_point, obs_xy)."""
    Cs = [np.array([3.0 * np.cos(a), 3.0 * np.sin(a) - 1.0, 1.5]) for a in np.linspace(-1.2, 1.2, 5)]
    Ws = [_cam(c, (0.0, 3.0, 1.0)) for c in Cs]
    oc, op, uv = [], [], []
    for c, W in enumerate(Ws):
        p = X @ W[:3, :3].T + W[:3, 3]
        x = p[:, :2] / p[:, 2:] * focal + principal[c]
        vis = np.flatnonzero((p[:, 2] > 0.1) & (x[:, 0] > 0) & (x[:, 0] < 319) & (x[:, 1] > 0) & (x[:, 1] < 179))
        oc.append(np.full(len(vis), c))
        op.append(vis)
        uv.append(x[vis] + rng.normal(0, noise_px, (len(vis), 2)))
    return (Ws, *map(np.concatenate, (oc, op, uv)))


def test_bundle_adjustment_with_lidar_prior_recovers_cameras():
    scan = _room(spacing=0.05)
    rng = np.random.default_rng(5)
    X = scan.points[rng.choice(len(scan.points), 1500, replace=False)]
    Ws, oc, op, uv = _room_views(X, np.tile([159.5, 89.5], (5, 1)), 0.1, rng)
    W0 = []
    for W in Ws:
        R = so3_exp(rng.normal(0, 0.005, 3)) @ W[:3, :3]
        C = -W[:3, :3].T @ W[:3, 3] + rng.normal(0, 0.03, 3)
        W0.append(pose_matrix(R, -R @ C))
    res = bundle_adjust(np.stack(W0), np.full(5, 300.0 * 1.01), np.tile([159.5, 89.5], (5, 1)),
                        X + rng.normal(0, 0.03, X.shape), oc, op, uv, scan=scan, focal_prior=np.full(5, 300.0),
                        options=BundleOptions(focal_sigma_rel=0.05, centre_sigma_m=0.5))
    for W, We in zip(Ws, res.world_to_camera):
        assert rotation_angle_deg(W[:3, :3], We[:3, :3]) < 0.1
        assert np.linalg.norm(-W[:3, :3].T @ W[:3, 3] + We[:3, :3].T @ We[:3, 3]) < 0.015
    np.testing.assert_allclose(res.focal, 300.0, rtol=4e-3)
    assert np.median(res.reprojection_px) < 0.5


def test_bundle_adjustment_refines_principal_points_only_when_asked():
    # the room scan seen by 5 cameras whose principal points are ~1 px off the image centre (as
    # the synthetic sensors'): with the prior the adjustment finds them and the rotations come out
    # right; held at the centre, a rotation absorbs the offset
    scan = _room(spacing=0.05)
    rng = np.random.default_rng(11)
    X = scan.points[rng.choice(len(scan.points), 3000, replace=False)]
    true_pp = np.array([159.5, 89.5]) + rng.normal(0, 1.0, (5, 2))
    Ws, oc, op, uv = _room_views(X, true_pp, 0.05, rng)
    centred = np.tile([159.5, 89.5], (5, 1))

    def adjust(principal_sigma_px):
        return bundle_adjust(np.stack(Ws), np.full(5, 300.0), centred, X + rng.normal(0, 0.02, X.shape), oc, op,
                             uv, scan=scan, options=BundleOptions(pixel_sigma=0.1, focal_sigma_rel=0.03,
                                                                  centre_sigma_m=0.3,
                                                                  principal_sigma_px=principal_sigma_px))

    free, held = adjust(2.0), adjust(None)
    np.testing.assert_array_equal(held.principal, centred)
    assert np.abs(free.principal - true_pp).max() < 0.35, free.principal - true_pp
    rot = [rotation_angle_deg(W[:3, :3], We[:3, :3]) for W, We in zip(Ws, free.world_to_camera)]
    rot_held = [rotation_angle_deg(W[:3, :3], We[:3, :3]) for W, We in zip(Ws, held.world_to_camera)]
    assert max(rot) < 0.06 and min(rot_held) > 0.15, (rot, rot_held)


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_export_reads_back(tmp_path, binary):
    K = np.array([[310.0, 0, 159.5], [0, 311.0, 89.5], [0, 0, 1]])
    cams = {f"S{i}": (K, _cam([4 * np.cos(i), 4 * np.sin(i), 1.5]), 320, 180) for i in range(3)}
    X = np.random.default_rng(6).normal(size=(25, 3))
    cols = np.random.default_rng(7).uniform(0, 1, (25, 3)).astype(np.float32)
    obs = (np.array([0, 0, 3]), np.array([0, 2, 1]), np.array([[10.0, 20.0], [30.0, 40.0], [50.0, 60.0]]))
    out = export_colmap(tmp_path / "model", cams, X, cols, binary=binary, observations=obs)
    ext = ".bin" if binary else ".txt"
    assert {"cameras" + ext, "images" + ext, "points3D" + ext} <= {p.name for p in out.iterdir()}
    rec = pycolmap.Reconstruction(str(out))
    assert rec.num_images() == 3 and rec.num_points3D() == 25
    for im in rec.images.values():
        cid = im.name[:-4]
        np.testing.assert_allclose(im.cam_from_world().matrix(), cams[cid][1][:3], atol=1e-9)
        cam = rec.cameras[im.camera_id]
        np.testing.assert_allclose(cam.params, [310, 311, 160, 90])
    got = np.array(sorted(p.xyz.tolist() for p in rec.points3D.values()))
    np.testing.assert_allclose(got, np.array(sorted(X.tolist())), atol=1e-9)
    assert sum(p.track.length() for p in rec.points3D.values()) == 3
