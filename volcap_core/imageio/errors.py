"""The errors of reading an image file: one class for every failure, one for an ambiguous choice.

Every reader of :mod:`volcap_core.imageio` raises :class:`ImageReadError` naming the file and the
reason, so a caller (ingest, the CLI) can report any image failure the same way; the structure
check, the part/view choice and the decoders all raise it.
"""

from __future__ import annotations

import os

__all__ = ["ImageReadError", "SourceChoiceError"]


class ImageReadError(ValueError):
    """An image file could not be read. ``str(err)`` is ``"<path>: <reason>"``."""

    def __init__(self, path: str | os.PathLike[str], reason: str) -> None:
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")

    def __reduce__(self):  # keep (path, reason) across pickling (process pools, Prefect)
        return (type(self), (self.path, self.reason))


class SourceChoiceError(ImageReadError):
    """The file holds several parts or views and the choice made picks none or several of them.
    The reason lists what the file holds."""
