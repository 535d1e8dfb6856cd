"""The GPU machine's Python as the GPU benches' tests stand it in (``bench/gpu_*.py``): a lent GPU
has no Prefect, pycolmap, OpenCV or OpenImageIO, so a bench's ``--run`` part is tested in a process
where they cannot be imported, and its other parts are loaded from the script file
(:func:`load_bench`, which every bench script's tests use)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: what a lent GPU machine lacks (bench/gpu_checks.sh's header)
ABSENT = ("prefect", "pycolmap", "cv2", "OpenImageIO")


def load_bench(name: str):
    """``bench/<name>.py`` as a module."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "bench" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def run_without_absent(name: str, args: list[str], timeout_s: float = 600) -> subprocess.CompletedProcess:
    """``python bench/<name>.py ARGS`` from the repository root in a process where :data:`ABSENT`
    cannot be imported (``sys.modules[m] = None``)."""
    script = ROOT / "bench" / f"{name}.py"
    code = ("import sys, runpy\n"
            + "".join(f"sys.modules[{m!r}] = None\n" for m in ABSENT)
            + f"sys.argv = {[script.name, *map(str, args)]!r}\n"
            + f"runpy.run_path({str(script)!r}, run_name='__main__')\n")
    return subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=timeout_s)
