"""The rig's lidar scan of the static stage: reading it, aligning a reconstruction to it, and
lifting image points onto it.

A scan is points [N, 3] (metres, stage frame) with unit normals [N, 3]. Surfaces are treated as
locally planar: a point's distance to the scan is its point-to-plane distance to the nearest scan
point, ``n · (x - p)``.

scipy is imported where it is used: ingest reads scans (:func:`decode_ply_points`) on every run,
cached or not, and importing scipy costs it a second or two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from volcap_core.calibration.geometry import Similarity, so3_exp


def decode_ply_points(data: bytes) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices of a PLY (binary little-endian or ASCII; float/double x y z, optional nx ny nz)
    -> points [N, 3] float64 and normals [N, 3] float64 (None when the file has none)."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError("not a PLY file")
    nl = data.index(b"\n", end) + 1
    header = data[:nl].decode("ascii", "replace").splitlines()
    fmt = header[1].split()[1] if len(header) > 1 else ""
    n, props, in_vertex = 0, [], False
    for line in header:
        parts = line.split()
        if parts[:1] == ["element"]:
            in_vertex = parts[1] == "vertex"
            if in_vertex:
                n = int(parts[2])
        elif parts[:1] == ["property"] and in_vertex:
            if parts[1] == "list":
                raise ValueError("PLY vertex lists are not supported")
            props.append((parts[2], parts[1]))
    types = {"float": "f4", "float32": "f4", "double": "f8", "float64": "f8", "uchar": "u1", "uint8": "u1",
             "int": "i4", "int32": "i4", "uint": "u4", "short": "i2", "ushort": "u2", "char": "i1"}
    if fmt == "ascii":
        rows = data[nl:].decode("ascii").split("\n")[:n]
        arr = np.array([[float(v) for v in r.split()[:len(props)]] for r in rows], np.float64)
        cols = {name: arr[:, i] for i, (name, _) in enumerate(props)}
    elif fmt == "binary_little_endian":
        dt = np.dtype([(name, "<" + types[t]) for name, t in props])
        rec = np.frombuffer(data, dt, count=n, offset=nl)
        cols = {name: rec[name].astype(np.float64) for name, _ in props}
    else:
        raise ValueError(f"unsupported PLY format {fmt!r}")
    pts = np.stack([cols["x"], cols["y"], cols["z"]], 1)
    nrm = np.stack([cols["nx"], cols["ny"], cols["nz"]], 1) if "nx" in cols else None
    return pts, nrm


def estimate_normals(points: np.ndarray, k: int = 12) -> np.ndarray:
    """Unit normals [N, 3] from the k nearest neighbours' covariance (sign arbitrary)."""
    from scipy.spatial import cKDTree

    tree = cKDTree(points)
    _, idx = tree.query(points, k=min(k, len(points)))
    nb = points[idx] - points[idx].mean(1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    _, vec = np.linalg.eigh(cov)
    return vec[:, :, 0]


@dataclass
class LidarScan:
    """Scan points and normals with a KD-tree for nearest-point queries."""

    points: np.ndarray
    normals: np.ndarray

    def __post_init__(self):
        self.points = np.asarray(self.points, np.float64).reshape(-1, 3)
        if self.normals is None:
            self.normals = estimate_normals(self.points)
        self.normals = np.asarray(self.normals, np.float64).reshape(-1, 3)
        self.normals /= np.maximum(np.linalg.norm(self.normals, axis=1, keepdims=True), 1e-12)
        from scipy.spatial import cKDTree

        self.tree = cKDTree(self.points)

    @staticmethod
    def from_ply_bytes(data: bytes) -> "LidarScan":
        p, n = decode_ply_points(data)
        return LidarScan(p, n)

    def nearest(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For points [N, 3]: Euclidean distance to the nearest scan point [N], that point's index
        [N] and the signed point-to-plane distance [N]."""
        x = np.asarray(x, np.float64).reshape(-1, 3)
        d, i = self.tree.query(x)
        plane = np.einsum("ij,ij->i", self.normals[i], x - self.points[i])
        return d, i, plane

    def surface_distance(self, x: np.ndarray, max_point_distance: float = 0.2) -> np.ndarray:
        """|point-to-plane| distance [N]; inf where no scan point lies within ``max_point_distance``."""
        d, _, plane = self.nearest(x)
        out = np.abs(plane)
        out[d > max_point_distance] = np.inf
        return out


def align_to_lidar(points: np.ndarray, scan: LidarScan, init: Similarity = Similarity(),
                   gates: tuple[float, ...] = (0.5, 0.25, 0.12, 0.06, 0.04, 0.04, 0.04),
                   weights: np.ndarray | None = None, with_scale: bool = True) -> tuple[Similarity, dict]:
    """Robust point-to-plane ICP of a similarity ``x_stage = s R x + t`` taking ``points`` [N, 3]
    onto the scan, started at ``init``. Each round keeps pairs whose nearest scan point is within the
    round's gate (metres, after the current transform) and solves one Gauss-Newton step with Cauchy
    weights. Returns the similarity and stats (inliers, RMS plane distance in metres)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    wts = np.ones(len(pts)) if weights is None else np.asarray(weights, np.float64)
    T = Similarity(init.s, init.R.copy(), init.t.copy())
    stats = {}
    for gate in gates:
        for _ in range(3):
            y = T.apply(pts)
            d, idx, plane = scan.nearest(y)
            sel = d < gate
            if sel.sum() < 7:
                break
            n = scan.normals[idx[sel]]
            r = plane[sel]
            ys = y[sel]
            c = ys.mean(0)
            # perturbation y' = (1 + ds) (I + [w]x) (y - c) + c + dt  ->  r' = r + J [w, dt, ds]
            q = ys - c
            J = np.concatenate([np.cross(q, n), n, np.einsum("ij,ij->i", n, q)[:, None]], 1)
            if not with_scale:
                J = J[:, :6]
            scale = max(gate / 3.0, 1e-3)
            w = wts[sel] / (1.0 + (r / scale) ** 2)
            H = J.T @ (J * w[:, None]) + 1e-9 * np.eye(J.shape[1])
            g = J.T @ (w * r)
            dx = -np.linalg.solve(H, g)
            dw, dt = dx[:3], dx[3:6]
            ds = dx[6] if with_scale else 0.0
            step = Similarity(1.0 + ds, so3_exp(dw), c + dt - (1.0 + ds) * so3_exp(dw) @ c)
            T = step.compose(T)
            if np.linalg.norm(dx[:6]) < 1e-7:
                break
        stats = {"inliers": int(sel.sum()), "rms_plane_m": float(np.sqrt(np.mean(r ** 2))) if sel.any() else np.inf,
                 "gate_m": gate}
    return T, stats


def lift_to_lidar(K: np.ndarray, world_to_camera: np.ndarray, uv: np.ndarray, scan: LidarScan,
                  width: int, height: int, radius_px: float = 3.0, depth_tol: float = 0.08,
                  max_depth: float = 1e3) -> tuple[np.ndarray, np.ndarray]:
    """Intersect the viewing rays of OpenCV pixels ``uv`` [N, 2] of a calibrated camera with the scan.

    The scan is projected into the camera; for each pixel the front-most scan points projecting
    within ``radius_px`` (grown up to 4x where the scan is sparse in the image) give a tangent
    plane, and the ray is intersected with it. Returns points [N, 3] and a validity mask [N]
    (False where no scan point is near the ray or the intersection is implausible).
    """
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    R, t = world_to_camera[:3, :3], world_to_camera[:3, 3]
    C = -R.T @ t
    pc = scan.points @ R.T + t
    front = pc[:, 2] > 0.05
    margin = 4 * radius_px
    z = pc[front, 2]
    proj = pc[front, :2] / z[:, None] @ K[:2, :2].T + K[:2, 2]
    inside = ((proj[:, 0] > -margin) & (proj[:, 0] < width + margin)
              & (proj[:, 1] > -margin) & (proj[:, 1] < height + margin))
    ids = np.flatnonzero(front)[inside]
    proj, z = proj[inside], z[inside]
    out = np.zeros((len(uv), 3))
    ok = np.zeros(len(uv), bool)
    if len(ids) == 0:
        return out, ok
    from scipy.spatial import cKDTree

    tree = cKDTree(proj)
    Kinv = np.linalg.inv(K)
    rays = np.c_[uv, np.ones(len(uv))] @ Kinv.T @ R  # world directions (unnormalised, z_cam = 1)
    for i in range(len(uv)):
        cand = []
        for r in (radius_px, 2 * radius_px, 4 * radius_px):
            cand = tree.query_ball_point(uv[i], r)
            if len(cand) >= 3:
                break
        if not cand:
            continue
        cand = np.asarray(cand)
        zc = z[cand]
        zmin = zc.min()
        front_c = cand[zc < zmin * (1 + depth_tol) + 0.02]
        # nearest in the image among the front-most
        j = front_c[np.argmin(np.linalg.norm(proj[front_c] - uv[i], axis=1))]
        p, n = scan.points[ids[j]], scan.normals[ids[j]]
        den = n @ rays[i]
        if abs(den) < 1e-6:
            continue
        lam = n @ (p - C) / den
        if not (0.05 < lam < max_depth) or abs(lam - zmin) > 0.25 * zmin + 0.1:
            continue
        out[i] = C + lam * rays[i]
        ok[i] = True
    return out, ok


def depth_buffer(K: np.ndarray, world_to_camera: np.ndarray, width: int, height: int, points: np.ndarray,
                 splat_px: int = 4) -> np.ndarray:
    """The camera's z-buffer of scan points: nearest depth (metres along the optical axis) per pixel
    [H, W], min-filtered over ``2 splat_px + 1`` pixels to close the gaps between scan samples;
    inf where no point projects."""
    pc = np.asarray(points, np.float64) @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    z = pc[:, 2]
    ok = z > 0.1
    uv = pc[ok, :2] / z[ok, None] @ K[:2, :2].T + K[:2, 2]
    ix = np.round(uv).astype(np.int64)
    inside = (ix[:, 0] >= 0) & (ix[:, 0] < width) & (ix[:, 1] >= 0) & (ix[:, 1] < height)
    zbuf = np.full((height, width), np.inf)
    np.minimum.at(zbuf, (ix[inside, 1], ix[inside, 0]), z[ok][inside])
    from scipy.ndimage import minimum_filter

    return minimum_filter(zbuf, size=2 * splat_px + 1, mode="nearest")
