"""Results in the Prefect UI: tables, markdown, images (contact sheets) and progress bars.

Thin, forgiving wrappers over :mod:`prefect.artifacts` (checked against Prefect 3.8.7):

* Every function is a no-op returning ``None`` outside a flow or task run. Prefect 3.8 still
  creates an unattached artifact there (with a ``FutureWarning`` that it will stop doing so);
  volcap's library code and tests call these helpers outside runs all the time and must not
  talk to a server then.
* Every failure (API unreachable, a server-side validation error, a value json cannot encode) is
  logged as a warning and swallowed: an artifact is a view on a result, and a coordinator's run
  must never fail because the view could not be drawn. Note that an unreachable API costs up
  to Prefect's client retry budget (``PREFECT_CLIENT_MAX_RETRIES``, ~1 min by default) per call;
  :class:`ProgressArtifact` therefore gives up after its first failure.
* Keys are normalised with :func:`artifact_key` (Prefect refuses anything but lowercase letters,
  digits and dashes, and would raise inside the run).
* The synchronous Prefect functions are called with ``_sync=True``: they are wrapped in Prefect's
  ``async_dispatch`` and would otherwise return an un-awaited coroutine (and create nothing) when
  called from an async flow.

Artifacts made inside a task run are attached to that task run (and its flow run); the same key in
later runs makes a new version of the artifact, which the UI's Artifacts page shows by key.
"""

from __future__ import annotations

import base64
import logging
import math
import re
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any
from uuid import UUID

import prefect.artifacts as _pa

__all__ = ["ProgressArtifact", "artifact_key", "publish_image", "publish_markdown", "publish_table"]

_module_log = logging.getLogger(__name__)
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def artifact_key(*parts: str) -> str:
    """A valid Prefect artifact key from ``parts``: ``artifact_key("segment", "0:8", "Metrics")``
    -> ``"segment-0-8-metrics"``.

    Lowercases, replaces every run of characters other than ``a-z``/``0-9`` with one ``-`` and trims
    dashes at both ends. Idempotent on keys that are already valid.

    Raises:
        ValueError: nothing usable is left (e.g. no parts, or only punctuation).
    """
    joined = "-".join(str(p) for p in parts).lower()
    key = re.sub(r"[^a-z0-9]+", "-", joined).strip("-")
    if not key:
        raise ValueError(f"artifact_key{parts!r}: no letters or digits to build a key from")
    return key


def publish_table(key: str, rows: list[dict], description: str) -> UUID | None:
    """A table artifact, one row per dict (columns are the union of the dicts' keys).

    Values are made JSON-safe first: numpy scalars and arrays become Python numbers and lists, NaN
    becomes an empty cell (``None``), ±inf the strings ``"inf"`` / ``"-inf"`` (a PSNR of identical
    images is legitimately infinite, and the UI's JSON parser rejects ``Infinity``), anything else
    unknown its ``str()``.

    Returns:
        the artifact id; ``None`` outside a run or when publishing failed (logged).
    """
    return _publish("table", key, lambda k: _pa.create_table_artifact(
        table=[_jsonable(dict(r)) for r in rows], key=k, description=description, _sync=True))


def publish_markdown(key: str, markdown: str, description: str) -> UUID | None:
    """A markdown artifact (GitHub-flavoured markdown as the Prefect UI renders it).

    Returns:
        the artifact id; ``None`` outside a run or when publishing failed (logged).
    """
    return _publish("markdown", key, lambda k: _pa.create_markdown_artifact(
        markdown=str(markdown), key=k, description=description, _sync=True))


def publish_image(key: str, image: bytes, description: str, *, max_inline_bytes: int = 1_000_000,
                  path: str | None = None) -> UUID | None:
    """Show a PNG or JPEG (e.g. :func:`volcap_core.contact_sheet.encode_jpeg` of a contact sheet)
    in the UI.

    * ``len(image) <= max_inline_bytes`` (the default case): a markdown artifact
      ``![description](data:image/...;base64,...)``. The image travels inside the artifact, so the
      UI shows it wherever it runs, unlike a path on the worker's disk that a coordinator's browser
      cannot read. Base64 adds a third, and the server also publishes the artifact as an event,
      which it refuses above ~1.5 MB (measured: "Refusing to publish event of size 2369091"):
      keep inline images small (a JPEG sheet at 720 px is ~0.2 MB).
    * larger, and ``path`` is an ``http(s)://`` URL: an image artifact
      (:func:`prefect.artifacts.create_image_artifact`, which displays an image from a URL the
      browser can fetch).
    * larger otherwise: a markdown artifact naming ``path`` (the file the image was written to,
      e.g. with :func:`volcap_core.contact_sheet.write_sheet`), or saying that it was not kept.

    Args:
        key: artifact key (normalised with :func:`artifact_key`).
        image: PNG or JPEG file bytes.
        description: one line; also the image's alt text.
        max_inline_bytes: largest image embedded as a data URI.
        path: where the full image lives (local path, ``s3://`` or ``http(s)://`` URL), if anywhere.

    Returns:
        the artifact id; ``None`` outside a run or when publishing failed (logged).
    """
    def create(k: str) -> UUID:
        data = bytes(image)
        if data.startswith(_PNG_SIGNATURE):
            mime = "image/png"
        elif data.startswith(b"\xff\xd8\xff"):
            mime = "image/jpeg"
        else:
            raise ValueError(f"publish_image expects PNG or JPEG bytes, got {data[:8]!r}... ({len(data)} bytes)")
        alt = _markdown_text(description) or "image"
        if len(data) <= max_inline_bytes:
            uri = f"data:{mime};base64," + base64.b64encode(data).decode("ascii")
            return _pa.create_markdown_artifact(markdown=f"![{alt}]({uri})", key=k, description=description,
                                                _sync=True)
        if path is not None and re.match(r"(?i)^https?://", str(path)):
            return _pa.create_image_artifact(image_url=str(path), key=k, description=description, _sync=True)
        size = f"{len(data) / 1e6:.1f} MB image, more than the {max_inline_bytes / 1e6:.1f} MB embedded in the UI"
        where = f"Written to `{path}`." if path is not None else "It was not written to a file."
        return _pa.create_markdown_artifact(markdown=f"**{alt}**\n\nImage not embedded ({size}). {where}",
                                            key=k, description=description, _sync=True)

    return _publish("image", key, create)


class ProgressArtifact:
    """A progress bar in the UI for a long loop (training iterations, frames rendered).

    ::

        progress = ProgressArtifact(artifact_key("train", segment_name), "training 0-8")
        for it in range(iterations):
            ...
            progress.update(it + 1, iterations)

    The artifact is created at 0 % on construction. :meth:`update` sends at most one update per
    ``min_interval_s`` of wall time (a training step can take milliseconds, a round trip to the API
    tens of them) and always sends the final 100 % (``step >= total``) once. Outside a run, or after
    the first failure to reach the API (logged once), every method is a no-op: a progress bar must
    not slow a loop down, let alone stop it. Safe to call from several threads.
    """

    def __init__(self, key: str, description: str, *, min_interval_s: float = 1.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.key = key
        self.description = description
        self.min_interval_s = float(min_interval_s)
        self._clock = clock
        self._lock = threading.Lock()
        self._last_sent_at = -math.inf
        self._last_sent: float | None = None
        self._finished = False
        #: the artifact's id; None outside a run or when creating it failed
        self.artifact_id: UUID | None = _publish("progress", key, lambda k: _pa.create_progress_artifact(
            progress=0.0, key=k, description=description, _sync=True))
        if self.artifact_id is not None:
            self._last_sent, self._last_sent_at = 0.0, self._clock()

    @property
    def active(self) -> bool:
        """Whether updates are still being sent (in a run, created, no failure, not finished)."""
        return self.artifact_id is not None and not self._finished

    def update(self, step: int, total: int) -> None:
        """Report ``step`` of ``total`` done (``step`` clamped to ``[0, total]``; 100 % when
        ``step >= total``). ``total <= 0`` counts as done."""
        if total <= 0:
            percent = 100.0
        else:
            percent = 100.0 * min(max(step, 0), total) / total
        self._send(percent)

    def finish(self) -> None:
        """Send 100 % now (a loop that stops early, e.g. converged); later updates are ignored."""
        self._send(100.0)

    def _send(self, percent: float) -> None:
        if not self.active:
            return
        with self._lock:
            if self.artifact_id is None or self._finished:  # another thread got here first
                return
            now = self._clock()
            final = percent >= 100.0
            if not final and (now - self._last_sent_at < self.min_interval_s or percent == self._last_sent):
                return
            try:
                _pa.update_progress_artifact(artifact_id=self.artifact_id, progress=percent, _sync=True)
            except Exception as exc:  # noqa: BLE001 - see the module docstring
                _warn(f"progress artifact {self.key!r}: update to {percent:.1f}% failed, "
                      f"no further updates: {type(exc).__name__}: {exc}")
                self.artifact_id = None
                return
            self._last_sent, self._last_sent_at = percent, now
            self._finished = final


# -- internals -------------------------------------------------------------------------------------


def _in_run() -> bool:
    """Whether a flow or task run context is active in this thread (where artifacts attach)."""
    from prefect.context import FlowRunContext, TaskRunContext

    return TaskRunContext.get() is not None or FlowRunContext.get() is not None


def _publish(kind: str, key: str, create: Callable[[str], UUID]) -> UUID | None:
    if not _in_run():
        return None
    try:
        return create(artifact_key(key))
    except Exception as exc:  # noqa: BLE001 - an artifact must never fail the run
        _warn(f"{kind} artifact {key!r} not published: {type(exc).__name__}: {exc}")
        return None


def _warn(message: str) -> None:
    # The run logger puts the warning next to the run in the UI; outside a run (or if even that
    # fails) the module logger still records it.
    try:
        from prefect import get_run_logger

        get_run_logger().warning(message)
    except Exception:  # noqa: BLE001
        _module_log.warning(message)


def _markdown_text(text: str) -> str:
    """One line of text safe inside ``![...]`` / ``**...**``: no brackets, no newlines."""
    return " ".join(str(text).replace("[", "(").replace("]", ")").replace("*", "").split())


def _jsonable(value: Any) -> Any:
    """Plain JSON values for a table cell (see :func:`publish_table`)."""
    if value is None or isinstance(value, (bool, str, int)):
        return value
    if isinstance(value, float):
        if math.isnan(value):
            return None
        return value if math.isfinite(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    tolist = getattr(value, "tolist", None)  # numpy scalars and arrays (and torch tensors)
    if callable(tolist):
        try:
            return _jsonable(tolist())
        except Exception:  # noqa: BLE001
            pass
    return str(value)
