"""The demo: every stage that exists, run on the built-in synthetic capture.

Stages join this flow as they land (ingest now; calibration, Poly4DGS, the production flow later).
"""

from __future__ import annotations

from prefect import flow

from flows.ingest import ingest_flow


@flow(name="demo", persist_result=False)
def demo_flow(store: str, capture_dir: str) -> dict:
    """Ingest the demo capture; returns the references a coordinator would look at."""
    capture = ingest_flow(store=store, capture_dir=capture_dir)
    return {"capture": capture.model_dump(mode="json")}
