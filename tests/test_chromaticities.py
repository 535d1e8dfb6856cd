"""volcap_core.chromaticities: the working space and conversions into it, against OpenColorIO's
studio config (its matrices are built independently of ours) and the published sRGB matrix."""

from __future__ import annotations

import json

import numpy as np
import pytest

from volcap_core.chromaticities import (
    CIE_XYZ,
    REC709_D65,
    WORKING_CHROMATICITIES,
    Chromaticities,
    bradford_matrix,
    convert_to_working,
    needs_conversion,
    rgb_to_xyz_matrix,
    to_working_matrix,
)

AP0 = Chromaticities(0.7347, 0.2653, 0.0, 1.0, 0.0001, -0.0770, 0.32168, 0.33767)  # ACES2065-1
REC2020 = Chromaticities(0.708, 0.292, 0.170, 0.797, 0.131, 0.046, 0.3127, 0.3290)
P3_D65 = Chromaticities(0.680, 0.320, 0.265, 0.690, 0.150, 0.060, 0.3127, 0.3290)


def _ocio_matrix(source: str) -> np.ndarray:
    """The 3x3 the studio config applies from ``source`` to Linear Rec.709 (sRGB), read off by
    pushing the unit vectors through it."""
    import PyOpenColorIO as ocio

    config = ocio.Config.CreateFromBuiltinConfig("studio-config-latest")
    proc = config.getProcessor(source, "Linear Rec.709 (sRGB)").getDefaultCPUProcessor()
    return np.array([proc.applyRGB([float(v) for v in e]) for e in np.eye(3)]).T


def test_working_space_is_linear_rec709_d65():
    assert WORKING_CHROMATICITIES == REC709_D65 == (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)
    assert not needs_conversion(None)  # an EXR without the attribute is Rec.709/D65
    assert not needs_conversion(Chromaticities(*np.float32(REC709_D65)))  # as stored in a file
    assert not needs_conversion(REC709_D65._replace(white_x=0.31271, white_y=0.32902))  # 5-digit D65
    assert needs_conversion(P3_D65) and needs_conversion(CIE_XYZ)
    assert needs_conversion(None, adopted_neutral=(0.32168, 0.33767))  # Rec.709 primaries, D60 neutral


def test_rec709_to_xyz_is_the_published_srgb_matrix(shared_data):
    reference = json.loads((shared_data / "reference" / "srgb_colour_science_reference.json").read_text())
    # IEC 61966-2-1 publishes it to 4 digits
    np.testing.assert_allclose(rgb_to_xyz_matrix(REC709_D65), reference["sRGB_matrix_RGB_to_XYZ"], atol=1e-4)


@pytest.mark.parametrize("name, chroma", [("Linear Rec.2020", REC2020), ("Linear P3-D65", P3_D65)])
def test_same_white_gamuts_match_opencolorio(name, chroma):
    np.testing.assert_allclose(to_working_matrix(chroma), _ocio_matrix(name), atol=2e-6)


def test_aces_white_is_adapted_with_bradford_as_opencolorio_does():
    # AP0's white is ACES's ~D60: the studio config's matrix includes a Bradford adaptation to D65
    np.testing.assert_allclose(to_working_matrix(AP0), _ocio_matrix("ACES2065-1"), atol=2e-6)
    # without adaptation the ACES white would come out tinted, not grey
    white = to_working_matrix(AP0) @ np.ones(3)
    np.testing.assert_allclose(white, np.ones(3), atol=1e-5)


def test_bradford_maps_the_source_white_to_the_target_white():
    d60, d65 = (0.32168, 0.33767), (0.3127, 0.3290)

    def xyz(x, y):
        return np.array([x / y, 1.0, (1 - x - y) / y])

    np.testing.assert_allclose(bradford_matrix(d60, d65) @ xyz(*d60), xyz(*d65), atol=1e-12)
    np.testing.assert_allclose(bradford_matrix(d65, d65), np.eye(3), atol=1e-12)


def test_cie_xyz_is_converted_without_adaptation():
    # XYZ primaries with white E: the values are tristimulus values, so the matrix is plain XYZ -> RGB
    np.testing.assert_allclose(to_working_matrix(CIE_XYZ), np.linalg.inv(rgb_to_xyz_matrix(REC709_D65)), atol=1e-12)


def test_adopted_neutral_is_what_comes_out_grey():
    neutral = (0.3127, 0.3290)  # AP0 footage whose neutral is D65 (not AP0's own white)
    m = to_working_matrix(AP0, adopted_neutral=neutral)
    d65_in_ap0 = np.linalg.solve(rgb_to_xyz_matrix(AP0), np.array([0.3127 / 0.3290, 1.0, (1 - 0.3127 - 0.3290) / 0.3290]))
    np.testing.assert_allclose(m @ d65_in_ap0, np.ones(3), atol=1e-6)
    assert not np.allclose(m, to_working_matrix(AP0), atol=1e-3)


@pytest.mark.parametrize("chroma, reason", [
    (Chromaticities(0.2, 0.2, 0.4, 0.4, 0.6, 0.6, 0.3127, 0.3290), "collinear"),
    (Chromaticities(0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.0), "not a physical white"),
    (Chromaticities(0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.7, 0.29), "outside the primaries' triangle"),
    (Chromaticities(float("nan"), 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290), "NaN or Inf"),
])
def test_chromaticities_that_define_no_space_are_refused(chroma, reason):
    with pytest.raises(ValueError, match=reason):
        to_working_matrix(chroma)


def test_opencolorio_applies_the_matrix():
    rgb = np.random.default_rng(5).uniform(-1.0, 50.0, size=(7, 9, 3)).astype(np.float32)
    out = convert_to_working(rgb, P3_D65)
    assert out.dtype == np.float32 and out.shape == rgb.shape and out is not rgb
    np.testing.assert_allclose(out, rgb.astype(np.float64) @ to_working_matrix(P3_D65).T, rtol=1e-5, atol=1e-5)
