"""The production journal: what each step of a production last ran on, so a plan can say why.

The task cache (``docs/tasks.md``) decides what actually recomputes; it knows *that* a key is new,
not *why*. After every step, the production flow writes a :class:`StepEntry` — the step's
fingerprint (its parameters, the digests of the outputs of the steps it reads, the versions of the
tasks it runs, for an ingest the folder's file listing) and its outputs — under the ref
``productions/<production>/steps/<step id>``. ``volcap plan`` recomputes each fingerprint and
compares: equal with every output still stored means cached; otherwise the first difference is the
reason (``never run``, ``task train-segment version 1 -> 2``, ``parameter train_steps changed``,
``input calibrate-static:cap changed``, ``output missing from the store``).

A fingerprint holds digests of two sorts: objects in the store (a capture record a calibration read)
and digests of things never stored (a folder listing, a step's outputs taken together, a weights
directory's stat fingerprint). The store follows every ``blake3:`` digest a record mentions (its gc
keeps them, ``volcap store verify`` wants them present), so the entry writes the second sort as
``blake3-fingerprint:<hex>``: not a reference, so never reported as a missing object, while every
digest that names a stored object stays a reference gc keeps. :func:`read_entry` gives the
fingerprint back in its ``blake3:`` form, the form :func:`compare_fingerprints` compares.

Pure store I/O, no Prefect.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, ClassVar

from volcap_core.digest import digest_bytes
from volcap_core.records import DIGEST_RE, ArtifactRef, Record, canonical_json
from volcap_core.store import ArtifactStore, MissingRefError

__all__ = ["FINGERPRINT_PREFIX", "StepEntry", "compare_fingerprints", "folder_listing_digest", "read_entry",
           "step_ref_name", "write_entry"]

#: How a journal entry writes a fingerprint digest that names no stored object (module docstring).
FINGERPRINT_PREFIX = "blake3-fingerprint:"
_DIGEST_PREFIX = "blake3:"


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


def _map_strings(doc: Any, f) -> Any:
    """``doc`` (JSON) with every string value (not key) replaced by ``f(value)``."""
    if isinstance(doc, str):
        return f(doc)
    if isinstance(doc, dict):
        return {k: _map_strings(v, f) for k, v in doc.items()}
    if isinstance(doc, list):
        return [_map_strings(v, f) for v in doc]
    return doc


def _digest_values(doc: Any) -> set[str]:
    found: set[str] = set()
    _map_strings(doc, lambda v: found.add(v) if DIGEST_RE.match(v) else None)
    return found


def _as_digest(value: str) -> str:
    """A ``blake3-fingerprint:`` value back in the ``blake3:`` form; any other string as it is."""
    return _DIGEST_PREFIX + value[len(FINGERPRINT_PREFIX):] if value.startswith(FINGERPRINT_PREFIX) else value


def read_entry(store: ArtifactStore, production: str, step_id: str) -> StepEntry | None:
    """The step's last entry, its fingerprint in the ``blake3:`` form it was computed in (an entry
    written before fingerprint digests had their own form reads the same)."""
    try:
        entry = store.get_record(store.get_ref(step_ref_name(production, step_id)), StepEntry)
    except MissingRefError:
        return None
    return entry.model_copy(update={"fingerprint": _map_strings(entry.fingerprint, _as_digest)})


def write_entry(store: ArtifactStore, production: str, step_id: str, fingerprint: dict[str, Any],
                outputs: dict[str, ArtifactRef]) -> ArtifactRef:
    """Journal a finished step. A digest value of ``fingerprint`` that names no stored object is
    written as ``blake3-fingerprint:<hex>`` (module docstring); one that names an object stays a
    reference, so gc keeps what a step read."""
    unstored = set(store.missing(_digest_values(fingerprint)))
    fingerprint = _map_strings(fingerprint, lambda v: FINGERPRINT_PREFIX + v[len(_DIGEST_PREFIX):]
                               if v in unstored else v)
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
