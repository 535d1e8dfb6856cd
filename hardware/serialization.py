"""How records grow without changing the bytes of those already written.

A field added to a record after records of it were stored is optional; while unset it is left out
of the record's JSON, so every older record (and every task cache key made of one) keeps its bytes
and its digest. This is the bottom layer (pydantic only), so hardware's rigs and every record of
``volcap_core`` (through ``volcap_core.records``) omit fields the same way::

    @model_serializer(mode="wrap")
    def _omit_unset(self, handler):
        return omit_unset(handler(self), ("new_field",))
"""

from __future__ import annotations

from typing import Any, Iterable


def omit_unset(data: Any, keys: Iterable[str]) -> Any:
    """``data`` (a model's serialised dict, changed in place) without those of ``keys`` whose value
    is unset: None or an empty dict, list or tuple. Anything but a dict is returned as it is."""
    if isinstance(data, dict):
        for k in keys:
            v = data.get(k, 0)
            if v is None or (isinstance(v, (dict, list, tuple)) and not v):
                del data[k]
    return data
