"""The production journal: what each step of a production last ran on, so a plan can say why.

The task cache (``docs/tasks.md``) decides what actually recomputes; it knows *that* a key is new,
not *why*. After every step, the production flow writes a :class:`StepEntry` — the step's
fingerprint (its parameters, the digests of the outputs of the steps it reads, the versions of the
tasks it runs, for an ingest the folder's file listing) and its outputs — under the ref
``productions/<production>/steps/<step id>``. ``volcap plan`` recomputes each fingerprint and
compares: equal with every output still stored means cached; otherwise the first difference is the
reason (``never run``, ``task train-segment version 1 -> 2``, ``parameter train_steps changed``,
``input calibrate-static:cap changed``, ``output missing from the store``).

Pure store I/O, no Prefect.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, ClassVar

from volcap_core.digest import digest_bytes
from volcap_core.records import ArtifactRef, Record, canonical_json
from volcap_core.store import ArtifactStore, MissingRefError

__all__ = ["StepEntry", "compare_fingerprints", "folder_listing_digest", "read_entry", "step_ref_name",
           "write_entry"]


class StepEntry(Record):
    """One step's last completed run: its fingerprint and named outputs."""

    kind: ClassVar[str] = "production-step"
    production: str
    step: str
    fingerprint: dict[str, Any]
    outputs: dict[str, ArtifactRef]


def step_ref_name(production: str, step_id: str) -> str:
    """``productions/<production>/steps/<kind>/<subject...>`` (step ids use ``:``; refs use ``/``)."""
    parts = [re.sub(r"[^A-Za-z0-9._-]", "_", p) for p in step_id.split(":")]
    return "/".join(["productions", production, "steps", *parts])


def read_entry(store: ArtifactStore, production: str, step_id: str) -> StepEntry | None:
    try:
        return store.get_record(store.get_ref(step_ref_name(production, step_id)), StepEntry)
    except MissingRefError:
        return None


def write_entry(store: ArtifactStore, production: str, step_id: str, fingerprint: dict[str, Any],
                outputs: dict[str, ArtifactRef]) -> ArtifactRef:
    entry = StepEntry(production=production, step=step_id, fingerprint=fingerprint, outputs=outputs)
    ref = store.put_record(entry)
    store.set_ref(step_ref_name(production, step_id), ref)
    return ref


def folder_listing_digest(folder: str | Path) -> str:
    """Digest of every file's relative path, size and modification time under ``folder``: the
    cheap stand-in for its content that a plan can afford (ingest itself fingerprints content)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"capture folder {folder} does not exist")
    rows = []
    for root, dirs, files in os.walk(folder):
        dirs.sort()
        for name in sorted(files):
            p = Path(root) / name
            st = p.stat()
            rows.append([p.relative_to(folder).as_posix(), st.st_size, st.st_mtime_ns])
    return digest_bytes(canonical_json(rows))


def _identity_change(was: Any, now: Any) -> str:
    """A task identity's change in words (journals of older versions hold the version string)."""
    if not isinstance(was, dict) or not isinstance(now, dict):
        return f"version {was.get('version') if isinstance(was, dict) else was} -> " \
               f"{now.get('version') if isinstance(now, dict) else now}"
    if was.get("version") != now.get("version"):
        return f"version {was.get('version')} -> {now.get('version')}"
    libs_was, libs_now = was.get("libraries", {}), now.get("libraries", {})
    for lib in sorted(set(libs_was) | set(libs_now)):
        if libs_was.get(lib) != libs_now.get(lib):
            return f"library {lib} {libs_was.get(lib)} -> {libs_now.get(lib)}"
    for name in sorted(set(was.get("defaults", {})) | set(now.get("defaults", {}))):
        if canonical_json(was.get("defaults", {}).get(name)) != canonical_json(now.get("defaults", {}).get(name)):
            return f"default {name} changed"
    return "identity changed"


def compare_fingerprints(old: dict[str, Any], new: dict[str, Any]) -> str | None:
    """The first difference between a stored and a current fingerprint, in words; None if equal.

    Fingerprints have the keys ``versions`` (task -> its identity: ``{"version", "defaults",
    "libraries"}``, ``tasks.contract.task_identity``), ``inputs`` (step id -> output digest),
    ``parameters`` and optionally ``source`` (e.g. a folder listing digest).
    """
    for task, ident in sorted(new.get("versions", {}).items()):
        was = old.get("versions", {}).get(task)
        if was is None:
            return f"task {task} is new in this step"
        if was != ident:
            return f"task {task}: {_identity_change(was, ident)}"
    for step, digest in sorted(new.get("inputs", {}).items()):
        if old.get("inputs", {}).get(step) != digest:
            return f"input {step} changed"
    if old.get("source") != new.get("source"):
        return "source files changed"
    old_p, new_p = old.get("parameters", {}), new.get("parameters", {})
    for key in sorted(set(old_p) | set(new_p)):
        if canonical_json(old_p.get(key)) != canonical_json(new_p.get(key)):
            return f"parameter {key} changed"
    if canonical_json(old) != canonical_json(new):
        return "fingerprint changed"
    return None
