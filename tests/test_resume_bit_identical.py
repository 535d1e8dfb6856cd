"""A segment whose worker dies (SIGKILL right after a checkpoint) and is resumed by a fresh process
ends with the same model and grids bytes as an uninterrupted run (CPU).

Each training runs ``train_segment_task``'s body in its own Python process (``python THIS_FILE``),
as a retry on another worker would: nothing is shared with the killed process but the store.
Outside Prefect there is no task-run context, so the checkpoint name (``current_run_key``) is
pinned to a constant and the run logger is a plain logger; everything else is the task's code.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CAMERAS = ["S000", "S001", "S002", "S003", "S004", "S005", "S008"]
TIMING = {"wall_s"}  # record fields that measure time, not content


def _config():
    from volcap_core.production.presets import PRESETS
    from volcap_core.splat.mcmc import MCMCConfig

    # MCMC relocation and growth on both sides of the checkpoint at step 4
    return PRESETS["test"].train_config(held_out=["S002"], max_gaussians=1500, steps=8, checkpoint_every=4,
                                        eval_max_views=1,
                                        mcmc=MCMCConfig(refine_start=2, refine_every=2, refine_stop=8, cap_max=1600))


def _worker(mode: str, store: str, refs_file: str) -> None:
    """Body of one subprocess: ``clean``, ``die`` (SIGKILL after the first checkpoint) or ``resume``."""
    import logging

    import tasks.reconstruct as rt
    import volcap_core.segment as segment_lib
    from volcap_core import reconstruction
    from volcap_core.records import ArtifactRef
    from volcap_core.store import ArtifactStore

    refs = json.loads(Path(refs_file).read_text())
    rt.current_run_key = lambda: "resume-test-segment"
    rt.get_run_logger = lambda: logging.getLogger("resume-test")
    real = segment_lib.train_segment
    seen = {}

    def wrapped(*args, checkpoint=None, resume_from=None, **kw):
        seen["resumed"] = resume_from is not None
        if mode == "die":
            def checkpoint_then_die(blob, step):
                checkpoint(blob, step)
                os.kill(os.getpid(), signal.SIGKILL)
            return real(*args, checkpoint=checkpoint_then_die, resume_from=resume_from, **kw)
        return real(*args, checkpoint=checkpoint, resume_from=resume_from, **kw)

    segment_lib.train_segment = wrapped
    ref = rt.train_segment_task.fn(store, *(ArtifactRef(**refs[k]) for k in ("capture", "calibration", "points")),
                                   [0, 2], _config(), 7)
    s = ArtifactStore(store)
    rec = s.get_record(ref, reconstruction.SegmentModel)
    out = rec.model_dump(mode="json", exclude=TIMING)
    out["history"] = [{k: v for k, v in h.items() if k not in TIMING} for h in out["history"]]
    print(json.dumps({"resumed": seen["resumed"], "record": out,
                      "checkpoints_left": sorted(s.list_refs("checkpoints/"))}))


def _run(mode: str, store: str, refs_file: Path, *, expect_kill: bool = False) -> dict | None:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, __file__, mode, store, str(refs_file)], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=300)
    if expect_kill:
        assert proc.returncode == -signal.SIGKILL, proc.stderr[-3000:]
        return None
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_killed_worker_resumed_in_a_fresh_process_is_bit_identical(prefect_api, tmp_path):
    import tasks.reconstruct as rt
    from flows.ingest import ingest_flow
    from flows.runtime import run_flow
    from volcap_core.store import ArtifactStore
    from volcap_core.synth import synthesize_capture

    cap_dir = synthesize_capture(tmp_path / "cap", rig="demo_scene", seed=3, frames=2, cameras=CAMERAS,
                                 supersample=1, write_depth=True).parent
    store = ArtifactStore(str(tmp_path / "store")).url
    capture = run_flow(ingest_flow, store=store, capture_dir=str(cap_dir)).result
    calib = rt.ground_truth_calibration.fn(store, capture)
    points = rt.ground_truth_points.fn(store, capture, calib, 1500, 7)
    refs_file = tmp_path / "refs.json"
    refs_file.write_text(json.dumps({k: v.model_dump(mode="json") for k, v in
                                     (("capture", capture), ("calibration", calib), ("points", points))}))
    shutil.copytree(tmp_path / "store", tmp_path / "store2")
    store2 = ArtifactStore(str(tmp_path / "store2")).url

    clean = _run("clean", store, refs_file)
    assert clean["resumed"] is False

    _run("die", store2, refs_file, expect_kill=True)
    left = ArtifactStore(store2).list_refs("checkpoints/")
    assert list(left) == ["checkpoints/resume-test-segment"]  # the dead worker left its checkpoint

    resumed = _run("resume", store2, refs_file)
    assert resumed["resumed"] is True
    assert resumed["checkpoints_left"] == []
    a, b = clean["record"], resumed["record"]
    # trained to the end; MCMC grew it past its start (70 % of the 1600 cap = 1120)
    assert b["steps"] == 8 and b["gaussians"] > 1120
    assert b["model"] == a["model"]  # same digest: the model bytes are identical
    assert b["grids"] == a["grids"]
    assert b == a  # every other field too (PSNR, SSIM, history steps), timing aside


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    _worker(*sys.argv[1:4])
