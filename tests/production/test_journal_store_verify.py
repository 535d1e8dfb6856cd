"""A production's step journal and `volcap store verify` (issue 31's bug): fingerprint digests of
things never stored (a folder listing, a step's outputs taken together) are not references, so a
production's store verifies clean; a really missing object is still reported; gc keeps what a
step's fingerprint read; a journal written before (plain ``blake3:`` fingerprints) still plans as
cached.

~10 s (the Prefect harness and one tiny ingest); the journal-only tests well under a second.
"""

from __future__ import annotations

import json

import pytest
import yaml
from typer.testing import CliRunner

from flows.cli import app
from flows.production import STEP_KINDS, ProductionRun, open_production, plan_production, step_fingerprint
from volcap_core.production.journal import (FINGERPRINT_PREFIX, StepEntry, compare_fingerprints,
                                            folder_listing_digest, read_entry, step_ref_name, write_entry)
from volcap_core.store import ArtifactStore
from volcap_core.synth import synthesize_capture


def _fingerprint(s: ArtifactStore, folder) -> tuple[dict, str]:
    """A calibration-like fingerprint: an unstored outputs digest, a stored capture it read, and an
    ingest-like listing digest; returns it and the stored object's digest."""
    read = s.put_bytes(b"the capture record a step read").digest
    fp = {"kind": "calibrate-static", "versions": {"calibrate-static": {"version": 11}},
          "inputs": {"ingest:cap": "blake3:" + "ab" * 32}, "parameters": {"capture": "cap"},
          "source": read, "listing": folder_listing_digest(folder)}
    return fp, read


def test_fingerprint_digests_are_not_dangling_and_real_ones_are_kept(tmp_path):
    (tmp_path / "cap").mkdir()
    (tmp_path / "cap" / "capture.json").write_text("{}")
    s = ArtifactStore(str(tmp_path / "store"))
    fp, read = _fingerprint(s, tmp_path / "cap")
    out = s.put_bytes(b"the step's output")
    write_entry(s, "p", "calibrate-static:cap", fp, {"static": out})

    report = s.verify()
    assert report.ok and report.dangling == [], report.dangling
    raw = s.get_bytes(s.get_ref(step_ref_name("p", "calibrate-static:cap")).digest).decode()
    assert raw.count(FINGERPRINT_PREFIX) == 2 and read in raw   # the stored one stays a reference
    # the journal gives back the fingerprint it was given: nothing to rerun
    assert compare_fingerprints(read_entry(s, "p", "calibrate-static:cap").fingerprint, fp) is None
    # gc keeps what the step read and wrote, however old
    assert s.gc(grace_s=0).deleted == 0 and s.exists(read) and s.exists(out)

    # really missing objects are still reported: the output, and the object the fingerprint read
    s.fs.rm_file(s._object_path(out.digest))
    s.fs.rm_file(s._object_path(read))
    dangling = s.verify().dangling
    name = step_ref_name("p", "calibrate-static:cap")
    assert sorted(dangling) == sorted([f"{name} -> {out.digest}", f"{name} -> {read}"]), dangling


def test_a_journal_written_before_reads_as_cached(tmp_path):
    """An entry of the old form (every digest ``blake3:``) compares equal: a resume reruns nothing."""
    (tmp_path / "cap").mkdir()
    s = ArtifactStore(str(tmp_path / "store"))
    fp, _ = _fingerprint(s, tmp_path / "cap")
    old = s.put_record(StepEntry(production="p", step="ingest:cap", fingerprint=fp,
                                 outputs={"capture": s.put_bytes(b"x")}))
    s.set_ref(step_ref_name("p", "ingest:cap"), old)
    assert compare_fingerprints(read_entry(s, "p", "ingest:cap").fingerprint, fp) is None


@pytest.mark.usefixtures("prefect_api")
def test_a_productions_store_verifies_clean(tmp_path):
    """The reported case: an ingest step's journal holds its folder listing digest."""
    cap = synthesize_capture(tmp_path / "cap", rig="demo_scene", seed=0, frames=1, supersample=1,
                             cameras=["S000", "S001"], actors=1).parent
    store = ArtifactStore(str(tmp_path / "store")).url
    spec = tmp_path / "spec.yaml"
    spec.write_text(yaml.safe_dump({
        "format": "volcap-production/1", "name": "verify", "store": store, "quality": {"preset": "test"},
        "captures": {"demo": {"folder": str(cap)}},
        "shots": [{"name": "still", "performance": "demo", "frames": [0, 1], "fps": 24, "resolution": [32, 18],
                   "sensor_mm": 36, "keyframes": [{"frame": 0, "position": [5.0, 0.0, 1.8],
                                                   "look_at": [0.0, 0.0, 1.0], "focal_mm": 24}]}]}))
    prod = open_production(spec)
    [ingest] = [st for st in prod.steps if st.kind == "ingest"]
    assert step_fingerprint(prod, ingest, {})["source"].startswith("blake3:")   # the listing digest

    STEP_KINDS["ingest"].run(ProductionRun(prod, "local", 1, 0.1, None), [ingest])   # the flow's own step
    assert next(p for p in plan_production(open_production(spec)) if p.step.id == ingest.id).status == "cached"

    result = CliRunner().invoke(app, ["store", "verify", "--store", store, "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output.strip().splitlines()[-1])["dangling"] == []

    # a really missing object is reported, by the command too (exit 1)
    s = ArtifactStore(store)
    capture = read_entry(s, "verify", ingest.id).outputs["capture"].digest
    s.fs.rm_file(s._object_path(capture))
    result = CliRunner().invoke(app, ["store", "verify", "--store", store, "--json"])
    assert result.exit_code == 1
    assert f"{step_ref_name('verify', ingest.id)} -> {capture}" in json.loads(
        result.output.strip().splitlines()[-1])["dangling"]
