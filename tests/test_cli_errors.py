"""A failure of the `volcap` command reads as one line: the cause, on stderr, last, exit code 1.

The real command in a subprocess, on a damaged EXR (whose decoder prints its own diagnostics on
fd 2), a missing ref and a refused production spec: stderr is exactly one line naming the file or
ref; with --verbose the traceback comes first. flows/cli_output.py states the contract.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from flows.cli_output import CliOutput, CommandError, is_expected, one_line
from volcap_core.native_stderr import detail_for

REPO = Path(__file__).resolve().parents[1]
#: A real damaged file whose decode makes OpenEXR print 11 lines of its own on fd 2.
CHATTY = REPO.parent / "shared" / "data" / "exr" / "Damaged" / \
    "asan_heap-oob_7f171b7ab3a2_937_b4e2415c399c2ab39548de911223769d_exr"


def cli_env(**extra: str) -> dict[str, str]:
    """The command's own defaults (INFO logs, as a coordinator runs it), not the test session's."""
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_LOGGING_LEVEL", "PREFECT_API_URL")}
    return {**env, **extra}


@pytest.fixture
def api_env(prefect_api):
    """Subprocesses talk to the session's temporary Prefect server instead of starting their own."""
    from prefect.settings import PREFECT_API_URL

    return cli_env(PREFECT_API_URL=PREFECT_API_URL.value())


def volcap(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "flows.cli", *args], capture_output=True, text=True,
                          env=env or os.environ.copy(), cwd=REPO, timeout=600)


def one_error_line(res: subprocess.CompletedProcess) -> str:
    """Exit code 1 and stderr exactly one non-empty line ``volcap: error: ...``; that line."""
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert res.returncode == 1, res.stderr[-3000:]
    assert len(lines) == 1, res.stderr[-3000:]
    assert lines[0].startswith("volcap: error: "), lines[0]
    return lines[0]


def damaged_capture(root: Path) -> Path:
    """One camera, one frame: a copy of the chatty damaged EXR, the rig sized to its header so that
    ingest refuses it only when decoding its pixels (the native library's diagnostics)."""
    from volcap_core.imageio.read import probe_image

    info = probe_image(CHATTY)
    x0, y0, x1, y1 = getattr(info, "display_window", None) or (0, 0, info.width - 1, info.height - 1)
    (root / "C0").mkdir(parents=True)
    shutil.copyfile(CHATTY, root / "C0" / "000000.exr")
    rig = {"name": "damaged", "kind": "scene", "fps": 24.0, "stage_size_m": [6.0, 8.0, 4.0],
           "lighting": {"description": "test"},
           "cameras": [{"id": "C0", "role": "static", "lens": {"focal_min_mm": 14.0, "focal_max_mm": 42.0},
                        "sensor": {"width_mm": 24.0, "height_mm": 18.0, "width_px": x1 - x0 + 1,
                                   "height_px": y1 - y0 + 1},
                        "mount": {"kind": "tripod", "position_m": [3.0, 0.0, 1.5], "look_at_m": [0.0, 0.0, 1.0]},
                        "nominal_focal_mm": 20.0}]}
    (root / "rig.json").write_text(json.dumps(rig))
    desc = {"format": "volcap-capture/1", "name": "damaged", "rig": "rig.json", "fps": 24,
            "take": {"start_timecode": "01:00:00:00", "frame_count": 1},
            "cameras": [{"id": "C0", "path": "C0", "start_timecode": "01:00:00:00", "encoding": "linear"}]}
    (root / "capture.json").write_text(json.dumps(desc))
    return root


@pytest.mark.skipif(not CHATTY.is_file(), reason=f"needs {CHATTY} (absent without ../shared)")
def test_damaged_exr_is_one_line_with_the_decoders_words_and_verbose_shows_the_traceback(api_env, tmp_path):
    cap = damaged_capture(tmp_path / "cap")
    frame = cap / "C0" / "000000.exr"
    store = str(tmp_path / "store")
    res = volcap("ingest", str(cap), "--store", store, "--json", env=api_env)
    line = one_error_line(res)
    assert f"camera C0, frame 0: {frame}: damaged EXR" in line
    # OpenEXR's own line about that file, folded in (it printed 11 of them on fd 2)
    assert "(decoder: (EXR_ERR_" in line and "EXR_ERR_" not in res.stdout
    # stdout: what ran (the failed task's line as progress, the summary); no traceback there either
    assert "failed: " in res.stdout and "Traceback" not in res.stdout
    assert "Task run failed with exception" not in res.stdout

    verbose = volcap("--verbose", "ingest", str(cap), "--store", store, env=api_env)
    assert verbose.returncode == 1
    err = verbose.stderr.strip().splitlines()
    assert "Traceback (most recent call last):" in verbose.stderr and "IngestError" in verbose.stderr
    assert err[-1].startswith("volcap: error: ") and str(frame) in err[-1]
    assert "nanobind" not in verbose.stderr  # the failed decode's objects are released before exit
    assert "Task run failed with exception" in verbose.stdout  # the demoted Prefect log, at DEBUG


def test_missing_ref_is_one_line_naming_the_ref(tmp_path):
    store = str(tmp_path / "store")
    res = volcap("render", "captures/nope", "--camera", "C0", "--time", "0", "--out", str(tmp_path / "x.exr"),
                 "--store", store)
    assert "'captures/nope'" in one_error_line(res) and res.stdout == ""
    verbose = volcap("render", "captures/nope", "--camera", "C0", "--time", "0", "--out",
                     str(tmp_path / "x.exr"), "--store", store, "--verbose")
    assert "Traceback (most recent call last):" in verbose.stderr and "MissingRefError" in verbose.stderr
    assert verbose.stderr.strip().splitlines()[-1] == one_error_line(res)


@pytest.mark.parametrize("api", ["session", "temporary"])
def test_refused_spec_in_a_flow_is_one_line_naming_the_file(api, request, tmp_path):
    # "temporary": no PREFECT_API_URL, the command starts (and at exit stops) its own Prefect API,
    # whose start and stop messages must not reach stderr either
    env = request.getfixturevalue("api_env") if api == "session" else cli_env()
    spec = tmp_path / "bad-spec.yaml"
    spec.write_text(textwrap.dedent(f"""\
        name: broken
        store: {tmp_path / 'store'}
        captures: {{}}
        shots: 3
        """))
    res = volcap("run", str(spec), env=env)  # loaded inside the production flow: Prefect logs it
    line = one_error_line(res)
    assert f"{spec}: invalid production spec:" in line and "shots" in line
    assert "Traceback" not in res.stdout and "failed: " in res.stdout


def test_report_classifies_and_folds(capsys):
    out = CliOutput()
    assert out.report(CommandError("refused: x.yaml")) == 1
    assert capsys.readouterr().err == "volcap: error: refused: x.yaml\n"
    assert out.report(RuntimeError("a bug\nsecond line")) == 1
    assert capsys.readouterr().err == \
        "volcap: internal error: RuntimeError: a bug second line (volcap --verbose shows the traceback)\n"
    assert is_expected(ValueError()) and is_expected(FileNotFoundError()) and not is_expected(TypeError())
    assert one_line(ValueError("a.yaml: invalid:\n  one\n  two")) == "a.yaml: invalid: one two"

    captured = "/c/C0/1.exr: (EXR_ERR_CORRUPT_CHUNK) Unable to decompress\n/c/C0/1.exr: second\nother: x\n"
    assert detail_for("camera C0, frame 1: /c/C0/1.exr: damaged EXR", captured) == \
        "(EXR_ERR_CORRUPT_CHUNK) Unable to decompress"
    assert detail_for("camera C0, frame 2: /c/C0/2.exr: damaged EXR", captured) is None


def test_native_stderr_is_captured_and_python_stderr_is_not():
    code = textwrap.dedent("""
        import os, subprocess, sys
        from volcap_core.native_stderr import NativeStderr
        n = NativeStderr().start()
        os.write(2, b"native: chatter\\n")
        subprocess.run([sys.executable, "-c", "import os; os.write(2, b'child: chatter\\\\n')"])
        print("python stderr", file=sys.stderr)
        got = n.read_new()
        n.stop()
        os.write(2, b"after stop\\n")
        print(repr(got))
    """)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert res.returncode == 0, res.stderr
    assert res.stderr == "python stderr\nafter stop\n"
    assert res.stdout.strip() == repr("native: chatter\nchild: chatter\n")
