"""The tracking cameras' solve: initial values, then a joint refinement of every camera's sequence.

Initialisation (:func:`initialise_tracking`): focal from the smoothed lens encoder, centre at the
rig's mount, relative rotations from the frame-to-frame homographies, absolute orientation by a
two-point RANSAC over the 2D-3D matches of all frames pooled (few per frame at high zoom, hundreds
together).

Refinement (:func:`refine_tracking`, torch, batched over cameras): Levenberg-Marquardt over, per frame,
rotation (3), centre (3) and log focal (1), and per camera a mean centre (3), a focal gain (log) and
an offset, minimising (Cauchy-robust) 2D-3D and 2D-2D reprojection errors plus

- a focal prior: ``log f_t = log(exp(a) * s(t) + b) ± focal_sigma_rel``, ``s`` the encoder focal
  (px) smoothed robustly over time (:func:`~volcap_core.calibration.tracking.lens.smooth_encoder_focal`),
  ``a, b`` the per-camera gain and offset (the encoder's calibration error);
- a centre prior: ``C_t = C_mean ± centre_sigma_m`` (the head barely translates).

The solution's stats carry its covariance's spread (``focal_sigma_pct``, ``rotation_sigma_deg``,
``centre_sigma_m``) and :func:`tracking_support` says whether it can be returned as calibrated.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from volcap_core.calibration.tracking.observe import TrackingObservations
from volcap_core.calibration.tracking.options import TrackingOptions

NF = 7   # per-frame parameters: rotation (3), centre (3), log focal (1)
NG = 5   # per-camera parameters: mean centre (3), focal gain (log), focal offset (px)


# --------------------------------------------------------------------------- initialisation

def _principal_per_frame(principal, T: int) -> np.ndarray:
    """(cx, cy) or [T', 2] -> [T, 2] float64 (one principal point per frame; rows past T' repeat
    the last)."""
    pp = np.asarray(principal, np.float64)
    if pp.ndim == 1:
        return np.broadcast_to(pp.reshape(1, 2), (T, 2)).copy()
    if len(pp) < T:
        pp = np.concatenate([pp, np.repeat(pp[-1:], T - len(pp), 0)])
    return pp[:T].reshape(T, 2).copy()


def _bearings(uv: np.ndarray, f: float, cx: float, cy: float) -> np.ndarray:
    b = np.stack([(uv[:, 0] - cx) / f, (uv[:, 1] - cy) / f, np.ones(len(uv))], 1)
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def _ransac_rotation(a: np.ndarray, b: np.ndarray, thr: float, rng: np.random.Generator,
                     iterations: int) -> np.ndarray:
    """Rotation R with R a_i ≈ b_i (unit vectors [N, 3]) from 2-point samples; refit on the inliers
    (|R a - b| < thr) a few times."""
    n = len(a)
    if n < 2:
        return np.eye(3)
    best, best_n = np.ones(n, bool), -1
    for _ in range(iterations):
        i, j = rng.choice(n, 2, replace=False)
        if abs(a[i] @ a[j]) > 0.9999995:
            continue
        R = _kabsch(a[[i, j]], b[[i, j]])
        inl = np.linalg.norm(a @ R.T - b, axis=1) < thr
        cnt = int(inl.sum())
        if cnt > best_n:
            best, best_n = inl, cnt
    R = _kabsch(a[best], b[best]) if best.sum() >= 2 else np.eye(3)
    for _ in range(3):
        inl = np.linalg.norm(a @ R.T - b, axis=1) < thr
        if inl.sum() >= 3:
            R = _kabsch(a[inl], b[inl])
    return R


def _kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation R minimising sum |R a_i - b_i|^2 (unit vectors [N, 3])."""
    U, _, Vt = np.linalg.svd(b.T @ a)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def initialise_tracking(obs: TrackingObservations, focal_px: np.ndarray, centre: np.ndarray,
                        principal, options: TrackingOptions = TrackingOptions()
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Initial rotations [T, 3, 3], centres [T, 3] and focal lengths [T] of one tracking camera.

    ``focal_px`` [T]: the smoothed encoder focal; ``centre`` [3]: the mount position (metres);
    ``principal``: (cx, cy), or [T, 2] one per frame (a zoom lens whose axis moves with the zoom).
    """
    T = obs.frame_count
    pp = _principal_per_frame(principal, T)
    # relative rotations R_t R_{t-1}^T: robust Kabsch on the bearings of the matches of (t-1, t)
    rng = np.random.default_rng(options.seed)
    rel = [np.eye(3)]
    cons = (obs.m2_j - obs.m2_i) == 1
    for t in range(1, T):
        sel = cons & (obs.m2_i == t - 1)
        if sel.sum() < 3:
            rel.append(rel[-1])
            continue
        bi = _bearings(obs.m2_ui[sel], focal_px[t - 1], *pp[t - 1])
        bj = _bearings(obs.m2_uj[sel], focal_px[t], *pp[t])
        rel.append(_ransac_rotation(bi, bj, 2.0 / focal_px[t], rng, 200) @ rel[-1])
    rel = np.asarray(rel)
    # pooled bearings in the frame-0 orientation
    t3 = obs.m3_frame
    uv = obs.m3_uv
    if len(t3) < 3:
        raise RuntimeError("tracking camera: fewer than 3 2D-3D matches over the whole take")
    rays = np.stack([(uv[:, 0] - pp[t3, 0]) / focal_px[t3], (uv[:, 1] - pp[t3, 1]) / focal_px[t3],
                     np.ones(len(t3))], 1)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    b = np.einsum("nji,nj->ni", rel[t3], rays)                    # R_rel^T ray
    d = obs.m3_X - centre
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    thr = options.ransac_px / np.median(focal_px)
    n = len(b)
    R0 = _ransac_rotation(d, b, thr, rng, options.ransac_iterations)
    inl = np.linalg.norm(d @ R0.T - b, axis=1) < thr
    R = rel @ R0
    C = np.repeat(np.asarray(centre, np.float64)[None], T, 0)
    return R, C, np.asarray(focal_px, np.float64).copy(), {"ransac_inliers": int(inl.sum()), "matches_3d": n,
                                                           "homographies": len(obs.H)}


# --------------------------------------------------------------------------- refinement

@dataclass
class TrackingSolution:
    """Per frame: ``K`` [T, 3, 3], ``world_to_camera`` [T, 4, 4]; per camera: focal ``gain``
    (multiplier on the smoothed encoder focal) and ``offset`` (px), mean ``centre`` [3].
    ``distortion`` [T, 5 or 8]: OpenCV's distCoeffs of each frame's lens (a zoom lens: the lens at
    that frame's focal) that the frame's observations were undistorted with, so ``K[t]`` is the
    pinhole of frame t rectified with it; None: the raw frames are pinholes."""

    K: np.ndarray
    world_to_camera: np.ndarray
    gain: float
    offset: float
    centre: np.ndarray
    stats: dict
    distortion: np.ndarray | None = None
    #: why the camera is left out of the calibration (:func:`tracking_support`), None when supported
    unsupported: str | None = None


def _skew(v: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(v[..., 0])
    return torch.stack([torch.stack([z, -v[..., 2], v[..., 1]], -1),
                        torch.stack([v[..., 2], z, -v[..., 0]], -1),
                        torch.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def _dpi(w: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """d pi / d w [Q, 2, 3] for pi = f * w_xy / w_z."""
    z = w[:, 2]
    d = torch.zeros(len(w), 2, 3, dtype=w.dtype, device=w.device)
    d[:, 0, 0] = f / z
    d[:, 1, 1] = f / z
    d[:, 0, 2] = -f * w[:, 0] / z ** 2
    d[:, 1, 2] = -f * w[:, 1] / z ** 2
    return d


class _Batch:
    """All cameras' observations concatenated, with the camera index of each."""

    def __init__(self, obs: list[TrackingObservations], principal: np.ndarray, prior_px: list[np.ndarray],
                 mounts: list[np.ndarray], o: TrackingOptions, dev):
        f64 = dict(dtype=torch.float64, device=dev)
        self.B = len(obs)
        self.T = max(ob.frame_count for ob in obs)
        self.n = NF * self.T + NG
        c3, t3, uv3, X3 = [], [], [], []
        c2, i2, j2, ui2, uj2 = [], [], [], [], []
        for b, ob in enumerate(obs):
            c3.append(np.full(len(ob.m3_frame), b))
            t3.append(ob.m3_frame)
            uv3.append(ob.m3_uv)
            X3.append(ob.m3_X)
            if o.mode != "independent":
                c2.append(np.full(len(ob.m2_i), b))
                i2.append(ob.m2_i)
                j2.append(ob.m2_j)
                ui2.append(ob.m2_ui)
                uj2.append(ob.m2_uj)
        L = lambda xs, s: torch.as_tensor(np.concatenate(xs) if xs else np.zeros(s), device=dev)  # noqa: E731
        self.c3 = L(c3, (0,)).long()
        self.t3 = L(t3, (0,)).long()
        self.uv3 = L(uv3, (0, 2)).to(torch.float64)
        self.X3 = L(X3, (0, 3)).to(torch.float64)
        self.c2 = L(c2, (0,)).long()
        self.i2 = L(i2, (0,)).long()
        self.j2 = L(j2, (0,)).long()
        self.ui2 = L(ui2, (0, 2)).to(torch.float64)
        self.uj2 = L(uj2, (0, 2)).to(torch.float64)
        self.pp = torch.as_tensor(principal, **f64)                                   # [B, T, 2]
        self.s = torch.stack([torch.as_tensor(p, **f64) for p in prior_px])            # [B, T]
        self.mount = torch.as_tensor(np.stack([ob_mount for ob_mount in mounts]), **f64)  # [B, 3]
        self.valid_frame = torch.zeros(self.B, self.T, dtype=torch.bool, device=dev)
        for b, ob in enumerate(obs):
            self.valid_frame[b, :ob.frame_count] = True


class _State:
    def __init__(self, R, C, logf, Cm, a, off):
        self.R, self.C, self.logf, self.Cm, self.a, self.off = R, C, logf, Cm, a, off

    def step(self, d: torch.Tensor, T: int) -> "_State":
        B = d.shape[0]
        fr = d[:, :NF * T].view(B, T, NF)
        g = d[:, NF * T:]
        dR = axis_angle_to_rotation_matrix(fr[..., :3].reshape(-1, 3)).view(B, T, 3, 3)
        return _State(dR @ self.R, self.C + fr[..., 3:6], self.logf + fr[..., 6], self.Cm + g[:, :3],
                      self.a + g[:, 3], self.off + g[:, 4])


def _terms(st: _State, bt: _Batch, o: TrackingOptions, jac: bool):
    """Residual blocks: list of (camera [Q], residual [Q, k], J [Q, k, m], index [Q, m], weight sigma)."""
    out = []
    f = torch.exp(st.logf)
    # 2D-3D
    if len(bt.c3):
        b, t = bt.c3, bt.t3
        R = st.R[b, t]
        w = (R @ (bt.X3 - st.C[b, t])[..., None])[..., 0]
        ft = f[b, t]
        z = w[:, 2].clamp(min=1e-6)
        pred = ft[:, None] * w[:, :2] / z[:, None] + bt.pp[b, t]
        r = (pred - bt.uv3) / o.pixel_sigma_3d
        behind = w[:, 2] <= 1e-6
        r = torch.where(behind[:, None], torch.full_like(r, 1e3), r)
        J = idx = None
        if jac:
            d = _dpi(w, ft)
            Jw = d @ (-_skew(w))
            JC = d @ (-R)
            Jf = (ft[:, None] * w[:, :2] / z[:, None])[..., None]
            # a point behind the camera has the constant residual above: no slope (its 1/z Jacobian
            # at the clamped depth would be ~1e6 x f, freezing its frame and the focal of the take)
            J = torch.cat([Jw, JC, Jf], 2) / o.pixel_sigma_3d * (~behind).to(w.dtype)[:, None, None]
            idx = (NF * t)[:, None] + torch.arange(NF, device=t.device)[None]
        out.append((b, r, J, idx))
    # 2D-2D (frame i -> frame j, same camera)
    if len(bt.c2):
        b, i, j = bt.c2, bt.i2, bt.j2
        fi, fj = f[b, i], f[b, j]
        ppi, pp = bt.pp[b, i], bt.pp[b, j]
        ray = torch.cat([(bt.ui2 - ppi) / fi[:, None], torch.ones_like(fi)[:, None]], 1)
        Ri, Rj = st.R[b, i], st.R[b, j]
        v = (Ri.transpose(1, 2) @ ray[..., None])[..., 0]
        w = (Rj @ v[..., None])[..., 0]
        z = w[:, 2].clamp(min=1e-6)
        pred = fj[:, None] * w[:, :2] / z[:, None] + pp
        r = (pred - bt.uj2) / o.pixel_sigma_2d
        J = idx = None
        if jac:
            d = _dpi(w, fj)
            Jwj = d @ (-_skew(w))
            RjRiT = Rj @ Ri.transpose(1, 2)
            Jwi = d @ RjRiT @ _skew(ray)
            dray = torch.zeros_like(ray)
            dray[:, :2] = -(bt.ui2 - ppi) / fi[:, None]
            Jfi = d @ (RjRiT @ dray[..., None])
            Jfj = (fj[:, None] * w[:, :2] / z[:, None])[..., None]
            zero3 = torch.zeros(len(b), 2, 3, dtype=w.dtype, device=w.device)
            J = torch.cat([Jwi, zero3, Jfi, Jwj, zero3, Jfj], 2) / o.pixel_sigma_2d
            ar = torch.arange(NF, device=b.device)[None]
            idx = torch.cat([(NF * i)[:, None] + ar, (NF * j)[:, None] + ar], 1)
        out.append((b, r, J, idx))
    return out


def _prior_terms(st: _State, bt: _Batch, o: TrackingOptions, jac: bool):
    """Quadratic priors: focal curve, centre, weak gauge terms. Same format as _terms."""
    out = []
    B, T = bt.B, bt.T
    dev = st.C.device
    bb, tt = torch.meshgrid(torch.arange(B, device=dev), torch.arange(T, device=dev), indexing="ij")
    vf = bt.valid_frame
    bb, tt = bb[vf], tt[vf]
    ar3 = torch.arange(3, device=dev)
    if o.mode == "priors":
        g = torch.exp(st.a)[bb] * bt.s[bb, tt]
        model = g + st.off[bb]
        r = ((st.logf[bb, tt] - torch.log(model)) / o.focal_sigma_rel)[:, None]
        J = idx = None
        if jac:
            J = torch.stack([torch.ones_like(g), -g / model, -1.0 / model], 1)[:, None, :] / o.focal_sigma_rel
            idx = torch.stack([NF * tt + 6, torch.full_like(tt, NF * T + 3), torch.full_like(tt, NF * T + 4)], 1)
        out.append((bb, r, J, idx))
        rc = (st.C[bb, tt] - st.Cm[bb]) / o.centre_sigma_m
        J = idx = None
        if jac:
            eye = torch.eye(3, dtype=rc.dtype, device=dev).expand(len(bb), 3, 3)
            J = torch.cat([eye, -eye], 2) / o.centre_sigma_m
            idx = torch.cat([(NF * tt + 3)[:, None] + ar3, (NF * T + ar3).expand(len(bb), 3)], 1)
        out.append((bb, rc, J, idx))
        bcam = torch.arange(B, device=dev)
        rm = (st.Cm - bt.mount) / o.mount_sigma_m
        J = idx = None
        if jac:
            J = torch.eye(3, dtype=rm.dtype, device=dev).expand(B, 3, 3) / o.mount_sigma_m
            idx = (NF * T + ar3).expand(B, 3)
        out.append((bcam, rm, J, idx))
        # weak priors on the encoder calibration (1 % gain, 1 % offset) keep the system regular
        scale = bt.s.mean(1)
        r = torch.stack([st.a / 0.01, st.off / (0.01 * scale)], 1)
        J = idx = None
        if jac:
            J = torch.zeros(B, 2, 2, dtype=r.dtype, device=dev)
            J[:, 0, 0] = 1 / 0.01
            J[:, 1, 1] = 1 / (0.01 * scale)
            idx = torch.tensor([NF * T + 3, NF * T + 4], device=dev).expand(B, 2)
        out.append((bcam, r, J, idx))
    else:
        # without priors: only a weak regulariser (1 m around the mount) so every frame stays solvable
        rc = (st.C[bb, tt] - bt.mount[bb]) / 1.0
        J = idx = None
        if jac:
            J = torch.eye(3, dtype=rc.dtype, device=dev).expand(len(bb), 3, 3).clone()
            idx = (NF * tt + 3)[:, None] + ar3
        out.append((bb, rc, J, idx))
    return out


def _cost(st: _State, bt: _Batch, o: TrackingOptions) -> torch.Tensor:
    """Per-camera cost [B]: Cauchy on data terms, squares on priors."""
    c = torch.zeros(bt.B, dtype=torch.float64, device=st.C.device)
    for b, r, _, _ in _terms(st, bt, o, False):
        c.index_add_(0, b, torch.log1p((r ** 2).sum(1)))
    for b, r, _, _ in _prior_terms(st, bt, o, False):
        c.index_add_(0, b, (r ** 2).sum(1))
    return c


def _normal_equations(st: _State, bt: _Batch, o: TrackingOptions):
    B, n = bt.B, bt.n
    dev = st.C.device
    H = torch.zeros(B * n * n, dtype=torch.float64, device=dev)
    g = torch.zeros(B * n, dtype=torch.float64, device=dev)
    for robust, terms in ((True, _terms(st, bt, o, True)), (False, _prior_terms(st, bt, o, True))):
        for b, r, J, idx in terms:
            if len(b) == 0:
                continue
            w = 1.0 / (1.0 + (r ** 2).sum(1)) if robust else torch.ones(len(b), dtype=r.dtype, device=dev)
            Jw = J * w[:, None, None]
            JtJ = Jw.transpose(1, 2) @ J                                        # [Q, m, m]
            Jtr = (Jw.transpose(1, 2) @ r[..., None])[..., 0]                   # [Q, m]
            flat = (b[:, None, None] * n * n + idx[:, :, None] * n + idx[:, None, :]).reshape(-1)
            H.index_add_(0, flat, JtJ.reshape(-1))
            g.index_add_(0, (b[:, None] * n + idx).reshape(-1), Jtr.reshape(-1))
    H = H.view(B, n, n)
    g = g.view(B, n)
    # frames a camera does not have, and the unused globals without priors, get unit diagonals
    diag = H.diagonal(dim1=1, dim2=2)
    diag += (diag == 0).to(H.dtype)
    return H, g


def refine_tracking(obs: list[TrackingObservations], init: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                    prior_px: list[np.ndarray], principal: np.ndarray, mounts: list[np.ndarray],
                    options: TrackingOptions = TrackingOptions()) -> list[TrackingSolution]:
    """Jointly refine every tracking camera's sequence (batched over cameras).

    ``init[b]`` = (R [T, 3, 3], C [T, 3], f [T]) from :func:`initialise_tracking`; ``prior_px[b]`` [T]
    the smoothed encoder focal in px; ``principal`` [B, 2], or per camera [T, 2] (a principal point
    per frame), held fixed; ``mounts[b]`` [3] the nominal centre (prior of the mean centre).
    """
    t0 = time.perf_counter()
    dev = torch.device(options.device)
    f64 = dict(dtype=torch.float64, device=dev)
    T_max = max(ob.frame_count for ob in obs)
    pp = np.stack([_principal_per_frame(principal[b], T_max) for b in range(len(obs))])       # [B, T, 2]
    bt = _Batch(obs, pp, prior_px, mounts, options, dev)
    B, T = bt.B, bt.T

    def pad(a, shape_tail, fill):
        out = np.broadcast_to(np.asarray(fill, np.float64), (B, T) + shape_tail).copy()
        for b, x in enumerate(a):
            out[b, :len(x)] = x
        return torch.as_tensor(out, **f64)

    R = pad([i[0] for i in init], (3, 3), np.eye(3))
    C = pad([i[1] for i in init], (3,), 0.0)
    logf = torch.log(pad([i[2] for i in init], (), 1.0))
    Cm = torch.stack([C[b, :obs[b].frame_count].mean(0) for b in range(B)])
    # start gain/offset at the least-squares fit of the initial focal to the prior curve
    a = torch.zeros(B, **f64)
    off = torch.zeros(B, **f64)
    st = _State(R, C, logf, Cm, a, off)
    lam = torch.full((B,), 1e-3, **f64)
    cost = _cost(st, bt, options)
    it = 0
    for it in range(options.iterations):
        H, g = _normal_equations(st, bt, options)
        D = torch.diag_embed(H.diagonal(dim1=1, dim2=2))
        d = torch.linalg.solve(H + lam[:, None, None] * D, -g[..., None])[..., 0]
        new = st.step(d, T)
        new_cost = _cost(new, bt, options)
        better = new_cost < cost
        st = _State(*[torch.where(_bc(better, x), y, x) for x, y in
                      ((st.R, new.R), (st.C, new.C), (st.logf, new.logf), (st.Cm, new.Cm), (st.a, new.a),
                       (st.off, new.off))])
        rel = (cost - new_cost) / cost.clamp(min=1e-12)
        cost = torch.where(better, new_cost, cost)
        lam = torch.where(better, (lam / 3).clamp(min=1e-9), lam * 5)
        if bool(((rel.abs() < 1e-7) & better | (lam > 1e7)).all()) and it > 2:
            break
    sols = []
    f = torch.exp(st.logf)
    spread = _spread(st, bt, options)
    for b in range(B):
        Tb = obs[b].frame_count
        K = np.zeros((Tb, 3, 3))
        K[:, 0, 0] = f[b, :Tb].cpu().numpy()
        K[:, 1, 1] = K[:, 0, 0]
        K[:, 0, 2], K[:, 1, 2] = pp[b, :Tb, 0], pp[b, :Tb, 1]
        K[:, 2, 2] = 1
        Rb = st.R[b, :Tb].cpu().numpy()
        Cb = st.C[b, :Tb].cpu().numpy()
        W = np.tile(np.eye(4), (Tb, 1, 1))
        W[:, :3, :3] = Rb
        W[:, :3, 3] = -np.einsum("tij,tj->ti", Rb, Cb)
        res = _per_frame_residuals(st, bt, options, b, Tb)
        sols.append(TrackingSolution(K, W, float(torch.exp(st.a[b])), float(st.off[b]),
                                     st.Cm[b].cpu().numpy(),
                                     {"cost": float(cost[b]), "iterations": it + 1, **res,
                                      **{k: float(v[b]) for k, v in spread.items()}}))
    for s in sols:
        s.stats["seconds"] = time.perf_counter() - t0
    return sols


def _spread(st: _State, bt: _Batch, o: TrackingOptions) -> dict[str, torch.Tensor]:
    """How well each camera's solution is determined, from the Gauss-Newton covariance ``H^-1`` at
    the solution (the residuals are in units of their sigma, so ``H^-1`` is a covariance; the
    Cauchy weights of the last step count the outliers out). Per camera [B]:

    - ``focal_sigma_pct``: standard deviation of the take's mean focal, % (along the zoom/dolly
      valley the data barely tell a zoom from a dolly, so this is what the mount and encoder priors
      leave open where the 2D-3D matches are few);
    - ``rotation_sigma_deg``: the largest standard deviation of a frame's orientation (degrees);
    - ``centre_sigma_m``: the largest standard deviation of a frame's centre (metres).

    A lower bound on the true spread: where the robust term's inliers would change, no quadratic
    model sees it.
    """
    H, _ = _normal_equations(st, bt, o)
    cov = torch.linalg.inv(H)                                                  # [B, n, n]
    B, T = bt.B, bt.T
    blocks = cov[:, :NF * T, :NF * T].reshape(B, T, NF, T, NF)
    per_frame = torch.diagonal(blocks, dim1=1, dim2=3).permute(0, 3, 1, 2)     # [B, T, NF, NF]
    valid = bt.valid_frame
    n_valid = valid.sum(1).to(cov.dtype)
    # mean log focal over a camera's frames: v = 1/T_b on its frames' log-focal entries
    v = torch.zeros(B, bt.n, dtype=cov.dtype, device=cov.device)
    v[:, 6:NF * T:NF] = valid.to(cov.dtype) / n_valid[:, None]
    var_f = torch.einsum("bi,bij,bj->b", v, cov, v)
    rot = torch.linalg.eigvalsh(per_frame[..., :3, :3]).amax(-1).clamp(min=0)  # [B, T]
    cen = torch.linalg.eigvalsh(per_frame[..., 3:6, 3:6]).amax(-1).clamp(min=0)
    zero = torch.zeros_like(rot)
    return {"focal_sigma_pct": 100 * var_f.clamp(min=0).sqrt(),
            "rotation_sigma_deg": torch.rad2deg(torch.where(valid, rot, zero).amax(1).sqrt()),
            "centre_sigma_m": torch.where(valid, cen, zero).amax(1).sqrt()}


def tracking_support(sol: TrackingSolution, options: TrackingOptions = TrackingOptions()) -> str | None:
    """Why a solved tracking camera cannot be returned as calibrated, or None: fewer 2D-3D inliers
    over the take than ``options.min_inliers_3d`` (the priors alone would place it), or a frame's
    orientation determined to worse than ``options.max_rotation_sigma_deg`` (``stats``'
    ``rotation_sigma_deg``, from the solve's covariance)."""
    inliers = int(sol.stats.get("reprojection_3d_px_inliers", 0))
    if inliers < options.min_inliers_3d:
        return (f"{inliers} 2D-3D inliers against the static reference over the take (needs at least "
                f"{options.min_inliers_3d})")
    sigma = float(sol.stats.get("rotation_sigma_deg", float("inf")))
    if options.max_rotation_sigma_deg is not None and not sigma <= options.max_rotation_sigma_deg:
        return (f"its orientation is determined to {sigma:.3g}° only (bound {options.max_rotation_sigma_deg}°, "
                f"from {inliers} 2D-3D inliers)")
    return None


def _bc(mask: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    return mask.view(-1, *([1] * (x.dim() - 1)))


def _per_frame_residuals(st, bt, o, b, Tb) -> dict:
    out = {}
    terms = _terms(st, bt, o, False)
    names = ["reprojection_3d_px", "reprojection_2d_px"] if len(bt.c3) else ["reprojection_2d_px"]
    sig = [o.pixel_sigma_3d, o.pixel_sigma_2d]
    for name, s, (cam, r, _, _) in zip(names, sig, terms):
        sel = cam == b
        e = (r[sel].norm(dim=1) * s).cpu().numpy()
        inl = e[e < 3 * s]
        out[name + "_median"] = float(np.median(inl)) if len(inl) else float("nan")   # over the inliers
        out[name + "_inliers"] = int(len(inl))
        out[name + "_matches"] = int(len(e))
    return out
