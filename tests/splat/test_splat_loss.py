"""SSIM/PSNR against scikit-image's values on real image pairs; the training loss's colour space."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from volcap_core.colour import srgb_encode_unbounded
from volcap_core.image_metrics import psnr, ssim
from volcap_core.splat.loss import grid_regularisers, reconstruction_loss

PAIRS = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "reference" / "ssim_pairs"


def _load(name):
    cv2 = pytest.importorskip("cv2")
    img = cv2.imread(str(PAIRS / name), cv2.IMREAD_UNCHANGED)
    if img is None:
        pytest.skip(f"cannot read {name}")
    img = torch.from_numpy(img.astype(np.float64) / 255.0)
    return img[..., None] if img.ndim == 2 else img


def _pairs():
    ref = PAIRS / "reference_values.json"
    if not ref.exists():
        return []
    values = json.loads(ref.read_text())["pairs"]
    return [pytest.param(v, id=k) for k, v in values.items()
            if all((PAIRS / f).exists() for f in v["files"])]


@pytest.mark.parametrize("pair", _pairs())
def test_ssim_and_psnr_match_scikit_image(pair):
    a, b = (_load(f) for f in pair["files"])
    s = float(ssim(a, b, padding="valid"))
    assert s == pytest.approx(pair["ssim_wang_gaussian_sigma1.5_popcov"], abs=1e-6)
    if "psnr_db" in pair:
        assert float(psnr(a, b)) == pytest.approx(pair["psnr_db"], abs=1e-6)


def test_reference_pairs_present_or_skip():
    """The reference set is either absent (skip, so its absence shows) or whole: ``_pairs`` quietly
    drops a pair with a missing file, which would shrink the scikit-image comparison unseen.

    A pair may also name a file outside the folder (the IPOL reference's noisy image, a ``.npy`` not
    shipped with the pairs): such a pair is not run, and is not required here."""
    ref = PAIRS / "reference_values.json"
    if not ref.exists():
        pytest.skip("shared SSIM reference pairs absent")
    values = json.loads(ref.read_text())["pairs"]
    local = {k: v for k, v in values.items() if all(Path(f).parent == Path(".") for f in v["files"])}
    assert local, "reference_values.json lists no pair inside the pair folder"
    missing = sorted({f for v in local.values() for f in v["files"] if not (PAIRS / f).is_file()})
    assert not missing, f"reference images missing: {missing}"
    for name, v in local.items():
        assert len(v["files"]) == 2, name
        assert 0 < v["ssim_wang_gaussian_sigma1.5_popcov"] <= 1, name
    assert set(local) <= {p.id for p in _pairs()}
    cv2 = pytest.importorskip("cv2")
    for f in sorted({f for v in local.values() for f in v["files"]}):
        assert cv2.imread(str(PAIRS / f), cv2.IMREAD_UNCHANGED) is not None, f"cannot read {f}"


def test_ssim_identity_shapes_and_batch():
    x = torch.rand(2, 20, 24, 3)
    assert float(ssim(x, x)) == pytest.approx(1.0, abs=1e-6)
    assert ssim(x, x, reduction="none").shape == (2, 20, 24, 3)
    assert ssim(x, x, padding="valid", reduction="none").shape == (2, 10, 14, 3)


def _ssim_conv2d(x, y, padding, window_size=11, sigma=1.5):
    """The SSIM map with the textbook conv2d blur: the reference for the matrix-product form."""
    import torch.nn.functional as F

    H, W, C = x.shape[-3:]
    g = torch.arange(window_size, dtype=torch.float64) - (window_size - 1) / 2
    g = torch.exp(-g * g / (2 * sigma * sigma))
    g = (g / g.sum()).to(x)
    pad = window_size // 2 if padding == "same" else 0

    def blur(t):
        t = F.conv2d(t, g.view(1, 1, -1, 1), padding=(pad, 0))
        return F.conv2d(t, g.view(1, 1, 1, -1), padding=(0, pad))

    a, b = (t.reshape(-1, H, W, C).permute(0, 3, 1, 2).reshape(-1, 1, H, W) for t in (x, y))
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a ** 2, blur(b * b) - mu_b ** 2, blur(a * b) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + 1e-4) * (2 * cov + 9e-4)
         / ((mu_a ** 2 + mu_b ** 2 + 1e-4) * (var_a + var_b + 9e-4)))
    h2, w2 = s.shape[-2:]
    return s.reshape(-1, C, h2, w2).permute(0, 2, 3, 1).reshape(*x.shape[:-3], h2, w2, C)


@pytest.mark.parametrize("shape", [(17, 29, 3), (2, 90, 160, 3), (12, 700, 1), (600, 13, 2)])
@pytest.mark.parametrize("padding", ["same", "valid"])
def test_matrix_product_ssim_equals_the_conv2d_form(shape, padding):
    """Values and gradients, dense band matrices (short axes) and blocks (axes > 512 px)."""
    g = torch.Generator().manual_seed(1)
    x = torch.rand(shape, generator=g, dtype=torch.float64)
    y = (x + 0.2 * torch.randn(shape, generator=g, dtype=torch.float64)).requires_grad_(True)
    ref = _ssim_conv2d(x, y, padding)
    got = ssim(x, y, padding=padding, reduction="none")
    assert got.shape == ref.shape
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-12)
    w = torch.rand(ref.shape, generator=g, dtype=torch.float64)
    (gr,) = torch.autograd.grad((ref * w).sum(), y)
    (gg,) = torch.autograd.grad((got * w).sum(), y)
    torch.testing.assert_close(gg, gr, rtol=0, atol=1e-12)
    x32, y32 = x.float(), y.detach().float()  # float32, the training dtype: float tolerance
    torch.testing.assert_close(ssim(x32, y32, padding=padding), ref.mean().float(),
                               rtol=0, atol=2e-6)


def test_ssim_rejects_images_smaller_than_the_window():
    with pytest.raises(ValueError):
        ssim(torch.rand(8, 30, 3), torch.rand(8, 30, 3), padding="valid")


def test_reconstruction_loss_is_computed_in_unbounded_srgb():
    t = torch.full((16, 16, 3), 0.2)
    p = torch.full((16, 16, 3), 0.3)
    loss, parts = reconstruction_loss(p, t)
    l1 = float((srgb_encode_unbounded(p) - srgb_encode_unbounded(t)).abs().mean())
    assert parts["l1"] == pytest.approx(l1, rel=1e-6)
    assert float(loss) == pytest.approx(0.8 * l1 + 0.2 * (1 - parts["ssim"]), rel=1e-6)


def test_hdr_targets_give_finite_loss_and_gradients():
    t = torch.logspace(-6, np.log10(65504), 16 * 16 * 3).reshape(16, 16, 3)
    p = torch.zeros(16, 16, 3, requires_grad=True)
    loss, _ = reconstruction_loss(p, t)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(p.grad).all()


def test_grid_regulariser_weights():
    E = torch.full((2, 3, 4, 4), 1.1)
    B = torch.full((3, 4, 4), 0.02)
    loss, parts = grid_regularisers(E, B)
    assert float(loss) == pytest.approx(10 * 0.01 - 0.05 * 0.02, rel=1e-5)
