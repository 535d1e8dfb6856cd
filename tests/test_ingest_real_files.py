"""Ingest's per-frame path on the real openexr-images collection (../shared/data).

Every readable RGB(A)/luminance EXR converts to a linear half EXR holding the same values (clamped to
the half range); every damaged or broken file is refused with an IngestError naming the camera and
frame. Runs in one child process so a decoder crash fails a test rather than the whole run.
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
    sys.path.insert(0, sys.argv[2])
    from volcap_core import imageio
    from volcap_core.capture import CameraSource
    from volcap_core.digest import digest_file
    from volcap_core.ingest import IngestError, RawFrame, convert_frame

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
            px, ch = imageio.decode_exr(data)
            src, _ = imageio.read_image(p)
            src = np.nan_to_num(src[..., :3], nan=0.0, posinf=65504.0, neginf=-65504.0)
            expected = np.clip(src, -65504, 65504).astype(np.float16).astype(np.float32)
            same = bool(np.array_equal(px[..., :3], expected))
            out["damaged" if damaged else "good"][key] = {"ok": True, "same": same}
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
    # Files without colour (depth-only parts, deep data) are refused by name, never crash.
    for name, err in refused.items():
        assert "UNEXPECTED" not in err, f"{name}: {err}"
        assert "no R,G,B" in err or "deep" in err.lower() or "channels" in err, f"{name}: {err}"
    assert len(converted) >= 45
    for name, r in converted.items():
        assert r["same"], f"{name}: stored half pixels differ from the decoded source"
