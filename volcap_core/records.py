"""Artifact references and records: the vocabulary every layer speaks.

An artifact is immutable bytes named by its digest (``blake3:<64 hex>``). Tasks take and return
:class:`ArtifactRef` values, never the bytes themselves. Domain records (captures, calibrations,
plans...) are pydantic models stored as *canonical JSON*: sorted keys, no insignificant
whitespace, UTF-8, so the same record always has the same digest.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any, ClassVar, TypeVar

from pydantic import BaseModel, ConfigDict, field_validator

DIGEST_RE = re.compile(r"^blake3:[0-9a-f]{64}$")

#: Media types used across volcap. A ref's media type says how to decode its bytes.
MEDIA_TREE = "application/vnd.volcap.tree+json"
MEDIA_EXR = "image/x-exr"
MEDIA_SAFETENSORS = "application/vnd.safetensors"
MEDIA_JSON = "application/json"
MEDIA_BYTES = "application/octet-stream"
MEDIA_PNG = "image/png"


class ArtifactRef(BaseModel):
    """A reference to an immutable artifact in a store.

    ``digest`` is ``blake3:<hex>`` of the bytes, ``size`` their length in bytes, ``media_type``
    how to read them (``MEDIA_*`` above, or ``application/vnd.volcap.<record>+json`` for records).
    A ref is location-free: the same ref is valid in every store that holds the digest.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    digest: str
    size: int
    media_type: str = MEDIA_BYTES

    @field_validator("digest")
    @classmethod
    def _check_digest(cls, v: str) -> str:
        if not DIGEST_RE.match(v):
            raise ValueError(f"not a blake3 digest: {v!r} (expected 'blake3:' + 64 lowercase hex)")
        return v

    @field_validator("size")
    @classmethod
    def _check_size(cls, v: int) -> int:
        if v < 0:
            raise ValueError(f"negative size {v}")
        return v

    @property
    def hex(self) -> str:
        return self.digest.split(":", 1)[1]

    def __str__(self) -> str:  # what a coordinator copies from a log
        return self.digest


def canonical_json(obj: Any) -> bytes:
    """Encode plain data (dict/list/str/int/float/bool/None) as canonical JSON bytes.

    Sorted keys, ``(",", ":")`` separators, UTF-8 without escapes, no NaN/Infinity (they have no
    JSON form and would make two equal records hash differently).
    """
    _reject_non_finite(obj)
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=False,
                      allow_nan=False).encode("utf-8")


def _reject_non_finite(obj: Any) -> None:
    if isinstance(obj, float) and not math.isfinite(obj):
        raise ValueError(f"non-finite number {obj!r} cannot be stored in a canonical record")
    if isinstance(obj, dict):
        for v in obj.values():
            _reject_non_finite(v)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            _reject_non_finite(v)


R = TypeVar("R", bound="Record")


class Record(BaseModel):
    """Base of every stored domain record (Capture, Calibration, SegmentPlan...).

    Subclasses set ``kind``; the media type ``application/vnd.volcap.<kind>+json`` travels in the
    ref so a reader knows what it holds before decoding it. Extra fields are refused so a typo in a
    hand-written record is an error, not a silently ignored value.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: ClassVar[str] = "record"

    @classmethod
    def media_type(cls) -> str:
        return f"application/vnd.volcap.{cls.kind}+json"

    def to_canonical_json(self) -> bytes:
        return canonical_json(self.model_dump(mode="json"))

    @classmethod
    def from_json_bytes(cls: type[R], data: bytes) -> R:
        return cls.model_validate_json(data)
