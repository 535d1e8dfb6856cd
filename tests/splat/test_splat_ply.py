"""PLY export in the standard 3DGS layout."""

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # _splat_scenes, any import mode

from _splat_scenes import random_gaussians  # noqa: E402

from volcap_core.splat.model import Poly4DGS, Poly4DGSConfig  # noqa: E402
from volcap_core.splat.ply import export_ply, gaussians_to_ply, read_ply  # noqa: E402


def test_header_layout_and_binary_body():
    g = random_gaussians(5, sh_degree=3)
    blob = gaussians_to_ply(g)
    header, body = blob.split(b"end_header\n", 1)
    lines = header.decode().splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    props = [line.split()[2] for line in lines if line.startswith("property")]
    assert props[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert props[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert props[54:] == ["opacity", "scale_0", "scale_1", "scale_2",
                          "rot_0", "rot_1", "rot_2", "rot_3"]
    assert "element vertex 5" in lines and len(body) == 5 * 62 * 4
    rows = np.frombuffer(body, "<f4").reshape(5, 62)
    # f_rest is channel-major: red's 15 bands first
    np.testing.assert_allclose(rows[:, 9:24], g.sh[:, 1:, 0].numpy(), rtol=1e-6)
    np.testing.assert_allclose(rows[:, 54], torch.logit(g.opacities.double()).numpy(), rtol=1e-5)
    np.testing.assert_allclose(rows[:, 55:58], np.log(g.scales.numpy()), rtol=1e-5)


def test_round_trip_and_model_slice():
    g = random_gaussians(7, sh_degree=1)
    back = read_ply(gaussians_to_ply(g))
    torch.testing.assert_close(back.means, g.means)
    torch.testing.assert_close(back.sh, g.sh)
    torch.testing.assert_close(back.opacities, g.opacities, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(back.scales, g.scales, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(back.quats, torch.nn.functional.normalize(g.quats, dim=-1))
    m = Poly4DGS.from_points(Poly4DGSConfig.paper(sh_degree=0), g.means, torch.rand(7, 3),
                             scales=torch.full((7,), 0.1), t0=torch.zeros(7), lifespan_s=0.1)
    assert read_ply(export_ply(m, 0.0)).means.shape == (7, 3)
    assert read_ply(export_ply(m, 10.0)).means.shape == (0, 3)  # all outside their lifespan
