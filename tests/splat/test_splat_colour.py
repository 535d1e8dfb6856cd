"""sRGB transfer functions: the IEC curve as colour-science computes it, exact inverses, and the
unbounded extension the trainer relies on (finite gradients everywhere, HDR preserved)."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from volcap_core.colour import (
    srgb_decode,
    srgb_decode_unbounded,
    srgb_encode,
    srgb_encode_unbounded,
)

REF = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "reference" / \
    "srgb_colour_science_reference.json"


@pytest.fixture(scope="module")
def ref():
    if not REF.exists():
        pytest.skip(f"shared reference data absent ({REF})")
    return json.loads(REF.read_text())


@pytest.mark.parametrize("fn_enc,fn_dec", [(srgb_encode, srgb_decode),
                                           (srgb_encode_unbounded, srgb_decode_unbounded)])
def test_matches_colour_science_grid_and_breakpoints(ref, fn_enc, fn_dec):
    for block in ("grid_linspace_0_1_1025", "special_points"):
        x = torch.tensor(ref[block]["x"], dtype=torch.float64)
        np.testing.assert_allclose(fn_dec(x).numpy(), ref[block]["eotf"], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(fn_enc(x).numpy(), ref[block]["eotf_inverse"], rtol=1e-12,
                                   atol=1e-15)


def test_uint8_codes_decode_like_reference(ref):
    codes = np.arange(256, dtype=np.float64) / 255.0
    np.testing.assert_allclose(srgb_decode(codes), ref["uint8_code_to_linear"], rtol=1e-12)
    # ingest's call: float32 numpy -> torch
    out = srgb_decode(torch.from_numpy(codes.astype(np.float32)))
    assert out.dtype == torch.float32
    np.testing.assert_allclose(out.numpy(), ref["uint8_code_to_linear"], rtol=2e-6, atol=1e-9)


def test_round_trips():
    x = torch.linspace(0, 1, 4097, dtype=torch.float64)
    torch.testing.assert_close(srgb_decode(srgb_encode(x)), x, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(srgb_encode(srgb_decode(x)), x, rtol=1e-12, atol=1e-15)
    wide = torch.cat([-torch.logspace(-8, 3, 200, dtype=torch.float64), torch.zeros(1),
                      torch.logspace(-8, 4.82, 400, dtype=torch.float64)])
    torch.testing.assert_close(srgb_decode_unbounded(srgb_encode_unbounded(wide)), wide,
                               rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(srgb_encode_unbounded(srgb_decode_unbounded(wide)), wide,
                               rtol=1e-12, atol=1e-15)


def test_unbounded_keeps_hdr_and_continues_linear_segment_below_zero():
    assert float(srgb_decode_unbounded(torch.tensor(2.0))) > 4.0  # no clamp above 1
    assert abs(float(srgb_encode_unbounded(torch.tensor(65504.0))) - 107.10) < 0.01
    neg = torch.tensor([-1.0, -1e-3])
    torch.testing.assert_close(srgb_decode_unbounded(neg), neg / 12.92)
    torch.testing.assert_close(srgb_encode_unbounded(neg), neg * 12.92)
    # the bounded pair clamps
    assert float(srgb_encode(torch.tensor(3.0))) == pytest.approx(1.0, abs=1e-6)
    assert float(srgb_decode(torch.tensor(-1.0))) == 0.0


@pytest.mark.parametrize("fn", [srgb_encode_unbounded, srgb_decode_unbounded])
def test_unbounded_gradients_finite_everywhere_including_zero(fn):
    x = torch.tensor([-1e4, -1.0, -1e-30, 0.0, 1e-30, 1e-6, 0.0031308, 0.04045, 1.0, 65504.0],
                     requires_grad=True)
    fn(x).sum().backward()
    assert torch.isfinite(x.grad).all() and (x.grad > 0).all()


def test_numpy_in_numpy_out_and_dtypes():
    a = np.linspace(0, 1, 5, dtype=np.float32)
    assert isinstance(srgb_encode(a), np.ndarray) and srgb_encode(a).dtype == np.float32
    h = torch.linspace(0, 1, 5, dtype=torch.float16)
    assert srgb_decode(h).dtype == torch.float16
    with pytest.raises(TypeError):
        srgb_decode(np.arange(3, dtype=np.uint8))


def test_the_srgb_slope_is_the_derivative_of_the_clamped_encoding():
    """``srgb_encode_and_slope`` feeds the scoring fit's Gauss-Newton steps: a wrong slope would
    stop the fit short of the best gain and offset, and every held-out figure with it."""
    import torch

    from volcap_core.colour import srgb_encode, srgb_encode_and_slope

    x = torch.cat([torch.linspace(-0.5, 1.5, 2001, dtype=torch.float64),
                   torch.tensor([0.001, 0.0031308 * 0.5, 0.5, 0.999], dtype=torch.float64)])
    x = x[(x - 0.0031308).abs() > 1e-6]            # the curve has a kink at the break: no derivative there
    x = x[((x - 0.0).abs() > 1e-6) & ((x - 1.0).abs() > 1e-6)]
    enc, slope = srgb_encode_and_slope(x)
    assert torch.equal(enc, srgb_encode(x))
    xg = x.clone().requires_grad_(True)
    srgb_encode(xg).sum().backward()
    assert torch.allclose(slope, xg.grad, rtol=1e-9, atol=1e-12)
    assert (slope[(x < 0) | (x > 1)] == 0).all()   # the clamp holds the encoding still there
