"""The truth flow: one shot of a production over a synthetic capture → its truth frames in the store.

    open      the production spec (flows/production.py open_production), the shot and its capture
    check     the capture is synthetic (its ground truth has scene.json): refused before anything runs
    ingest    a folder capture (cached: the production's own ingest, an unchanged folder costs nothing)
    truth     render-truth: every shot frame from the capture's stored ground truth
              (volcap_core/production/truth.py), a tree beside the shot's render frames, named
              ``productions/<production>/truth/<shot>``
"""

from __future__ import annotations

from pathlib import Path

from prefect import flow, get_run_logger

from flows.ingest import ingest_flow
from flows.production import Production, open_production
from tasks.production import render_shot_truth
from volcap_core.capture import Capture, CaptureFolder
from volcap_core.production.shot import Shot
from volcap_core.store import ArtifactStore
from volcap_core.synth.truth import SCENE_FILE

__all__ = ["truth_capture", "truth_flow", "truth_ref"]


def truth_ref(production: str, shot: str) -> str:
    """The store ref naming a shot's truth frames (beside ``productions/<name>/shots/<shot>``)."""
    return f"productions/{production}/truth/{shot}"


def truth_capture(prod: Production, shot: str, where: str | Path) -> tuple[Shot, str]:
    """The shot named ``shot`` and its capture's name in the spec, once the capture is known to be
    synthetic: ``ValueError`` ``<where>: shot S: capture X has no synthetic ground truth (...)``
    otherwise, before anything is ingested or rendered."""
    the_shot = prod.spec.shot(shot)
    name = the_shot.performance
    cs = prod.spec.captures[name]
    why = None
    if cs.folder is not None:
        folder = CaptureFolder.open(prod.folder(name))
        gt = folder.ground_truth_path
        if gt is None:
            why = f"{folder.description_path} names no ground_truth folder"
        elif not (gt / SCENE_FILE).is_file():
            why = f"no {gt / SCENE_FILE}"
    else:
        s = ArtifactStore(prod.store)
        record = s.get_record(s.resolve(cs.ref), Capture)
        if record.ground_truth is None:
            why = f"its record {cs.ref} carries no ground_truth tree"
        elif SCENE_FILE not in s.get_tree(record.ground_truth):
            why = f"its ground truth has no {SCENE_FILE}"
    if why is not None:
        raise ValueError(f"{where}: shot {shot}: capture {name} has no synthetic ground truth ({why}): "
                         "the truth is rendered only for synthetic captures (volcap synth)")
    return the_shot, name


@flow(name="truth", persist_result=False)
def truth_flow(spec: str, shot: str, store: str | None = None, supersample: int = 2) -> dict:
    """Render and store the truth of ``shot`` of the production spec at ``spec``; returns the
    production, shot, capture, the truth tree's digest, its ref name and the frame count."""
    log = get_run_logger()
    prod = open_production(spec, store, [shot])
    the_shot, capture_name = truth_capture(prod, shot, spec)
    s = ArtifactStore(prod.store)
    cs = prod.spec.captures[capture_name]
    capture = (ingest_flow(store=prod.store, capture_dir=str(prod.folder(capture_name))) if cs.folder is not None
               else s.resolve(cs.ref))
    frames = render_shot_truth(prod.store, capture, the_shot.model_dump(mode="json"), supersample)
    ref = truth_ref(prod.spec.name, shot)
    s.set_ref(ref, frames)
    count = len(s.get_tree(frames))
    log.info("shot %s: truth of %d frame(s) from capture %s -> %s", shot, count, capture_name, frames.digest)
    return {"production": prod.spec.name, "store": prod.store, "shot": shot, "capture": capture.digest,
            "truth": frames.digest, "ref": ref, "frames": count}
