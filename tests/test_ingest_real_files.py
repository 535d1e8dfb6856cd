"""Ingest's per-frame path on the real openexr-images collection (../shared/data).

Every readable single-picture RGB(A)/luminance EXR converts to a linear half EXR holding the same
values (clamped to the half range), placed in its display window and converted to the working
primaries when its ``chromaticities`` say otherwise; multi-part and multi-view files without a
chosen part/view, and every damaged or broken file, are refused with an IngestError naming the
camera and frame. Runs in one child process so a decoder crash fails a test rather than the whole
run. The expected pixels are built here from ``read_image`` (data window, as stored), the OpenEXR
bindings' header and index arithmetic, not from ingest's own window/colour helpers.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
EXR = REPO.parent / "shared" / "data" / "exr"
pytestmark = pytest.mark.skipif(not EXR.is_dir(), reason=f"needs {EXR} (absent without ../shared)")

CHILD = textwrap.dedent(r"""
    import json, re, sys
    from pathlib import Path
    import numpy as np
    import OpenEXR
    sys.path.insert(0, sys.argv[2])
    from volcap_core.capture import CameraSource, IngestError
    from volcap_core.chromaticities import Chromaticities, REC709_D65, to_working_matrix
    from volcap_core.digest import digest_file
    from volcap_core.imageio.read import decode_exr, read_image
    from volcap_core.ingest import RawFrame, convert_frame

    def expected_frame(p):
        src, _ = read_image(p)  # data window, values as stored, default view of part 0
        src = np.nan_to_num(src, nan=0.0, posinf=65504.0, neginf=-65504.0)
        header = OpenEXR.File(str(p), header_only=True).header(0)
        (dx0, dy0), (dx1, dy1) = (tuple(int(v) for v in a) for a in header["dataWindow"])
        (px0, py0), (px1, py1) = (tuple(int(v) for v in a) for a in header["displayWindow"])
        chroma = header.get("chromaticities")
        neutral = header.get("adoptedNeutral")
        names = {c.name for c in header["channels"]}
        luminance_only = "Y" in names and "RY" not in names and "R" not in names
        converted = False
        if not luminance_only and (neutral is not None or (chroma is not None and not np.allclose(chroma, REC709_D65, atol=2e-4))):
            m = to_working_matrix(Chromaticities(*(chroma or REC709_D65)),
                                  None if neutral is None else tuple(float(v) for v in neutral))
            rgb = (np.clip(src[..., :3], -65504, 65504).astype(np.float64) @ m.T).astype(np.float32)
            src = np.concatenate([rgb, src[..., 3:]], axis=-1)
            converted = True
        # display-window canvas: display pixel (x, y) is data pixel (x - dx0, y - dy0) where it
        # exists, 0 elsewhere (alpha too)
        ys, xs = np.arange(py0, py1 + 1), np.arange(px0, px1 + 1)
        iy, ix = np.flatnonzero((ys >= dy0) & (ys <= dy1)), np.flatnonzero((xs >= dx0) & (xs <= dx1))
        out = np.zeros((len(ys), len(xs), src.shape[-1]), np.float32)
        out[np.ix_(iy, ix)] = src[np.ix_(ys[iy] - dy0, xs[ix] - dx0)]
        return np.clip(out, -65504, 65504).astype(np.float16).astype(np.float32), converted

    exr = Path(sys.argv[1])
    broken = re.compile(r"comp_(bad_.*|early_eof_.*|short_decode_.*|invalid_unknown)\.exr$")
    cam = CameraSource(id="CAM7", path="x", start_timecode="00:00:00:00")
    out = {"good": {}, "damaged": {}}
    for p in sorted(exr.rglob("*")):
        if not p.is_file() or p.suffix in (".rst", ".md", "") and "Damaged" not in p.parts:
            continue
        if p.name in ("LICENSE", "COPYING", "README.md"):
            continue
        damaged = "Damaged" in p.parts or bool(broken.search(p.name))
        frame = RawFrame(take_index=3, camera_frame=3, path=p)
        key = str(p.relative_to(exr))
        try:
            data, repaired = convert_frame(frame, digest_file(p)[0], cam, ocio_config=None,
                                           nan_policy="repair", want_alpha=False)
            px, ch = decode_exr(data)
            expected, converted = expected_frame(p)
            same = px.shape == expected.shape and bool(np.array_equal(px, expected))
            # converted files: OpenColorIO's float32 matrix against numpy's float64, then half rounding
            close = px.shape == expected.shape and bool(np.allclose(px, expected, rtol=2e-3, atol=1e-4))
            out["damaged" if damaged else "good"][key] = {"ok": True, "same": same, "close": close,
                                                          "converted": converted}
        except IngestError as exc:
            out["damaged" if damaged else "good"][key] = {"ok": False, "error": str(exc)}
        except Exception as exc:
            out["damaged" if damaged else "good"][key] = {"ok": False, "error": f"UNEXPECTED {type(exc).__name__}: {exc}"}
    print(json.dumps(out))
""")


@pytest.fixture(scope="module")
def results() -> dict:
    proc = subprocess.run([sys.executable, "-c", CHILD, str(EXR), str(REPO)], capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_every_damaged_file_is_refused_naming_camera_and_frame(results):
    assert len(results["damaged"]) >= 90
    for name, r in results["damaged"].items():
        assert not r["ok"], f"{name} was accepted"
        assert r["error"].startswith(f"camera CAM7, frame 3: {EXR / name}: "), f"{name}: {r['error']}"
        assert "UNEXPECTED" not in r["error"], f"{name}: {r['error']}"


def test_every_readable_rgb_exr_converts_to_the_same_values_in_half(results):
    good = results["good"]
    converted = {n: r for n, r in good.items() if r["ok"]}
    refused = {n: r["error"] for n, r in good.items() if not r["ok"]}
    # Files without colour (depth-only parts, deep data) are refused by name, never crash; files
    # holding several parts or views are refused until capture.json chooses one.
    for name, err in refused.items():
        assert "UNEXPECTED" not in err, f"{name}: {err}"
        assert err.startswith(f"camera CAM7, frame 3: {EXR / name}: "), f"{name}: {err}"
        assert ("no R,G,B" in err or "deep" in err.lower() or "no part or view was chosen" in err), f"{name}: {err}"
    ambiguous = {n for n, e in refused.items() if "no part or view was chosen" in e}
    assert ambiguous == {"Beachball/multipart.0001.exr", "Beachball/multipart.0002.exr",
                         "Beachball/singlepart.0001.exr"}
    assert len(converted) >= 45
    for name, r in converted.items():
        if r["converted"]:
            assert r["close"], f"{name}: stored pixels differ from the source converted to the working primaries"
        else:
            assert r["same"], f"{name}: stored half pixels differ from the decoded source in its display window"
    # the files whose chromaticities are not Rec.709 (XYZ, ACES AP0 with an adoptedNeutral, odd primaries)
    assert {n for n, r in converted.items() if r["converted"]} == {
        "Chromaticities/XYZ.exr", "Chromaticities/XYZ_YC.exr", "ScanLines/Carrots.exr", "ScanLines/Tree.exr"}
