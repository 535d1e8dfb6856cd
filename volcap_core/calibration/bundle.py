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
  the default, holds the principal points where they are given);
- optionally (``distortion_sigma``; None, the default, holds the lens) corrections ``dk1``, ``dk2`` to
  the radial distortion the observations were rectified with (``bundle_adjust(lens=...)``: cameras
  whose images and observations were resampled into a pinhole through a lens calibration's k1, k2),
  with a prior of that sigma around zero (the lens calibration's accuracy). To first order in the
  correction, a rectified observation of the true lens sits at ``u + (u - c) g(rho²)``, ``u`` the
  pinhole projection, ``c`` / ``f_r`` the rectification's principal point and focal, ``rho = |u - c| /
  f_r`` and ``g = (dk1 rho² + dk2 rho⁴) / (1 + 3 k1 rho² + 5 k2 rho⁴ + 7 k3 rho⁶)`` (the correction
  of the distorted radius mapped back through the rectification's radial derivative, k3 that of a
  FULL_OPENCV lens, 0 otherwise; 0.0002 px from the exact rectification for a 0.003 correction of
  k1 = 0.1 at the corners of a 320x180 view at f = 310 px).

Cameras of one lens group (``lens_group``: the rig's ``lens_group``, one body and lens model) can
share ONE log focal (``BundleOptions.share_group_focal``), one principal point
(``share_group_principal``) and one lens correction (``share_group_distortion``); poses are always
per camera. A shared parameter is one unknown of the normal equations (:func:`camera_parameters`),
with one prior. All three are off by default: the units of one model differ (the principal point is
where a unit's sensor sits behind its lens; focal and distortion by the lens's tolerance), and
holding two units of the distorted demo rig to one focal made its static cameras worse.

Levenberg-Marquardt on the normal equations with the points eliminated by a Schur complement:
the reduced camera system is dense [9C, 9C] (C cameras; fewer unknowns when a lens group shares its
intrinsics: the per-camera system is summed onto the shared ones), the point blocks are 3x3.
Rotations are updated on the left (``R <- exp(w) R``, kornia's axis-angle map). float64 throughout.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from volcap_core.calibration.lidar import LidarScan

NCAM = 9  # rotation (3), centre (3), log focal (1), principal point (2)
NDIST = 2  # with lens corrections: dk1, dk2 (after the 9)


@dataclass(frozen=True)
class BundleOptions:
    pixel_sigma: float = 1.0
    lidar_sigma_m: float = 0.01
    lidar_gates_m: tuple[float, ...] = (0.3, 0.15, 0.08, 0.05)
    focal_sigma_rel: float | None = 0.05
    centre_sigma_m: float = 1.0
    #: None holds the principal points fixed; a value (px) refines them around the ones given
    principal_sigma_px: float | None = None
    #: None holds the lens (the observations are taken as rectified exactly); a value refines
    #: corrections to the radial k1, k2 of the cameras given a ``lens`` with this prior sigma around
    #: zero (a lens calibration's accuracy in k1 and k2)
    distortion_sigma: float | None = None
    #: the covariance (``BundleResult.sigma``) counts the observations at the robust spread of their
    #: inliers' residuals (1.4826 MAD per coordinate, at least 0.05 px) instead of ``pixel_sigma``:
    #: for an adjustment whose ``pixel_sigma`` is a loose weighting (step 4's 1 px, against
    #: residuals of ~0.1-0.4 px), so that its sigma say what the data and the priors hold
    sigma_from_residuals: bool = False
    iterations: int = 15
    #: after each round, observations reprojecting worse than this (px) are dropped
    outlier_px: tuple[float, ...] = (8.0, 4.0, 3.0, 2.0)
    #: cameras of one lens group (``bundle_adjust(lens_group=...)``) share one focal: one unknown,
    #: one prior (around the mean of the members' priors). Off by default: a lens group is one body and
    #: lens *model* calibrated once (``hardware.rig``), its units' focals differ by that calibration's
    #: error, and on the distorted demo capture one focal for both made the static rotations worse
    #: (docs/calibration.md)
    share_group_focal: bool = False
    #: ... and one principal point (when principal points are refined). Off: a lens group is one
    #: body and lens *model*, and each unit's principal point is where its sensor sits behind its lens
    share_group_principal: bool = False
    #: ... and one lens correction (when the distortion is refined). Off: each unit has its own
    #: lens, the group's calibration being of one of them (or of the model)
    share_group_distortion: bool = False
    device: str = "cpu"


@dataclass(frozen=True)
class CameraSigma:
    """How well an adjustment determines each camera: the standard deviations from the solution's
    covariance (:func:`_camera_sigma`), each [C]; NaN for an intrinsic the adjustment holds."""

    #: the largest standard deviation of the camera's rotation over the axes (degrees)
    rotation_deg: np.ndarray
    #: the largest standard deviation of the camera's centre over the axes (metres)
    centre_m: np.ndarray
    #: the standard deviation of the log focal (relative)
    focal_rel: np.ndarray
    #: the largest standard deviation of the principal point over x, y (px)
    principal_px: np.ndarray
    #: directions of the cameras that the observations and priors leave undetermined (two cameras
    #: without a scan: their turn about the baseline, which only the seed poses hold), left out of
    #: the sigma above (:func:`_covariance`)
    undetermined: int = 0


@dataclass(frozen=True)
class BundleResult:
    """What :func:`bundle_adjust` returns: C cameras, P points, M observations (in the order given)."""

    #: refined poses [C, 4, 4] (OpenCV, metres)
    world_to_camera: np.ndarray
    #: refined focal lengths [C] (px, fx = fy)
    focal: np.ndarray
    #: principal points [C, 2] (OpenCV px; as given when held)
    principal: np.ndarray
    #: refined points [P, 3] (metres)
    points: np.ndarray
    #: [P] bool: the points that carried a lidar term in the last round
    on_lidar: np.ndarray
    #: [M] reprojection error of every observation at the solution (px)
    reprojection_px: np.ndarray
    #: [M] bool: the observations kept in the last round
    inlier: np.ndarray
    #: each camera's standard deviations from the solution's covariance
    sigma: CameraSigma
    #: ``cost_per_round``, ``seconds``, ``lidar_points``, ``focals`` and ``principal_points`` (the
    #: number of distinct unknowns)
    stats: dict
    #: with lens corrections, [C, 2] (dk1, dk2: zero for the cameras without a lens); None without
    distortion: np.ndarray | None = None


def _skew(v: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(v[..., 0])
    return torch.stack([torch.stack([z, -v[..., 2], v[..., 1]], -1),
                        torch.stack([v[..., 2], z, -v[..., 0]], -1),
                        torch.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def _cauchy_weight(r2: torch.Tensor) -> torch.Tensor:
    return 1.0 / (1.0 + r2)


def _cauchy_cost(r2: torch.Tensor) -> torch.Tensor:
    return torch.log1p(r2).sum()


@dataclass(frozen=True)
class CameraParameters:
    """How the per-camera blocks of the normal equations map onto the unknowns: ``index`` [C * n]
    the unknown of each camera's rotation (3), centre (3), log focal (1), principal point (2) and,
    with ``distortion``, radial corrections (2), in camera-major order (``n`` = :attr:`per_camera`);
    ``count`` the number of unknowns; ``focal_of`` / ``principal_of`` / ``distortion_of`` [C] the
    index of each camera's focal / principal point / correction among those; ``*_weight`` [C] each
    camera's share of its (possibly shared) prior, 1 / the size of the group sharing it, so a shared
    parameter carries its prior once."""

    index: np.ndarray
    count: int
    focal_of: np.ndarray
    principal_of: np.ndarray
    distortion_of: np.ndarray
    focal_weight: np.ndarray
    principal_weight: np.ndarray
    distortion_weight: np.ndarray
    per_camera: int

    @property
    def shared(self) -> bool:
        return self.count < len(self.index)


def camera_parameters(lens_group: Sequence[str | None] | None, ncam: int, *, share_focal: bool = False,
                      share_principal: bool = False, distortion: bool = False,
                      share_distortion: bool = False) -> CameraParameters:
    """The unknowns of ``ncam`` cameras whose lens groups are ``lens_group`` (None, or None for a
    camera: its own): a pose per camera, a log focal per lens group (``share_focal``), a principal
    point per lens group (``share_principal``) and, with ``distortion``, radial corrections per lens
    group (``share_distortion``), otherwise per camera."""
    groups = list(lens_group) if lens_group is not None else [None] * ncam
    if len(groups) != ncam:
        raise ValueError(f"lens_group has {len(groups)} entries for {ncam} cameras")

    def classes(share: bool) -> np.ndarray:
        seen: dict = {}
        return np.array([seen.setdefault(("group", g) if share and g is not None else ("camera", i), len(seen))
                         for i, g in enumerate(groups)], np.int64).reshape(ncam)

    focal_of, principal_of, distortion_of = classes(share_focal), classes(share_principal), classes(share_distortion)
    nf, npp = int(focal_of.max(initial=-1)) + 1, int(principal_of.max(initial=-1)) + 1
    nd = int(distortion_of.max(initial=-1)) + 1 if distortion else 0
    n = NCAM + (NDIST if distortion else 0)
    index = np.zeros((ncam, n), np.int64)
    index[:, :6] = np.arange(6 * ncam).reshape(ncam, 6)
    index[:, 6] = 6 * ncam + focal_of
    index[:, 7] = 6 * ncam + nf + 2 * principal_of
    index[:, 8] = index[:, 7] + 1
    if distortion:
        index[:, 9] = 6 * ncam + nf + 2 * npp + 2 * distortion_of
        index[:, 10] = index[:, 9] + 1

    def share(of):
        return 1.0 / np.bincount(of, minlength=1)[of] if ncam else np.zeros(0)

    return CameraParameters(index=index.reshape(-1), count=6 * ncam + nf + 2 * npp + 2 * nd, focal_of=focal_of,
                            principal_of=principal_of, distortion_of=distortion_of, focal_weight=share(focal_of),
                            principal_weight=share(principal_of), distortion_weight=share(distortion_of),
                            per_camera=n)


def group_mean(values: torch.Tensor, of: np.ndarray) -> torch.Tensor:
    """Each camera's value [C, ...] replaced by the mean over the cameras sharing it (``of`` [C])."""
    idx = torch.as_tensor(of, dtype=torch.long, device=values.device)
    n = int(of.max(initial=-1)) + 1
    sums = torch.zeros((n,) + values.shape[1:], dtype=values.dtype, device=values.device).index_add_(0, idx, values)
    counts = torch.bincount(idx, minlength=n).to(values.dtype).reshape((n,) + (1,) * (values.dim() - 1))
    return (sums / counts)[idx]


def solve_shared(S: torch.Tensor, rhs: torch.Tensor, params: CameraParameters) -> torch.Tensor:
    """Solve the per-camera system ``S x = rhs`` ([Cn, Cn], [Cn]) with the parameters ``params``
    shares tied: with ``T`` the [Cn, N] 0/1 map from the unknowns to the per-camera parameters,
    ``(Tᵀ S T) y = Tᵀ rhs`` and ``x = T y``. Untied (every parameter its own) it is a plain solve."""
    if not params.shared:
        return torch.linalg.solve(S, rhs)
    idx = torch.as_tensor(params.index, dtype=torch.long, device=S.device)
    rr = torch.zeros(params.count, dtype=rhs.dtype, device=rhs.device).index_add_(0, idx, rhs)
    return torch.linalg.solve(_on_unknowns(S, params), rr)[idx]


def _on_unknowns(S: torch.Tensor, params: CameraParameters) -> torch.Tensor:
    """``Tᵀ S T`` [N, N]: the per-camera system ``S`` [Cn, Cn] summed onto the unknowns."""
    idx = torch.as_tensor(params.index, dtype=torch.long, device=S.device)
    n = params.count
    St = torch.zeros(n, len(idx), dtype=S.dtype, device=S.device).index_add_(0, idx, S)
    return torch.zeros(n, n, dtype=S.dtype, device=S.device).index_add_(1, idx, St)


class _State:
    def __init__(self, R, C, logf, pp, X, dk=None):
        self.R, self.C, self.logf, self.pp, self.X, self.dk = R, C, logf, pp, X, dk

    def updated(self, dc: torch.Tensor, dp: torch.Tensor) -> "_State":
        dR = axis_angle_to_rotation_matrix(dc[:, :3])
        dk = None if self.dk is None else self.dk + dc[:, 9:11]
        return _State(dR @ self.R, self.C + dc[:, 3:6], self.logf + dc[:, 6], self.pp + dc[:, 7:9], self.X + dp, dk)


@dataclass
class _Problem:
    """What stays fixed through the adjustment: priors, options, the unknowns' map, the lenses."""

    pp0: torch.Tensor
    logf0: torch.Tensor
    C0: torch.Tensor
    options: BundleOptions
    fix_focal: bool
    params: CameraParameters
    wf: torch.Tensor
    wpp: torch.Tensor
    wd: torch.Tensor
    #: [C, 5] (f, cx, cy, k1, k2) of each camera's rectification and [C] bool which have one (None:
    #: no lens corrections)
    lens: torch.Tensor | None = None
    has_lens: torch.Tensor | None = None
    #: [C] each camera's principal-point prior sigma (px), when principal points are refined
    pps: torch.Tensor | None = None
    #: [C] each camera's focal prior sigma (relative, of the log focal), when focals are refined
    fs: torch.Tensor | None = None


def bundle_adjust(world_to_camera: np.ndarray, focal: np.ndarray, principal: np.ndarray,
                  points: np.ndarray, obs_camera: np.ndarray, obs_point: np.ndarray, obs_xy: np.ndarray,
                  *, scan: LidarScan | None = None, focal_prior: np.ndarray | None = None,
                  centre_prior: np.ndarray | None = None, lens_group: Sequence[str | None] | None = None,
                  lens: Sequence[Sequence[float] | None] | None = None,
                  principal_sigma: Sequence[float] | None = None, focal_sigma: Sequence[float] | None = None,
                  options: BundleOptions = BundleOptions()) -> BundleResult:
    """Refine static cameras and points.

    Shapes: ``world_to_camera`` [C, 4, 4] (OpenCV), ``focal`` [C] px (fx = fy), ``principal``
    [C, 2] OpenCV px (held fixed unless ``options.principal_sigma_px``), ``points`` [P, 3] metres,
    observations ``obs_camera`` [M], ``obs_point`` [M], ``obs_xy`` [M, 2] OpenCV px. ``focal_prior`` [C] px (default: ``focal``),
    ``centre_prior`` [C, 3] (default: the initial centres). ``lens_group`` [C]: each camera's lens
    group (the rig's ``lens_group``; None: its own); the cameras of a group share one focal
    (``options.share_group_focal``), started at and held around the mean of their focals and priors
    (one prior for the group), and with ``options.share_group_principal`` one principal point.
    ``lens`` [C]: per camera whose observations were rectified through a lens calibration, that
    rectification's ``(f, cx, cy, k1, k2)`` or ``(f, cx, cy, k1, k2, k3)`` (the pinhole it resampled
    into and its radial terms),
    None for the others; with ``options.distortion_sigma`` those cameras get radial corrections
    (module docstring), the others none. ``principal_sigma`` [C]: each camera's principal-point prior
    sigma (px) when ``options.principal_sigma_px`` refines them (default: that value for every camera;
    e.g. tighter for cameras whose principal point a lens calibration measured). ``focal_sigma`` [C]:
    each camera's focal prior sigma (relative) when ``options.focal_sigma_rel`` refines the focals
    (default: that value for every camera; e.g. tighter for cameras whose focal a lens calibration
    measured). Cameras sharing a focal (``share_group_focal``) should share its sigma.

    Returns the refined cameras and points, each observation's reprojection error and inlier flag,
    and each camera's standard deviations (:class:`BundleResult`).
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
    refine_lens = options.distortion_sigma is not None and lens is not None and any(v is not None for v in lens)
    params = camera_parameters(lens_group, ncam, share_focal=options.share_group_focal,
                               share_principal=options.share_group_principal, distortion=refine_lens,
                               share_distortion=options.share_group_distortion)
    # a shared focal / principal point that is refined starts at (and is held around) the mean of
    # its cameras' (held ones stay as given)
    if not fix_focal:
        logf, logf0 = group_mean(logf, params.focal_of), group_mean(logf0, params.focal_of)
    if options.principal_sigma_px is not None:
        pp0 = group_mean(pp0, params.principal_of)
    lens_t = has_lens = dk = None
    if refine_lens:
        if len(lens) != ncam:
            raise ValueError(f"lens has {len(lens)} entries for {ncam} cameras")
        has_lens = torch.as_tensor([v is not None for v in lens], device=dev)
        lens_t = torch.as_tensor(np.array([(tuple(v) + (0.0,) * (6 - len(v))) if v is not None
                                           else (1.0, 0.0, 0.0, 0.0, 0.0, 0.0) for v in lens],
                                          np.float64).reshape(ncam, 6), **f64)
        dk = torch.zeros(ncam, NDIST, **f64)
    pps = None
    if options.principal_sigma_px is not None:
        pps = torch.as_tensor(np.full(ncam, options.principal_sigma_px, np.float64) if principal_sigma is None
                              else np.asarray(principal_sigma, np.float64).reshape(ncam), **f64)
    fs = None
    if not fix_focal:
        fs = torch.as_tensor(np.full(ncam, options.focal_sigma_rel, np.float64) if focal_sigma is None
                             else np.asarray(focal_sigma, np.float64).reshape(ncam), **f64)
    prob = _Problem(pp0, logf0, C0, options, fix_focal, params, torch.as_tensor(params.focal_weight, **f64),
                    torch.as_tensor(params.principal_weight, **f64), torch.as_tensor(params.distortion_weight, **f64),
                    lens_t, has_lens, pps, fs)

    state = _State(R, C, logf, pp0.clone(), X, dk)
    on_lidar = torch.zeros(npt, dtype=torch.bool, device=dev)
    plane_n = plane_d = None
    history = []
    gates = options.lidar_gates_m if scan is not None else (None,) * len(options.outlier_px)
    keep = torch.ones(len(oc), dtype=torch.bool, device=dev)
    oc_all, op_all, uv_all = oc, op, uv
    for rnd, gate in enumerate(gates):
        if rnd > 0 and options.outlier_px:
            thr = options.outlier_px[min(rnd - 1, len(options.outlier_px) - 1)]
            keep = _residual_px(state, prob, oc_all, op_all, uv_all).norm(dim=1) < thr
            cnt = torch.bincount(op_all[keep], minlength=npt)
            keep &= cnt[op_all] >= 2
            oc, op, uv = oc_all[keep], op_all[keep], uv_all[keep]
            pairs = _observation_pairs(op, npt)
        if scan is not None:
            plane_n, plane_d, on_lidar = _associate(scan, state.X, gate, dev)
        else:
            plane_n = plane_d = None
        lam = 1e-3
        cost = _cost(state, prob, oc, op, uv, plane_n, plane_d, on_lidar)
        for _ in range(options.iterations):
            dc, dp = _lm_step(state, prob, oc, op, uv, plane_n, plane_d, on_lidar, pairs, lam, ncam, npt)
            new = state.updated(dc, dp)
            new_cost = _cost(new, prob, oc, op, uv, plane_n, plane_d, on_lidar)
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
    sigma_prob = prob
    if prob.options.sigma_from_residuals:
        r = _residual_px(state, prob, oc, op, uv).reshape(-1)
        spread = max(1.4826 * float((r - r.median()).abs().median()), 0.05) if len(r) else prob.options.pixel_sigma
        sigma_prob = replace(prob, options=replace(prob.options, pixel_sigma=spread))
    sigma = _camera_sigma(state, sigma_prob, oc, op, uv, plane_n, plane_d, on_lidar, pairs, ncam, npt)
    Rn, Cn = state.R, state.C
    out_w2c = torch.eye(4, **f64).repeat(ncam, 1, 1)
    out_w2c[:, :3, :3] = Rn
    out_w2c[:, :3, 3] = -(Rn @ Cn[..., None])[..., 0]
    res = _residual_px(state, prob, oc_all, op_all, uv_all)
    return BundleResult(world_to_camera=out_w2c.cpu().numpy(), focal=torch.exp(state.logf).cpu().numpy(),
                        principal=state.pp.cpu().numpy(), points=state.X.cpu().numpy(),
                        on_lidar=on_lidar.cpu().numpy(), reprojection_px=res.norm(dim=1).cpu().numpy(),
                        inlier=keep.cpu().numpy(), sigma=sigma,
                        stats={"cost_per_round": history, "seconds": time.perf_counter() - t0,
                               "lidar_points": int(on_lidar.sum()),
                               "focals": int(params.focal_of.max(initial=-1)) + 1,
                               "principal_points": int(params.principal_of.max(initial=-1)) + 1},
                        distortion=None if state.dk is None else state.dk.cpu().numpy())


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


def _lens_terms(state: _State, prob: _Problem, oc, u: torch.Tensor):
    """The lens correction of pinhole pixels ``u`` [M, 2] of cameras ``oc``: (offset [M, 2] to add,
    d offset / d (dk1, dk2) [M, 2, 2]), or None without lens corrections."""
    if prob.lens is None:
        return None
    L = prob.lens[oc]
    d = u - L[:, 1:3]
    rho2 = (d ** 2).sum(1) / L[:, 0] ** 2
    slope = 1.0 + 3.0 * L[:, 3] * rho2 + 5.0 * L[:, 4] * rho2 ** 2 + 7.0 * L[:, 5] * rho2 ** 3
    on = prob.has_lens[oc].to(u.dtype)
    basis = torch.stack([rho2, rho2 ** 2], 1) * (on / slope)[:, None]                  # [M, 2]
    g = (basis * state.dk[oc]).sum(1)
    return d * g[:, None], d[:, :, None] * basis[:, None, :]


def _residual_px(state, prob: _Problem, oc, op, uv):
    _, _, xn, f, _ = _project(state, oc, op)
    u = f[:, None] * xn + state.pp[oc]
    lt = _lens_terms(state, prob, oc, u)
    if lt is not None:
        u = u + lt[0]
    return u - uv


def _cost(state, prob: _Problem, oc, op, uv, plane_n, plane_d, on_lidar):
    o = prob.options
    r = _residual_px(state, prob, oc, op, uv) / o.pixel_sigma
    c = _cauchy_cost((r ** 2).sum(1))
    if plane_n is not None and on_lidar.any():
        rl = ((plane_n * state.X).sum(1) - plane_d)[on_lidar] / o.lidar_sigma_m
        c = c + _cauchy_cost(rl ** 2)
    if not prob.fix_focal:
        c = c + (prob.wf * ((state.logf - prob.logf0) / prob.fs) ** 2).sum()
    c = c + (((state.C - prob.C0) / o.centre_sigma_m) ** 2).sum()
    if o.principal_sigma_px is not None:
        c = c + (prob.wpp[:, None] * ((state.pp - prob.pp0) / prob.pps[:, None]) ** 2).sum()
    if state.dk is not None:
        c = c + (prob.wd[:, None] * (state.dk / o.distortion_sigma) ** 2).sum()
    return float(c)


def _lm_step(state, prob: _Problem, oc, op, uv, plane_n, plane_d, on_lidar, pairs, lam, ncam, npt):
    """One Levenberg-Marquardt step (damping ``lam``): the cameras' update [C, n] and the points' [P, 3]."""
    S, rhs, Hpp_inv, Hcp, gp = _reduced_system(state, prob, oc, op, uv, plane_n, plane_d, on_lidar, pairs, lam,
                                               ncam, npt)
    n = prob.params.per_camera
    # a lens group's shared focal (principal point): its cameras' rows and columns summed onto one
    # unknown; the damping is then the summed diagonal, as for any other parameter
    dc = solve_shared(S, rhs, prob.params).view(ncam, n)
    # back-substitute the points
    t = gp.clone()
    t.index_add_(0, op, (Hcp.transpose(1, 2) @ dc[oc][..., None])[..., 0])
    dp = -(Hpp_inv @ t[..., None])[..., 0]
    return dc, dp


def _camera_sigma(state, prob: _Problem, oc, op, uv, plane_n, plane_d, on_lidar, pairs, ncam, npt) -> CameraSigma:
    """How well the adjustment determines each camera at ``state``: the Gauss-Newton covariance of
    the camera parameters with the points eliminated (the inverse of the undamped reduced camera
    system, priors and lidar terms included; residuals in units of ``pixel_sigma``, the last
    Cauchy weights counting the outliers out), per camera [C]: ``rotation_deg`` and ``centre_m``
    (the largest standard deviation over the axes), ``focal_rel`` (of the log focal) and
    ``principal_px`` (largest over x, y); NaN for an intrinsic the adjustment holds. A principal
    point and a rotation trade along a direction only the second order of the projection tells
    apart, so a refined principal point widens its camera's rotation here. The observations count
    at ``pixel_sigma``, not at their residual's spread (step 5's 0.1 px is about twice it): what the
    observations pin down is stated with that allowance for their systematic errors."""
    # a point seen once and held by no lidar term is undetermined along its ray (its block is
    # singular at lam = 0, and eliminating it would only spread rounding): it says nothing of the
    # cameras, so it is left out
    seen = torch.bincount(op, minlength=npt)
    told = (seen[op] >= 2) | on_lidar[op]
    if not bool(told.all()):
        oc, op, uv = oc[told], op[told], uv[told]
        pairs = _observation_pairs(op, npt)
    S, *_ = _reduced_system(state, prob, oc, op, uv, plane_n, plane_d, on_lidar, pairs, 0.0, ncam, npt)
    n = prob.params.per_camera
    free, alone = 0, np.zeros(ncam, bool)
    if prob.params.shared:   # on the shared unknowns, mapped back to each camera's parameters
        idx = torch.as_tensor(prob.params.index, dtype=torch.long, device=S.device)
        cov = torch.linalg.inv(_on_unknowns(S, prob.params))[idx][:, idx]
    else:
        cov, free, alone = _covariance(S, ncam)
    ar = torch.arange(ncam, device=S.device)
    blocks = cov.view(ncam, n, ncam, n)[ar, :, ar, :]                               # [C, n, n]

    def largest(b):     # a block that is not positive (rounding of an undetermined camera): inf
        top = torch.linalg.eigvalsh(b).amax(-1)
        return torch.where(top >= 0, top.clamp(min=0).sqrt(), torch.full_like(top, float("inf"))).cpu().numpy()

    nan = np.full(ncam, np.nan)
    inf = np.where(alone, np.inf, 1.0)     # a camera with a direction of its own undetermined
    return CameraSigma(undetermined=free,
                       rotation_deg=inf * np.degrees(largest(blocks[:, :3, :3])), centre_m=inf * largest(blocks[:, 3:6, 3:6]),
                       focal_rel=nan if prob.fix_focal else largest(blocks[:, 6:7, 6:7]),
                       principal_px=nan if prob.options.principal_sigma_px is None else largest(blocks[:, 7:9, 7:9]))


#: a direction of the reduced camera system whose information is below this fraction of the
#: largest is undetermined (:func:`_covariance`): two cameras without a scan turning together about
#: their baseline gave 6e-16 (Pose2Sim cam01-cam02: only the 1e-12 damping held it), every
#: determined direction measured so far 1e-7 or more (the centre priors')
UNDETERMINED_RCOND = 1e-12


def _covariance(S: torch.Tensor, ncam: int) -> tuple[torch.Tensor, int, np.ndarray]:
    """The inverse of the reduced camera system ``S`` [C n, C n] on the directions the observations
    and priors determine (information above :data:`UNDETERMINED_RCOND` of the largest). An
    undetermined direction that moves several cameras together (two cameras without a scan turning
    about their baseline) is left out of the covariance and counted (the second value): stating it
    as a sigma of thousands of degrees would hide what the data do hold. One that moves a single
    camera (a camera nothing observes) marks that camera (the third value, [C] bool): its sigma is
    inf. Full rank: ``inv(S)``, 0, none marked."""
    ev, V = torch.linalg.eigh(S)
    keep = ev > UNDETERMINED_RCOND * ev[-1]
    alone = np.zeros(ncam, bool)
    if bool(keep.all()):
        return torch.linalg.inv(S), 0, alone
    share = (V[:, ~keep] ** 2).reshape(ncam, -1, int((~keep).sum())).sum(1).cpu().numpy()     # [C, k]
    together = (share > 0.05).sum(0) >= 2
    alone[np.unique(share[:, ~together].argmax(0))] = True
    return (V[:, keep] / ev[keep]) @ V[:, keep].T, int(together.sum()), alone


def _compiled_normal_equations():
    """:mod:`~volcap_core.calibration.bundle_numba` (the normal equations' blocks, the torch code's
    bits), imported on first use, or None where numba does not import: then the torch code forms them."""
    try:
        from volcap_core.calibration import bundle_numba
    except ImportError:
        return None
    return bundle_numba


def _reduced_system(state, prob: _Problem, oc, op, uv, plane_n, plane_d, on_lidar, pairs, lam, ncam, npt):
    """The normal equations with the points eliminated (Schur complement), damped by ``lam``:
    the reduced camera system ``S`` [Cn, Cn] and its right-hand side [Cn], and what the points'
    back-substitution needs (``Hpp_inv`` [P, 3, 3], ``Hcp`` [M, n, 3], ``gp`` [P, 3])."""
    o, fix_focal = prob.options, prob.fix_focal
    wf, wpp = prob.wf, prob.wpp
    n = prob.params.per_camera
    Xc, z, xn, f, R = _project(state, oc, op)
    u = f[:, None] * xn + state.pp[oc]
    lt = _lens_terms(state, prob, oc, u)
    if lt is not None:
        u = u + lt[0]
    # d pi / d Xc  [M, 2, 3] (of the pinhole: the lens correction's own dependence on the pose is
    # second order, ~1e-3 of it)
    dpi = torch.zeros(len(z), 2, 3, dtype=z.dtype, device=z.device)
    dpi[:, 0, 0] = f / z
    dpi[:, 1, 1] = f / z
    dpi[:, 0, 2] = -f * xn[:, 0] / z
    dpi[:, 1, 2] = -f * xn[:, 1] / z
    Jf = (f[:, None] * xn)[..., None]
    Jd = lt[1] if lt is not None else None
    r = (u - uv) / o.pixel_sigma                                            # [M, 2]
    w = _cauchy_weight((r ** 2).sum(1)).sqrt()                              # [M]
    Jw = dpi @ (-_skew(Xc))
    JC = dpi @ (-R)
    Jpp = torch.eye(2, dtype=z.dtype, device=z.device).expand(len(z), 2, 2)
    Jc = torch.cat([Jw, JC, Jf, Jpp] + ([Jd] if Jd is not None else []), 2)     # [M, 2, n]
    if fix_focal:
        Jc[..., 6] = 0.0
    if o.principal_sigma_px is None:
        Jc[..., 7:9] = 0.0
    Jp = dpi @ R                                                            # [M, 2, 3]
    s = (w / o.pixel_sigma)[:, None, None]
    Jc, Jp = Jc * s, Jp * s
    rw = r * w[:, None]
    Hcc = torch.zeros(ncam, n, n, dtype=z.dtype, device=z.device)
    gc = torch.zeros(ncam, n, dtype=z.dtype, device=z.device)
    Hpp = torch.zeros(npt, 3, 3, dtype=z.dtype, device=z.device)
    gp = torch.zeros(npt, 3, dtype=z.dtype, device=z.device)
    compiled = _compiled_normal_equations() if z.device.type == "cpu" else None
    if compiled is not None:
        Hcp = torch.from_numpy(compiled.add_observation_blocks(Jc.numpy(), Jp.numpy(), rw.numpy(), oc.numpy(),
                                                               op.numpy(), Hcc.numpy(), gc.numpy(), Hpp.numpy(),
                                                               gp.numpy()))
    else:
        Hcc.index_add_(0, oc, Jc.transpose(1, 2) @ Jc)
        gc.index_add_(0, oc, (Jc.transpose(1, 2) @ rw[..., None])[..., 0])
        Hpp.index_add_(0, op, Jp.transpose(1, 2) @ Jp)
        gp.index_add_(0, op, (Jp.transpose(1, 2) @ rw[..., None])[..., 0])
        Hcp = Jc.transpose(1, 2) @ Jp                                       # [M, n, 3]
    if plane_n is not None and on_lidar.any():
        rl = ((plane_n * state.X).sum(1) - plane_d) / o.lidar_sigma_m
        wl = _cauchy_weight(rl ** 2) * on_lidar.to(rl.dtype)
        nn = plane_n[:, :, None] * plane_n[:, None, :] / o.lidar_sigma_m ** 2
        Hpp = Hpp + wl[:, None, None] * nn
        gp = gp + (wl * rl / o.lidar_sigma_m)[:, None] * plane_n
    # priors (a shared focal's or principal point's prior split between its cameras, so that it
    # counts once when their blocks are summed onto the shared unknown)
    idx = torch.arange(3, 6, device=z.device)
    Hcc[:, idx, idx] += 1.0 / o.centre_sigma_m ** 2
    gc[:, 3:6] += (state.C - prob.C0) / o.centre_sigma_m ** 2
    if fix_focal:
        Hcc[:, 6, 6] += 1.0
    else:
        Hcc[:, 6, 6] += wf / prob.fs ** 2
        gc[:, 6] += wf * (state.logf - prob.logf0) / prob.fs ** 2
    idx = torch.arange(7, 9, device=z.device)
    if o.principal_sigma_px is None:
        Hcc[:, idx, idx] += 1.0
    else:
        Hcc[:, idx, idx] += (wpp / prob.pps ** 2)[:, None]
        gc[:, 7:9] += (wpp / prob.pps ** 2)[:, None] * (state.pp - prob.pp0)
    if state.dk is not None:
        idx = torch.arange(9, 11, device=z.device)
        Hcc[:, idx, idx] += prob.wd[:, None] / o.distortion_sigma ** 2
        gc[:, 9:11] += prob.wd[:, None] * state.dk / o.distortion_sigma ** 2
    # Levenberg-Marquardt damping
    eyec = torch.eye(n, dtype=z.dtype, device=z.device)
    eye3 = torch.eye(3, dtype=z.dtype, device=z.device)
    Hcc_d = Hcc + lam * (Hcc.diagonal(dim1=1, dim2=2)[..., None] * eyec) + 1e-12 * eyec
    Hpp_d = Hpp + lam * (Hpp.diagonal(dim1=1, dim2=2)[..., None] * eye3) + 1e-9 * eye3
    Hpp_inv = torch.linalg.inv(Hpp_d)
    # Schur complement on the points
    a, b = pairs
    S = torch.zeros(ncam * ncam, n, n, dtype=z.dtype, device=z.device)
    if compiled is not None:
        compiled.subtract_point_blocks(S.numpy(), Hcp.numpy(), Hpp_inv.numpy(), oc.numpy(), op.numpy(), a.numpy(),
                                       b.numpy(), ncam)
    else:
        blocks = Hcp[a] @ Hpp_inv[op[a]] @ Hcp[b].transpose(1, 2)          # [Q, n, n]
        S.index_add_(0, oc[a] * ncam + oc[b], -blocks)
    S = S.view(ncam, ncam, n, n)
    S[torch.arange(ncam), torch.arange(ncam)] += Hcc_d
    S = S.permute(0, 2, 1, 3).reshape(ncam * n, ncam * n)
    v = Hpp_inv @ gp[..., None]                                             # [P, 3, 1]
    rhs = -gc
    rhs = rhs.index_add(0, oc, (Hcp @ v[op])[..., 0])
    return S, rhs.reshape(-1), Hpp_inv, Hcp, gp
