"""Export Gaussians at one instant as a standard 3DGS PLY (what SuperSplat, the INRIA viewer,
gsplat's viewer, Polycam and most splat tools open).

Layout: binary little-endian, one ``vertex`` element, float32 properties in this order::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_{3(K-1)-1}  opacity
    scale_0 scale_1 scale_2  rot_0 rot_1 rot_2 rot_3

``f_rest`` is channel-major (all of red's higher bands, then green's, then blue's), ``opacity`` is a
logit, ``scale_*`` are log standard deviations, ``rot`` is a unit quaternion wxyz; normals are 0.
Viewers compute ``SH · Y + 0.5`` and display it as sRGB: Poly4DGS colours already are (unbounded)
sRGB, so the file shows the model's colours without conversion.
"""

from __future__ import annotations

import numpy as np
import torch

from volcap_core.splat.model import Gaussians3D, Poly4DGS, evaluate

__all__ = ["export_ply", "gaussians_to_ply", "read_ply"]


def _fields(k: int) -> list[str]:
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def gaussians_to_ply(g: Gaussians3D) -> bytes:
    """Encode ``g`` (M Gaussians, ``sh [M, K, 3]``) as PLY bytes."""
    m, k = g.sh.shape[0], g.sh.shape[1]
    sh = g.sh.detach().cpu().double()
    o = g.opacities.detach().cpu().double().clamp(1e-7, 1 - 1e-7)
    q = torch.nn.functional.normalize(g.quats.detach().cpu().double(), dim=-1, eps=1e-12)
    cols = [g.means.detach().cpu().double(), torch.zeros(m, 3, dtype=torch.float64), sh[:, 0],
            sh[:, 1:].transpose(1, 2).reshape(m, 3 * (k - 1)), torch.log(o / (1 - o))[:, None],
            torch.log(g.scales.detach().cpu().double().clamp(min=1e-30)), q]
    data = torch.cat(cols, dim=1).numpy().astype("<f4")
    names = _fields(k)
    assert data.shape[1] == len(names)
    header = "ply\nformat binary_little_endian 1.0\n"
    header += "comment volcap Poly4DGS slice\n"
    header += f"element vertex {m}\n"
    header += "".join(f"property float {n}\n" for n in names)
    header += "end_header\n"
    return header.encode("ascii") + np.ascontiguousarray(data).tobytes()


def export_ply(model: Poly4DGS, t: float) -> bytes:
    """The model sliced at time ``t`` (seconds; Gaussians with opacity < 1/255 at t left out) as
    PLY bytes."""
    with torch.no_grad():
        return gaussians_to_ply(evaluate(model, t))


def read_ply(data: bytes) -> Gaussians3D:
    """Parse a binary little-endian 3DGS PLY with float properties (the inverse of
    :func:`gaussians_to_ply`; also reads files from other 3DGS tools)."""
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError("not a PLY file")
    header = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError("only binary_little_endian PLY is supported")
    n, names = 0, []
    for line in header:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            n = int(parts[2])
        elif parts[:1] == ["property"]:
            if parts[1] != "float":
                raise ValueError(f"unsupported property type {parts[1]!r}")
            names.append(parts[2])
    body = np.frombuffer(data, dtype="<f4", count=n * len(names), offset=end + len(b"end_header\n"))
    arr = torch.from_numpy(body.reshape(n, len(names)).astype(np.float32))
    col = {name: arr[:, i] for i, name in enumerate(names)}
    rest = sorted((x for x in names if x.startswith("f_rest_")), key=lambda s: int(s[7:]))
    k = 1 + len(rest) // 3
    sh = torch.zeros(n, k, 3)
    sh[:, 0] = torch.stack([col[f"f_dc_{c}"] for c in range(3)], -1)
    if rest:
        sh[:, 1:] = torch.stack([col[r] for r in rest], -1).reshape(n, 3, k - 1).transpose(1, 2)
    return Gaussians3D(
        means=torch.stack([col["x"], col["y"], col["z"]], -1),
        quats=torch.stack([col[f"rot_{i}"] for i in range(4)], -1),
        scales=torch.exp(torch.stack([col[f"scale_{i}"] for i in range(3)], -1)),
        opacities=torch.sigmoid(col["opacity"]), sh=sh, ids=torch.arange(n))
