"""Direct (photometric) refinement of static cameras against the lidar scan.

Feature-based bundle adjustment of a few wide low-resolution views leaves rotations tenths of a
degree off (docs/calibration.md): a few hundred two- and three-view points do not pin them (near-null directions couple rotations with
point depths). The stage background is clean and textured, and the lidar says where it is, so
every textured background pixel can vote: a scan point ``X`` seen by cameras ``a`` and ``b`` must
look the same in both,

    r_ab(X) = I_a(pi_a(X)) - I_b(pi_b(X)),

where ``I`` are locally contrast-normalised images (insensitive to per-camera gain, black level
and vignetting). ``X`` stays on the scan, so the frame and scale are the scan's. Gauss-Newton /
Levenberg-Marquardt over all cameras' rotation, centre and (optionally) log focal, with Cauchy
weights, priors on focal and centre, coarse to fine over Gaussian-blurred images.

Visibility: a scan point is visible in a camera when it lies in front of it, inside the image, faces
it, and is not behind other scan points (z-buffer of the scan, min-filtered to close the gaps between
scan samples). Actors are not in the scan: pass background plates (:func:`background_plate`) or rely
on the robust loss.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from volcap_core.calibration.images import exposure_normalise, luminance
from volcap_core.calibration.lidar import LidarScan, depth_buffer

NCAM = 9   # rotation (3), centre (3), log focal (1), principal point (2)


@dataclass(frozen=True)
class PhotometricOptions:
    #: Gaussian blur (px) of each coarse-to-fine level
    blur_px: tuple[float, ...] = (3.0, 1.5, 0.75)
    iterations: int = 12
    #: half size (px) of the window of the local contrast normalisation
    normalise_radius: int = 4
    focal_sigma_rel: float | None = 0.03
    #: prior (px) of the principal point around the initial one (None: held fixed, the default). A
    #: 1 px error of a 320 px-wide view is a 0.2° rotation error, and the synthetic sensors are off by
    #: ~1 px; but for distant backgrounds a principal-point shift and a rotation look the same, and
    #: freeing it made the rotations worse (measured), so it stays fixed.
    principal_sigma_px: float | None = None
    centre_sigma_m: float = 0.05
    #: minimum cosine between the scan normal and the direction to the camera
    min_view_cos: float = 0.25
    #: maximum number of scan samples used (random subset)
    max_points: int = 60000
    #: camera pairs need at least this many common visible samples
    min_pair_points: int = 200
    #: maximum angle (deg) between the viewing directions of a pair at a shared point
    max_pair_angle_deg: float = 75.0
    device: str = "cpu"
    seed: int = 0


def background_plate(frames: list[np.ndarray]) -> np.ndarray:
    """Per-pixel median of a static camera's frames [H, W, C] each: actors that move leave it."""
    return np.median(np.stack([np.asarray(f, np.float32) for f in frames]), axis=0)


def normalised_image(linear: np.ndarray, radius: int = 4) -> np.ndarray:
    """Locally contrast-normalised log-luminance [H, W] float32: (L - mean_w) / (std_w + eps) over a
    (2r+1)^2 box, with L = log(luminance + 0.01) of the exposure-normalised image."""
    import cv2

    img = exposure_normalise(np.asarray(linear, np.float32))
    lum = luminance(img) if img.ndim == 3 else img
    L = np.log(np.maximum(lum, 0.0) + 0.01).astype(np.float32)
    k = (2 * radius + 1, 2 * radius + 1)
    m = cv2.blur(L, k, borderType=cv2.BORDER_REFLECT)
    v = cv2.blur(L * L, k, borderType=cv2.BORDER_REFLECT) - m * m
    return ((L - m) / (np.sqrt(np.maximum(v, 0.0)) + 0.05)).astype(np.float32)


def scan_visibility(K: np.ndarray, world_to_camera: np.ndarray, width: int, height: int,
                    points: np.ndarray, normals: np.ndarray, min_view_cos: float = 0.25,
                    splat_px: int = 4, depth_tol: float = 0.03) -> np.ndarray:
    """Boolean [N]: scan points visible in a camera (in front, inside, facing it, not occluded)."""
    R, t = world_to_camera[:3, :3], world_to_camera[:3, 3]
    C = -R.T @ t
    pc = points @ R.T + t
    z = pc[:, 2]
    ok = z > 0.1
    uv = np.zeros((len(points), 2))
    uv[ok] = pc[ok, :2] / z[ok, None] @ K[:2, :2].T + K[:2, 2]
    ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= height - 1)
    to_cam = C - points
    cosv = np.einsum("ij,ij->i", normals, to_cam) / np.maximum(np.linalg.norm(to_cam, axis=1), 1e-9)
    ok &= np.abs(cosv) > min_view_cos
    ix = np.round(uv[ok]).astype(np.int64)
    zbuf = depth_buffer(K, world_to_camera, width, height, points[ok], splat_px)
    vis = np.zeros(len(points), bool)
    vis[np.flatnonzero(ok)] = z[ok] <= zbuf[ix[:, 1], ix[:, 0]] * (1 + depth_tol) + 0.02
    return vis


def refine_photometric(images: dict[str, np.ndarray], K: dict[str, np.ndarray],
                       world_to_camera: dict[str, np.ndarray], scan: LidarScan,
                       *, centre_prior: dict[str, np.ndarray] | None = None,
                       focal_prior: dict[str, float] | None = None,
                       options: PhotometricOptions = PhotometricOptions()) -> dict:
    """Refine static cameras so the scan looks the same in every camera that sees it.

    ``images``: id -> linear RGB [H, W, C] (background plates preferably); ``K``: id -> [3, 3]
    (fx = fy assumed, principal point held); ``world_to_camera``: id -> [4, 4] initial poses.
    Priors: centre (default: the initial centres) with ``centre_sigma_m``; log focal (default: the
    initial focal) with ``focal_sigma_rel`` (None holds focal lengths fixed).

    Returns ``world_to_camera`` and ``K`` dicts, ``pairs`` used, per-level RMS residuals and seconds.
    """
    t0 = time.perf_counter()
    ids = sorted(images)
    dev = torch.device(options.device)
    f64 = dict(dtype=torch.float64, device=dev)
    rng = np.random.default_rng(options.seed)
    pts = scan.points
    nrm = scan.normals
    if len(pts) > options.max_points * 4:
        sub = rng.choice(len(pts), options.max_points * 4, replace=False)
        pts, nrm = pts[sub], nrm[sub]
    sizes = {c: images[c].shape[:2] for c in ids}
    vis = np.stack([scan_visibility(K[c], world_to_camera[c], sizes[c][1], sizes[c][0], pts, nrm,
                                    options.min_view_cos) for c in ids])        # [C, N]
    keep = vis.sum(0) >= 2
    if keep.sum() > options.max_points:
        idx = np.flatnonzero(keep)
        keep[:] = False
        keep[rng.choice(idx, options.max_points, replace=False)] = True
    pts, vis = pts[keep], vis[:, keep]
    # pairs of cameras with enough common samples and not too oblique
    centres = {c: -world_to_camera[c][:3, :3].T @ world_to_camera[c][:3, 3] for c in ids}
    pa, pb, pp_ = [], [], []
    for i in range(len(ids)):
        for j in range(i + 1, len(ids)):
            common = np.flatnonzero(vis[i] & vis[j])
            if len(common) < options.min_pair_points:
                continue
            da = centres[ids[i]] - pts[common]
            db = centres[ids[j]] - pts[common]
            cosang = np.einsum("ij,ij->i", da, db) / (np.linalg.norm(da, axis=1) * np.linalg.norm(db, axis=1))
            common = common[cosang > math.cos(math.radians(options.max_pair_angle_deg))]
            if len(common) < options.min_pair_points:
                continue
            pa.append(np.full(len(common), i))
            pb.append(np.full(len(common), j))
            pp_.append(common)
    if not pa:
        raise RuntimeError("photometric refinement: no camera pair shares enough visible scan points")
    ra = torch.as_tensor(np.concatenate(pa), device=dev)
    rb = torch.as_tensor(np.concatenate(pb), device=dev)
    rp = torch.as_tensor(np.concatenate(pp_), device=dev)
    X = torch.as_tensor(pts, **f64)
    ncam = len(ids)
    R = torch.as_tensor(np.stack([world_to_camera[c][:3, :3] for c in ids]), **f64)
    Cc = torch.as_tensor(np.stack([centres[c] for c in ids]), **f64)
    logf = torch.log(torch.as_tensor([K[c][0, 0] for c in ids], **f64))
    aspect = torch.as_tensor([K[c][1, 1] / K[c][0, 0] for c in ids], **f64)
    pp = torch.as_tensor(np.stack([K[c][:2, 2] for c in ids]), **f64)
    pp0 = pp.clone()
    C0 = torch.as_tensor(np.stack([(centre_prior or centres)[c] for c in ids]), **f64)
    logf0 = logf.clone() if focal_prior is None else torch.log(torch.as_tensor([focal_prior[c] for c in ids], **f64))
    fix_focal = options.focal_sigma_rel is None
    norm_imgs = {c: normalised_image(images[c], options.normalise_radius) for c in ids}
    hmax = max(s[0] for s in sizes.values())
    wmax = max(s[1] for s in sizes.values())
    levels = []
    for blur in options.blur_px:
        ims, gxs, gys = [], [], []
        for c in ids:
            img = _blur(norm_imgs[c], blur)
            gx, gy = _gradients(img)
            ims.append(_pad(img, hmax, wmax))
            gxs.append(_pad(gx, hmax, wmax))
            gys.append(_pad(gy, hmax, wmax))
        levels.append(torch.as_tensor(np.stack([ims, gxs, gys], 1), dtype=torch.float32, device=dev))
    wh = torch.as_tensor([[sizes[c][1], sizes[c][0]] for c in ids], **f64)
    history = []
    for lev in levels:
        lam = 1e-3
        state = (R, Cc, logf, pp)
        cost, _ = _photo_cost(state, lev, X, ra, rb, rp, pp0, aspect, wh, C0, logf0, options, fix_focal, None)
        scale = None
        for _ in range(options.iterations):
            dc, scale = _photo_step(state, lev, X, ra, rb, rp, pp0, aspect, wh, C0, logf0, options,
                                    fix_focal, lam, ncam, scale)
            dR = axis_angle_to_rotation_matrix(dc[:, :3])
            new = (dR @ state[0], state[1] + dc[:, 3:6], state[2] + dc[:, 6], state[3] + dc[:, 7:9])
            new_cost, _ = _photo_cost(new, lev, X, ra, rb, rp, pp0, aspect, wh, C0, logf0, options, fix_focal, scale)
            cost, _ = _photo_cost(state, lev, X, ra, rb, rp, pp0, aspect, wh, C0, logf0, options, fix_focal, scale)
            if new_cost < cost:
                state = new
                lam = max(lam / 3, 1e-9)
                if (cost - new_cost) / max(cost, 1e-12) < 1e-6:
                    break
            else:
                lam *= 5
                if lam > 1e6:
                    break
        R, Cc, logf, pp = state
        _, rms = _photo_cost(state, lev, X, ra, rb, rp, pp0, aspect, wh, C0, logf0, options, fix_focal, scale)
        history.append(rms)
    out_w2c, out_K = {}, {}
    f = torch.exp(logf).cpu().numpy()
    for i, c in enumerate(ids):
        Ri = R[i].cpu().numpy()
        m = np.eye(4)
        m[:3, :3] = Ri
        m[:3, 3] = -Ri @ Cc[i].cpu().numpy()
        out_w2c[c] = m
        ppi = pp[i].cpu().numpy()
        out_K[c] = np.array([[f[i], 0, ppi[0]], [0, f[i] * float(aspect[i]), ppi[1]], [0, 0, 1.0]])
    return {"world_to_camera": out_w2c, "K": out_K, "samples": int(len(rp)), "points": int(len(pts)),
            "pairs": sorted({(ids[int(a)], ids[int(b)]) for a, b in zip(ra[::97], rb[::97])}),
            "rms_per_level": history, "seconds": time.perf_counter() - t0}


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT) if sigma > 0 else img


def _gradients(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gx = np.zeros_like(img)
    gy = np.zeros_like(img)
    gx[:, 1:-1] = (img[:, 2:] - img[:, :-2]) / 2
    gy[1:-1] = (img[2:] - img[:-2]) / 2
    return gx, gy


def _pad(img: np.ndarray, h: int, w: int) -> np.ndarray:
    out = np.zeros((h, w), np.float32)
    out[: img.shape[0], : img.shape[1]] = img
    return out


def _sample(lev: torch.Tensor, cam: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear samples [Q, 3] (value, d/dx, d/dy) of the per-camera images at OpenCV px uv [Q, 2]."""
    ncam, _, H, W = lev.shape
    gx = 2 * (uv[:, 0] + 0.5) / W - 1
    gy = 2 * (uv[:, 1] + 0.5) / H - 1
    out = torch.empty(len(uv), 3, dtype=torch.float64, device=uv.device)
    for c in torch.unique(cam).tolist():
        sel = cam == c
        g = torch.stack([gx[sel], gy[sel]], -1).to(lev.dtype)[None, None]
        s = F.grid_sample(lev[c:c + 1], g, mode="bilinear", padding_mode="border", align_corners=False)
        out[sel] = s[0, :, 0].T.to(torch.float64)
    return out


def _proj(state, cam, X, pp, aspect):
    R, C, logf, pp = state
    Xc = (R[cam] @ (X - C[cam])[..., None])[..., 0]
    z = Xc[:, 2].clamp(min=1e-6)
    f = torch.exp(logf)[cam]
    fy = f * aspect[cam]
    uv = torch.stack([f * Xc[:, 0] / z, fy * Xc[:, 1] / z], -1) + pp[cam]
    return Xc, z, f, fy, uv


def _residuals(state, lev, X, ra, rb, rp, pp, aspect, wh):
    Xa = X[rp]
    _, _, _, _, ua = _proj(state, ra, Xa, pp, aspect)
    _, _, _, _, ub = _proj(state, rb, Xa, pp, aspect)
    sa = _sample(lev, ra, ua)
    sb = _sample(lev, rb, ub)
    inside = ((ua >= 0) & (ua <= wh[ra] - 1)).all(1) & ((ub >= 0) & (ub <= wh[rb] - 1)).all(1)
    return sa[:, 0] - sb[:, 0], sa, sb, ua, ub, inside


def _robust_scale(r: torch.Tensor) -> float:
    return float(1.4826 * r.abs().median().clamp(min=1e-3))


def _photo_cost(state, lev, X, ra, rb, rp, pp0, aspect, wh, C0, logf0, o, fix_focal, scale):
    r, *_, inside = _residuals(state, lev, X, ra, rb, rp, pp0, aspect, wh)
    r = r[inside]
    s = _robust_scale(r) if scale is None else scale
    c = float(torch.log1p((r / s) ** 2).sum())
    c += float((((state[1] - C0) / o.centre_sigma_m) ** 2).sum())
    if o.principal_sigma_px is not None:
        c += float((((state[3] - pp0) / o.principal_sigma_px) ** 2).sum())
    if not fix_focal:
        c += float((((state[2] - logf0) / o.focal_sigma_rel) ** 2).sum())
    return c, float(r.pow(2).mean().sqrt())


def _dproj(state, cam, X, pp, aspect):
    R, C, logf, pp = state
    Xc, z, f, fy, uv = _proj(state, cam, X, pp, aspect)
    d = torch.zeros(len(z), 2, 3, dtype=z.dtype, device=z.device)
    d[:, 0, 0] = f / z
    d[:, 1, 1] = fy / z
    d[:, 0, 2] = -f * Xc[:, 0] / z ** 2
    d[:, 1, 2] = -fy * Xc[:, 1] / z ** 2
    zero = torch.zeros_like(Xc[:, 0])
    skew = torch.stack([torch.stack([zero, -Xc[:, 2], Xc[:, 1]], -1),
                        torch.stack([Xc[:, 2], zero, -Xc[:, 0]], -1),
                        torch.stack([-Xc[:, 1], Xc[:, 0], zero], -1)], -2)
    Jw = d @ (-skew)
    JC = d @ (-R[cam])
    Jf = (uv - pp[cam])[..., None]
    Jp = torch.eye(2, dtype=z.dtype, device=z.device).expand(len(z), 2, 2)
    return torch.cat([Jw, JC, Jf, Jp], 2)                                  # [Q, 2, 9]


def _photo_step(state, lev, X, ra, rb, rp, pp0, aspect, wh, C0, logf0, o, fix_focal, lam, ncam, scale):
    pp = state[3]
    r, sa, sb, ua, ub, inside = _residuals(state, lev, X, ra, rb, rp, pp, aspect, wh)
    s = _robust_scale(r[inside]) if scale is None else scale
    w = inside.to(r.dtype) / (1 + (r / s) ** 2)
    Xa = X[rp]
    Ja = (sa[:, 1:3, None] * _dproj(state, ra, Xa, pp, aspect)).sum(1)    # [Q, 9]
    Jb = -(sb[:, 1:3, None] * _dproj(state, rb, Xa, pp, aspect)).sum(1)
    if fix_focal:
        Ja[:, 6] = 0
        Jb[:, 6] = 0
    if o.principal_sigma_px is None:
        Ja[:, 7:9] = 0
        Jb[:, 7:9] = 0
    H = torch.zeros(ncam * ncam, NCAM, NCAM, dtype=r.dtype, device=r.device)
    wa = Ja * w[:, None]
    wb = Jb * w[:, None]
    H.index_add_(0, ra * ncam + ra, wa[:, :, None] * Ja[:, None, :])
    H.index_add_(0, rb * ncam + rb, wb[:, :, None] * Jb[:, None, :])
    H.index_add_(0, ra * ncam + rb, wa[:, :, None] * Jb[:, None, :])
    H.index_add_(0, rb * ncam + ra, wb[:, :, None] * Ja[:, None, :])
    g = torch.zeros(ncam, NCAM, dtype=r.dtype, device=r.device)
    g.index_add_(0, ra, wa * r[:, None])
    g.index_add_(0, rb, wb * r[:, None])
    H = H.view(ncam, ncam, NCAM, NCAM).permute(0, 2, 1, 3).reshape(ncam * NCAM, ncam * NCAM)
    g = g.reshape(-1)
    # priors (in units where the data term is r^2 / s^2 ~ 1 per sample: scale them by s^2)
    s2 = s * s
    for i in range(ncam):
        b = i * NCAM
        for k in range(3):
            H[b + 3 + k, b + 3 + k] += s2 / o.centre_sigma_m ** 2
            g[b + 3 + k] += s2 * float(state[1][i, k] - C0[i, k]) / o.centre_sigma_m ** 2
        if fix_focal:
            H[b + 6, b + 6] += 1.0
        else:
            H[b + 6, b + 6] += s2 / o.focal_sigma_rel ** 2
            g[b + 6] += s2 * float(state[2][i] - logf0[i]) / o.focal_sigma_rel ** 2
        for k in range(2):
            if o.principal_sigma_px is None:
                H[b + 7 + k, b + 7 + k] += 1.0
            else:
                H[b + 7 + k, b + 7 + k] += s2 / o.principal_sigma_px ** 2
                g[b + 7 + k] += s2 * float(state[3][i, k] - pp0[i, k]) / o.principal_sigma_px ** 2
    D = torch.diag(H.diagonal())
    dc = torch.linalg.solve(H + lam * D + 1e-12 * torch.eye(len(g), dtype=r.dtype, device=r.device), -g)
    return dc.view(ncam, NCAM), s
