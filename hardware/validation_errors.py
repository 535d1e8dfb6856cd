"""Turn pydantic validation errors into one readable message per problem: field path and value.

In the bottom layer (pydantic only) so that the rigs (``hardware.rig.load_rig``) and the
production spec and shots (``volcap_core.production``) word their refusals the same way."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from pydantic import ValidationError

__all__ = ["clean_loc", "format_loc", "format_validation_error"]


def clean_loc(loc: Sequence[int | str]) -> tuple[int | str, ...]:
    """Drop the entries pydantic adds for validators and union members (``function-after[...]``,
    ``str``...), leaving the path of fields and indices."""
    return tuple(p for p in loc if not (isinstance(p, str) and (
        "function-" in p or "[" in p or p in ("str", "int", "float", "Shot"))))


def format_loc(loc: Sequence[int | str]) -> str:
    """``('shots', 2, 'keyframes', 0, 'focal_mm')`` → ``shots[2].keyframes[0].focal_mm``."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out or "(top level)"


def _short(value: Any, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def format_validation_error(exc: ValidationError, *,
                            describe_loc: Callable[[tuple], str] | None = None) -> list[str]:
    """One line per error: ``<path>: <message> (got <value>)``.

    ``describe_loc`` may turn a location into something friendlier (e.g. ``keyframe 2 (frame
    130)``); by default the dotted path. Where it returns ``""`` the line is the message alone
    (a validator's message that already names what it is about). Pydantic's "Value error, " prefix is dropped; the value is
    left out when it is a whole object (a model validator's message names what is wrong).
    """
    lines = []
    errors = exc.errors()
    for err in errors:
        loc = tuple(err.get("loc", ()))
        # a sequence whose item failed is also reported "too short" by pydantic: noise
        if err.get("type") == "too_short" and any(
                len(e.get("loc", ())) > len(loc) and tuple(e["loc"][:len(loc)]) == loc
                for e in errors):
            continue
        loc = clean_loc(loc)
        where = describe_loc(loc) if describe_loc else format_loc(loc)
        msg = err.get("msg", "invalid")
        for prefix in ("Value error, ", "Assertion failed, "):
            if msg.startswith(prefix):
                msg = msg[len(prefix):]
        line = f"{where}: {msg}" if where else msg
        value = err.get("input")
        if err.get("type") != "missing" and "input" in err and not isinstance(value, (dict, list)):
            line += f" (got {_short(value)})"
        lines.append(line)
    return lines
