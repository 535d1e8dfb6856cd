"""Contact sheets: layout, the error panel's meaning, PNG round trip, refusals."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from volcap_core.contact_sheet import GAP, SheetRow, contact_sheet, encode_png, write_sheet

INFERNO_0 = cv2.applyColorMap(np.zeros((1, 1), np.uint8), cv2.COLORMAP_INFERNO)[0, 0, ::-1]  # RGB
INFERNO_255 = cv2.applyColorMap(np.full((1, 1), 255, np.uint8), cv2.COLORMAP_INFERNO)[0, 0, ::-1]


def _image(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A smooth linear-light image with some HDR and slightly negative values, [h, w, 3] float32."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    rng = np.random.default_rng(seed)
    img = np.stack([xx / w * 1.5, yy / h, 0.2 + 0.0 * xx], axis=-1) - 0.02
    return (img + rng.normal(0, 0.01, img.shape)).astype(np.float32)


def _error_panel(sheet: np.ndarray, row_top: int, panel_w: int, panel_h: int) -> np.ndarray:
    x0 = GAP + 2 * (panel_w + GAP)
    return sheet[row_top:row_top + panel_h, x0:x0 + panel_w]


def _panel_w(max_width: int) -> int:
    return (max_width - 4 * GAP) // 3


def _row_top(sheet: np.ndarray, panel_h: int) -> int:
    """Top of the (single) row's panels: the panel band is the last ``panel_h`` rows above the
    bottom margin."""
    return sheet.shape[0] - GAP - panel_h


def test_shape_dtype_and_determinism():
    rows = [SheetRow("S004 frame 4 held-out PSNR 23.1 dB", _image(90, 160), _image(90, 160, 1))]
    a = contact_sheet(rows, title="segment 0-8", max_width=1000)
    b = contact_sheet(rows, title="segment 0-8", max_width=1000)
    assert a.dtype == np.uint8 and a.ndim == 3 and a.shape[2] == 3
    assert a.shape[1] == 3 * _panel_w(1000) + 4 * GAP <= 1000
    assert np.array_equal(a, b)
    # a title adds a strip
    assert contact_sheet(rows, max_width=1000).shape[0] < a.shape[0]


def test_identical_output_gives_zero_error_panel():
    truth = _image(90, 160)
    truth[10, 10] = 7.5  # HDR: clamped for display, identical on both sides, so no error
    sheet = contact_sheet([SheetRow("same", truth, truth.copy())], max_width=600)
    pw = _panel_w(600)
    ph = round(90 * pw / 160)
    err = _error_panel(sheet, _row_top(sheet, ph), pw, ph)
    assert err.shape == (ph, pw, 3)
    assert (err == INFERNO_0).all()


def test_large_error_is_bright_and_localised():
    truth = _image(90, 160)
    output = truth.copy()
    output[30:60, 60:100] += 0.6  # a big wrong patch, centre of the image
    sheet = contact_sheet([SheetRow("patch", truth, output)], max_width=1600)
    pw = _panel_w(1600)
    ph = round(90 * pw / 160)
    err = _error_panel(sheet, _row_top(sheet, ph), pw, ph).astype(int)
    s = pw / 160  # upscaled with nearest neighbour
    inside = err[int(35 * s):int(55 * s), int(65 * s):int(95 * s)]
    outside = err[: int(20 * s), : int(40 * s)]
    assert (outside == INFERNO_0).all()
    assert inside.sum(axis=2).min() > 400  # orange-yellow, not dark purple
    # a difference of error_scale or more saturates the map
    sat = contact_sheet([SheetRow("sat", np.zeros((8, 8, 3)), np.ones((8, 8, 3)))], max_width=600)
    ph8 = _panel_w(600)
    assert (_error_panel(sat, _row_top(sat, ph8), ph8, ph8) == INFERNO_255).all()


def test_non_finite_pixels_show_as_maximal_error():
    truth = np.full((4, 4, 3), 0.18, np.float32)
    output = truth.copy()
    output[0, 0, 1] = np.nan
    sheet = contact_sheet([SheetRow("nan", truth, output)], max_width=4 * 3 + 4 * GAP + 3 * 4 * 9)
    pw = _panel_w(sheet.shape[1])
    err = _error_panel(sheet, _row_top(sheet, pw), pw, pw)
    assert (err[0, 0] == INFERNO_255).all() and (err[-1, -1] == INFERNO_0).all()


def test_mask_outline_is_drawn_on_the_error_panel():
    truth = _image(90, 160)
    mask = np.zeros((90, 160), np.float32)
    mask[20:70, 50:110] = 1.0
    sheet = contact_sheet([SheetRow("mask", truth, truth, mask)], max_width=600)
    pw = _panel_w(600)
    ph = round(90 * pw / 160)
    err = _error_panel(sheet, _row_top(sheet, ph), pw, ph)
    cyan = (err == np.array([0, 255, 255], np.uint8)).all(axis=2)
    assert cyan.sum() > 100
    ys, xs = np.nonzero(cyan)
    s = pw / 160
    assert abs(ys.min() - 20 * s) <= 2 and abs(xs.max() - 110 * s) <= 3


def test_mixed_sizes_share_the_panel_width():
    rows = [SheetRow("tiny", _image(90, 160), _image(90, 160, 1)),
            SheetRow("big", _image(540, 960), _image(540, 960, 2)),
            SheetRow("portrait", _image(200, 100), _image(200, 100, 3))]
    sheet = contact_sheet(rows, max_width=900)
    pw = _panel_w(900)
    assert sheet.shape[1] == 3 * pw + 4 * GAP
    # total height: header strip(s) + label strip per row + panel heights; the panels alone are
    # round(h * pw / w) tall, so the sheet must be at least that
    panels = sum(round(h * pw / w) for h, w in [(90, 160), (540, 960), (200, 100)])
    assert panels < sheet.shape[0] < panels + 4 * 40


def test_label_and_headers_are_drawn():
    rows = [SheetRow("S004 frame 4 held-out PSNR 23.1 dB", _image(90, 160), _image(90, 160))]
    sheet = contact_sheet(rows, max_width=900)
    pw = _panel_w(900)
    ph = round(90 * pw / 160)
    top = _row_top(sheet, ph)
    label_strip = sheet[top - 20:top - GAP]  # the row's label strip lies right above its panels
    assert len(np.unique(label_strip.reshape(-1, 3), axis=0)) > 2
    header = sheet[:GAP + 16]
    for k in range(3):  # one header per column
        col = header[:, GAP + k * (pw + GAP): GAP + k * (pw + GAP) + pw]
        assert col.max() > 150
    # different labels draw differently
    other = contact_sheet([SheetRow("S001 frame 0", rows[0].truth, rows[0].output)], max_width=900)
    assert not np.array_equal(sheet, other)


def test_png_round_trip(tmp_path):
    sheet = contact_sheet([SheetRow("png", _image(90, 160), _image(90, 160, 1))], title="t", max_width=700)
    data = encode_png(sheet)
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
    assert np.array_equal(decoded, sheet)
    path = tmp_path / "sheet.png"
    write_sheet(path, sheet)
    assert path.read_bytes() == data
    assert [p.name for p in tmp_path.iterdir()] == ["sheet.png"]  # no temporary file left behind
    assert np.array_equal(cv2.imread(str(path), cv2.IMREAD_COLOR)[:, :, ::-1], sheet)
    jpg = tmp_path / "sheet.jpg"           # pages embed JPEGs: a tenth of the size
    write_sheet(jpg, sheet)
    back = cv2.imread(str(jpg), cv2.IMREAD_COLOR)[:, :, ::-1]
    assert jpg.read_bytes()[:2] == b"\xff\xd8" and np.abs(back.astype(int) - sheet).mean() < 4


@pytest.mark.parametrize("rows, match", [
    ([], "at least one"),
    ([SheetRow("a", np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))], "same shape"),
    ([SheetRow("a", np.zeros((4, 4, 4)), np.zeros((4, 4, 4)))], r"\[H, W, 3\]"),
    ([SheetRow("a", np.zeros((4, 4)), np.zeros((4, 4)))], r"\[H, W, 3\]"),
    ([SheetRow("a", np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4, 3), np.uint8))], "float"),
    ([SheetRow("a", np.zeros((4, 4, 3)), np.zeros((4, 4, 3)), np.zeros((4, 5)))], "mask"),
    ([SheetRow("a", np.zeros((0, 4, 3)), np.zeros((0, 4, 3)))], "empty"),
])
def test_bad_inputs_raise(rows, match):
    with pytest.raises(ValueError, match=match):
        contact_sheet(rows)


def test_bad_parameters_and_png_inputs_raise():
    row = SheetRow("a", np.zeros((4, 4, 3)), np.zeros((4, 4, 3)))
    with pytest.raises(ValueError, match="error_scale"):
        contact_sheet([row], error_scale=0)
    with pytest.raises(ValueError, match="max_width"):
        contact_sheet([row], max_width=20)
    with pytest.raises(ValueError, match="uint8"):
        encode_png(np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ValueError, match="uint8"):
        encode_png(np.zeros((4, 4), np.uint8))
