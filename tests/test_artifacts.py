"""UI artifacts: what a flow publishes is what the API serves back; outside a run nothing happens;
a failing API never fails the caller."""

from __future__ import annotations

import base64
import json
import logging
import re

import numpy as np
import pytest

import tasks.artifacts as fa
from tasks.artifacts import ProgressArtifact, artifact_key, publish_image, publish_markdown, publish_table
from volcap_core.contact_sheet import SheetRow, contact_sheet, encode_png


def _png() -> bytes:
    img = np.full((9, 16, 3), 0.18, np.float32)
    return encode_png(contact_sheet([SheetRow("S004 frame 4", img, img * 1.1)], max_width=300))


def test_artifact_key():
    assert artifact_key("segment", "0-8", "metrics") == "segment-0-8-metrics"
    assert artifact_key("Segment", "0:8", "PSNR (dB)") == "segment-0-8-psnr-db"
    assert artifact_key("--a__b  c--") == "a-b-c"
    assert artifact_key(artifact_key("x", "Y")) == "x-y"  # idempotent
    with pytest.raises(ValueError):
        artifact_key("", "::")


def test_outside_a_run_nothing_is_published(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("must not reach Prefect outside a run")

    for name in ("create_table_artifact", "create_markdown_artifact", "create_image_artifact",
                 "create_progress_artifact", "update_progress_artifact"):
        monkeypatch.setattr(fa._pa, name, boom)
    assert publish_table("k", [{"a": 1}], "d") is None
    assert publish_markdown("k", "# hi", "d") is None
    assert publish_image("k", _png(), "d") is None
    p = ProgressArtifact("k", "d")
    p.update(1, 2)
    p.update(2, 2)
    p.finish()
    assert p.artifact_id is None and not p.active


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def test_failures_are_logged_not_raised(monkeypatch):
    import httpx

    # a handler on the module's logger itself: Prefect's logging setup replaces root handlers,
    # where pytest's caplog listens
    records = _Records()
    logging.getLogger("tasks.artifacts").addHandler(records)

    def unreachable(*a, **k):
        raise httpx.ConnectError("All connection attempts failed")

    monkeypatch.setattr(fa, "_in_run", lambda: True)  # as if inside a run whose API went away
    for name in ("create_table_artifact", "create_markdown_artifact", "create_progress_artifact"):
        monkeypatch.setattr(fa._pa, name, unreachable)
    try:
        assert publish_table("k", [{"a": 1}], "d") is None
        assert publish_markdown("k", "x", "d") is None
        assert publish_image("k", _png(), "d") is None
        assert publish_image("k", b"not a png", "d") is None  # bad input: logged, not raised
        p = ProgressArtifact("k", "d")
        p.update(5, 5)
    finally:
        logging.getLogger("tasks.artifacts").removeHandler(records)
    assert p.artifact_id is None
    assert sum("ConnectError" in m for m in records.messages) == 4
    assert any("expects PNG or JPEG bytes" in m for m in records.messages)


def test_progress_is_throttled_and_always_ends_at_100(monkeypatch):
    sent: list[float] = []
    now = [0.0]
    monkeypatch.setattr(fa, "_in_run", lambda: True)
    monkeypatch.setattr(fa._pa, "create_progress_artifact", lambda progress, **k: sent.append(progress) or "id")
    monkeypatch.setattr(fa._pa, "update_progress_artifact", lambda artifact_id, progress, **k: sent.append(progress))
    p = ProgressArtifact("train", "d", clock=lambda: now[0])
    for step in range(1, 101):  # 100 steps, 0.05 s each: 5 s
        now[0] += 0.05
        p.update(step, 100)
    assert sent[0] == 0.0 and sent[-1] == 100.0
    assert 4 <= len(sent) - 2 <= 5  # at most one update per second between creation and the end
    p.update(100, 100)
    p.finish()
    assert sent.count(100.0) == 1 and not p.active


def test_artifacts_in_a_flow_run(prefect_api):
    from prefect import flow, task
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterFlowRunId
    from prefect.runtime import flow_run

    png = _png()

    @task
    def table_in_task() -> object:
        return publish_table(artifact_key("segment", "0:8", "metrics"),
                             [{"camera": "S004", "psnr": np.float32(23.1), "ssim": float("nan")},
                              {"camera": "S005", "psnr": float("inf"), "frames": np.arange(2)}],
                             "held-out metrics")

    @flow(persist_result=False)
    def publish_all() -> dict:
        ids = {"table": table_in_task(),
               "markdown": publish_markdown("notes", "# Segment 0-8\n\n*fine*", "notes"),
               "image": publish_image("contact-sheet", png, "contact sheet [S004]"),
               "big": publish_image("big-sheet", png, "big sheet", max_inline_bytes=10, path="/store/sheet.png"),
               "url": publish_image("url-sheet", png, "url sheet", max_inline_bytes=10,
                                    path="https://example.com/sheet.png")}
        p = ProgressArtifact("train-0-8", "training")
        for step in range(1, 11):
            p.update(step, 10)
        ids["progress"] = p.artifact_id
        ids["run"] = flow_run.get_id()
        return ids

    ids = publish_all()
    assert all(v is not None for v in ids.values()), ids
    with get_client(sync_client=True) as client:
        arts = client.read_artifacts(artifact_filter=ArtifactFilter(
            flow_run_id=ArtifactFilterFlowRunId(any_=[ids["run"]])))
    by_key = {a.key: a for a in arts}
    assert set(by_key) == {"segment-0-8-metrics", "notes", "contact-sheet", "big-sheet", "url-sheet", "train-0-8"}

    table = by_key["segment-0-8-metrics"]
    assert table.type == "table" and table.id == ids["table"] and table.task_run_id is not None
    assert json.loads(table.data) == [{"camera": "S004", "psnr": pytest.approx(23.1, abs=1e-5), "ssim": None},
                                      {"camera": "S005", "psnr": "inf", "frames": [0, 1]}]

    notes = by_key["notes"]
    assert notes.type == "markdown" and notes.data == "# Segment 0-8\n\n*fine*" and notes.description == "notes"

    image = by_key["contact-sheet"]
    assert image.type == "markdown" and image.description == "contact sheet [S004]"
    m = re.fullmatch(r"!\[contact sheet \(S004\)\]\(data:image/png;base64,([A-Za-z0-9+/=]+)\)", image.data)
    assert m and base64.b64decode(m.group(1)) == png

    big = by_key["big-sheet"]
    assert big.type == "markdown" and "/store/sheet.png" in big.data and "base64" not in big.data
    url = by_key["url-sheet"]
    assert url.type == "image" and url.data == "https://example.com/sheet.png"

    progress = by_key["train-0-8"]
    assert progress.type == "progress" and float(progress.data) == 100.0
