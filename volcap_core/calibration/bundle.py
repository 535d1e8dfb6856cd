"""Bundle adjustment of static cameras in torch, with the lidar scan as a prior on the points.

COLMAP's bundle adjuster takes no custom residual from Python, so this one carries the terms the
calibration needs (all robust, Cauchy, in units of their sigma):

- reprojection of every observation (``pixel_sigma`` px);
- point-to-plane distance of each point to its nearest lidar point (``lidar_sigma_m``), for points
  whose nearest scan point is within a gate (points on actors get none);
- a prior on each camera's log focal length around the lens metadata (``focal_sigma_rel``; None
  holds focal lengths fixed, as the paper does);
- a weak prior on each camera centre around a seed (the rig's nominal mounts), which only fixes
  what nothing else observes;
- optionally a prior on each principal point around the image centre (``principal_sigma_px``; None,
  the default, holds the principal points where they are given).

Levenberg-Marquardt on the normal equations with the points eliminated by a Schur complement:
the reduced camera system is dense [9C, 9C] (C cameras), the point blocks are 3x3. Rotations are
updated on the left (``R <- exp(w) R``, kornia's axis-angle map). float64 throughout.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from volcap_core.calibration.lidar import LidarScan

NCAM = 9  # rotation (3), centre (3), log focal (1), principal point (2)


@dataclass(frozen=True)
class BundleOptions:
    pixel_sigma: float = 1.0
    lidar_sigma_m: float = 0.01
    lidar_gates_m: tuple[float, ...] = (0.3, 0.15, 0.08, 0.05)
    focal_sigma_rel: float | None = 0.05
    centre_sigma_m: float = 1.0
    #: None holds the principal points fixed; a value (px) refines them around the ones given
    principal_sigma_px: float | None = None
    iterations: int = 15
    #: after each round, observations reprojecting worse than this (px) are dropped
    outlier_px: tuple[float, ...] = (8.0, 4.0, 3.0, 2.0)
    device: str = "cpu"


def _skew(v: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(v[..., 0])
    return torch.stack([torch.stack([z, -v[..., 2], v[..., 1]], -1),
                        torch.stack([v[..., 2], z, -v[..., 0]], -1),
                        torch.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def _cauchy_weight(r2: torch.Tensor) -> torch.Tensor:
    return 1.0 / (1.0 + r2)


def _cauchy_cost(r2: torch.Tensor) -> torch.Tensor:
    return torch.log1p(r2).sum()


class _State:
    def __init__(self, R, C, logf, pp, X):
        self.R, self.C, self.logf, self.pp, self.X = R, C, logf, pp, X

    def updated(self, dc: torch.Tensor, dp: torch.Tensor) -> "_State":
        dR = axis_angle_to_rotation_matrix(dc[:, :3])
        return _State(dR @ self.R, self.C + dc[:, 3:6], self.logf + dc[:, 6], self.pp + dc[:, 7:9], self.X + dp)


def bundle_adjust(world_to_camera: np.ndarray, focal: np.ndarray, principal: np.ndarray,
                  points: np.ndarray, obs_camera: np.ndarray, obs_point: np.ndarray, obs_xy: np.ndarray,
                  *, scan: LidarScan | None = None, focal_prior: np.ndarray | None = None,
                  centre_prior: np.ndarray | None = None,
                  options: BundleOptions = BundleOptions()) -> dict:
    """Refine static cameras and points.

    Shapes: ``world_to_camera`` [C, 4, 4] (OpenCV), ``focal`` [C] px (fx = fy), ``principal``
    [C, 2] OpenCV px (held fixed unless ``options.principal_sigma_px``), ``points`` [P, 3] metres, observations ``obs_camera`` [M],
    ``obs_point`` [M], ``obs_xy`` [M, 2] OpenCV px. ``focal_prior`` [C] px (default: ``focal``),
    ``centre_prior`` [C, 3] (default: the initial centres).

    Returns a dict: ``world_to_camera`` [C, 4, 4], ``focal`` [C], ``principal`` [C, 2], ``points`` [P, 3],
    ``on_lidar`` [P] bool (points that carried a lidar term in the last round), ``reprojection_px``
    [M], ``inlier`` [M] bool (observations kept in the last round) and ``stats``.
    """
    t0 = time.perf_counter()
    dev = torch.device(options.device)
    f64 = dict(dtype=torch.float64, device=dev)
    w2c = torch.as_tensor(np.asarray(world_to_camera), **f64)
    R = w2c[:, :3, :3].clone()
    C = -(R.transpose(1, 2) @ w2c[:, :3, 3:4])[..., 0]
    logf = torch.log(torch.as_tensor(np.asarray(focal, np.float64), **f64))
    pp0 = torch.as_tensor(np.asarray(principal, np.float64), **f64).reshape(-1, 2)
    X = torch.as_tensor(np.asarray(points, np.float64), **f64).reshape(-1, 3)
    oc = torch.as_tensor(np.asarray(obs_camera), dtype=torch.long, device=dev)
    op = torch.as_tensor(np.asarray(obs_point), dtype=torch.long, device=dev)
    uv = torch.as_tensor(np.asarray(obs_xy, np.float64), **f64).reshape(-1, 2)
    ncam, npt = R.shape[0], X.shape[0]
    logf0 = torch.log(torch.as_tensor(np.asarray(focal if focal_prior is None else focal_prior, np.float64), **f64))
    C0 = C.clone() if centre_prior is None else torch.as_tensor(np.asarray(centre_prior, np.float64), **f64)
    fix_focal = options.focal_sigma_rel is None
    pairs = _observation_pairs(op, npt)

    state = _State(R, C, logf, pp0.clone(), X)
    on_lidar = torch.zeros(npt, dtype=torch.bool, device=dev)
    history = []
    gates = options.lidar_gates_m if scan is not None else (None,) * len(options.outlier_px)
    keep = torch.ones(len(oc), dtype=torch.bool, device=dev)
    oc_all, op_all, uv_all = oc, op, uv
    for rnd, gate in enumerate(gates):
        if rnd > 0 and options.outlier_px:
            thr = options.outlier_px[min(rnd - 1, len(options.outlier_px) - 1)]
            keep = _residual_px(state, oc_all, op_all, uv_all).norm(dim=1) < thr
            cnt = torch.bincount(op_all[keep], minlength=npt)
            keep &= cnt[op_all] >= 2
            oc, op, uv = oc_all[keep], op_all[keep], uv_all[keep]
            pairs = _observation_pairs(op, npt)
        if scan is not None:
            plane_n, plane_d, on_lidar = _associate(scan, state.X, gate, dev)
        else:
            plane_n = plane_d = None
        lam = 1e-3
        cost = _cost(state, pp0, oc, op, uv, plane_n, plane_d, on_lidar, logf0, C0, options, fix_focal)
        for _ in range(options.iterations):
            dc, dp = _lm_step(state, pp0, oc, op, uv, plane_n, plane_d, on_lidar, logf0, C0, options,
                              fix_focal, pairs, lam, ncam, npt)
            new = state.updated(dc, dp)
            new_cost = _cost(new, pp0, oc, op, uv, plane_n, plane_d, on_lidar, logf0, C0, options, fix_focal)
            if new_cost < cost:
                rel = (cost - new_cost) / max(cost, 1e-12)
                state, cost = new, new_cost
                lam = max(lam / 3.0, 1e-9)
                if rel < 1e-7:
                    break
            else:
                lam *= 5.0
                if lam > 1e8:
                    break
        history.append(float(cost))
    Rn, Cn = state.R, state.C
    out_w2c = torch.eye(4, **f64).repeat(ncam, 1, 1)
    out_w2c[:, :3, :3] = Rn
    out_w2c[:, :3, 3] = -(Rn @ Cn[..., None])[..., 0]
    res = _residual_px(state, oc_all, op_all, uv_all)
    return {"world_to_camera": out_w2c.cpu().numpy(), "focal": torch.exp(state.logf).cpu().numpy(),
            "principal": state.pp.cpu().numpy(),
            "points": state.X.cpu().numpy(), "on_lidar": on_lidar.cpu().numpy(),
            "reprojection_px": res.norm(dim=1).cpu().numpy(), "inlier": keep.cpu().numpy(),
            "stats": {"cost_per_round": history, "seconds": time.perf_counter() - t0,
                      "lidar_points": int(on_lidar.sum())}}


def _observation_pairs(op: torch.Tensor, npt: int) -> tuple[torch.Tensor, torch.Tensor]:
    """All ordered pairs (i, j) of observations of the same point (i == j included)."""
    order = torch.argsort(op, stable=True)
    counts = torch.bincount(op, minlength=npt)
    starts = torch.cumsum(counts, 0) - counts
    lmax = int(counts.max()) if len(counts) else 0
    if lmax == 0:
        e = torch.zeros(0, dtype=torch.long, device=op.device)
        return e, e
    slot = torch.arange(lmax, device=op.device)
    table = starts[:, None] + slot[None, :]
    valid = slot[None, :] < counts[:, None]
    table = torch.where(valid, order[table.clamp(max=len(order) - 1)], torch.full_like(table, -1))
    a = table[:, :, None].expand(-1, lmax, lmax)
    b = table[:, None, :].expand(-1, lmax, lmax)
    m = (a >= 0) & (b >= 0)
    return a[m], b[m]


def _associate(scan: LidarScan, X: torch.Tensor, gate: float, dev):
    x = X.detach().cpu().numpy()
    d, idx, _ = scan.nearest(x)
    n = scan.normals[idx]
    dd = np.einsum("ij,ij->i", n, scan.points[idx])
    ok = d < gate
    return (torch.as_tensor(n, dtype=torch.float64, device=dev),
            torch.as_tensor(dd, dtype=torch.float64, device=dev),
            torch.as_tensor(ok, device=dev))


def _project(state: _State, oc, op):
    R = state.R[oc]
    Xc = (R @ (state.X[op] - state.C[oc])[..., None])[..., 0]
    f = torch.exp(state.logf)[oc]
    z = Xc[:, 2].clamp(min=1e-6)
    xn = Xc[:, :2] / z[:, None]
    return Xc, z, xn, f, R


def _residual_px(state, oc, op, uv):
    _, _, xn, f, _ = _project(state, oc, op)
    return f[:, None] * xn + state.pp[oc] - uv


def _cost(state, pp0, oc, op, uv, plane_n, plane_d, on_lidar, logf0, C0, o: BundleOptions, fix_focal):
    r = _residual_px(state, oc, op, uv) / o.pixel_sigma
    c = _cauchy_cost((r ** 2).sum(1))
    if plane_n is not None and on_lidar.any():
        rl = ((plane_n * state.X).sum(1) - plane_d)[on_lidar] / o.lidar_sigma_m
        c = c + _cauchy_cost(rl ** 2)
    if not fix_focal:
        c = c + (((state.logf - logf0) / o.focal_sigma_rel) ** 2).sum()
    c = c + (((state.C - C0) / o.centre_sigma_m) ** 2).sum()
    if o.principal_sigma_px is not None:
        c = c + (((state.pp - pp0) / o.principal_sigma_px) ** 2).sum()
    return float(c)


def _lm_step(state, pp0, oc, op, uv, plane_n, plane_d, on_lidar, logf0, C0, o: BundleOptions, fix_focal,
             pairs, lam, ncam, npt):
    Xc, z, xn, f, R = _project(state, oc, op)
    r = (f[:, None] * xn + state.pp[oc] - uv) / o.pixel_sigma                     # [M, 2]
    w = _cauchy_weight((r ** 2).sum(1)).sqrt()                              # [M]
    # d pi / d Xc  [M, 2, 3]
    dpi = torch.zeros(len(z), 2, 3, dtype=z.dtype, device=z.device)
    dpi[:, 0, 0] = f / z
    dpi[:, 1, 1] = f / z
    dpi[:, 0, 2] = -f * xn[:, 0] / z
    dpi[:, 1, 2] = -f * xn[:, 1] / z
    Jw = dpi @ (-_skew(Xc))
    JC = dpi @ (-R)
    Jf = (f[:, None] * xn)[..., None]
    Jpp = torch.eye(2, dtype=z.dtype, device=z.device).expand(len(z), 2, 2)
    Jc = torch.cat([Jw, JC, Jf, Jpp], 2)                                    # [M, 2, 9]
    if fix_focal:
        Jc[..., 6] = 0.0
    if o.principal_sigma_px is None:
        Jc[..., 7:9] = 0.0
    Jp = dpi @ R                                                            # [M, 2, 3]
    s = (w / o.pixel_sigma)[:, None, None]
    Jc, Jp = Jc * s, Jp * s
    rw = r * w[:, None]
    Hcc = torch.zeros(ncam, NCAM, NCAM, dtype=z.dtype, device=z.device)
    gc = torch.zeros(ncam, NCAM, dtype=z.dtype, device=z.device)
    Hcc.index_add_(0, oc, Jc.transpose(1, 2) @ Jc)
    gc.index_add_(0, oc, (Jc.transpose(1, 2) @ rw[..., None])[..., 0])
    Hpp = torch.zeros(npt, 3, 3, dtype=z.dtype, device=z.device)
    gp = torch.zeros(npt, 3, dtype=z.dtype, device=z.device)
    Hpp.index_add_(0, op, Jp.transpose(1, 2) @ Jp)
    gp.index_add_(0, op, (Jp.transpose(1, 2) @ rw[..., None])[..., 0])
    Hcp = Jc.transpose(1, 2) @ Jp                                           # [M, 9, 3]
    if plane_n is not None and on_lidar.any():
        rl = ((plane_n * state.X).sum(1) - plane_d) / o.lidar_sigma_m
        wl = _cauchy_weight(rl ** 2) * on_lidar.to(rl.dtype)
        nn = plane_n[:, :, None] * plane_n[:, None, :] / o.lidar_sigma_m ** 2
        Hpp = Hpp + wl[:, None, None] * nn
        gp = gp + (wl * rl / o.lidar_sigma_m)[:, None] * plane_n
    # priors
    idx = torch.arange(3, 6, device=z.device)
    Hcc[:, idx, idx] += 1.0 / o.centre_sigma_m ** 2
    gc[:, 3:6] += (state.C - C0) / o.centre_sigma_m ** 2
    if fix_focal:
        Hcc[:, 6, 6] += 1.0
    else:
        Hcc[:, 6, 6] += 1.0 / o.focal_sigma_rel ** 2
        gc[:, 6] += (state.logf - logf0) / o.focal_sigma_rel ** 2
    idx = torch.arange(7, 9, device=z.device)
    if o.principal_sigma_px is None:
        Hcc[:, idx, idx] += 1.0
    else:
        Hcc[:, idx, idx] += 1.0 / o.principal_sigma_px ** 2
        gc[:, 7:9] += (state.pp - pp0) / o.principal_sigma_px ** 2
    # Levenberg-Marquardt damping
    eyec = torch.eye(NCAM, dtype=z.dtype, device=z.device)
    eye3 = torch.eye(3, dtype=z.dtype, device=z.device)
    Hcc_d = Hcc + lam * (Hcc.diagonal(dim1=1, dim2=2)[..., None] * eyec) + 1e-12 * eyec
    Hpp_d = Hpp + lam * (Hpp.diagonal(dim1=1, dim2=2)[..., None] * eye3) + 1e-9 * eye3
    Hpp_inv = torch.linalg.inv(Hpp_d)
    # Schur complement on the points
    a, b = pairs
    blocks = Hcp[a] @ Hpp_inv[op[a]] @ Hcp[b].transpose(1, 2)              # [Q, 9, 9]
    S = torch.zeros(ncam * ncam, NCAM, NCAM, dtype=z.dtype, device=z.device)
    S.index_add_(0, oc[a] * ncam + oc[b], -blocks)
    S = S.view(ncam, ncam, NCAM, NCAM)
    S[torch.arange(ncam), torch.arange(ncam)] += Hcc_d
    S = S.permute(0, 2, 1, 3).reshape(ncam * NCAM, ncam * NCAM)
    v = Hpp_inv @ gp[..., None]                                             # [P, 3, 1]
    rhs = -gc
    rhs = rhs.index_add(0, oc, (Hcp @ v[op])[..., 0])
    dc = torch.linalg.solve(S, rhs.reshape(-1)).view(ncam, NCAM)
    # back-substitute the points
    t = gp.clone()
    t.index_add_(0, op, (Hcp.transpose(1, 2) @ dc[oc][..., None])[..., 0])
    dp = -(Hpp_inv @ t[..., None])[..., 0]
    return dc, dp
