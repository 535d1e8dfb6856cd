"""The store's credentials in a flow run on a worker: its environment, or a Prefect Secret block.

Both deployments' entrypoints (``production_flow``, ``train_segment_flow``; docs/operations.md)
call :func:`store_credentials_from_block` first thing, so a worker whose environment has no
``AWS_*`` variables reads them from the server instead of failing on its first store access.
"""

from __future__ import annotations

import os

#: Names a Prefect ``Secret`` block whose value is a JSON object of environment variables for the
#: store (``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``AWS_DEFAULT_REGION``, ``AWS_ENDPOINT_URL``).
STORE_SECRET_ENV = "VOLCAP_STORE_SECRET"
STORE_SECRET_KEYS = ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN", "AWS_DEFAULT_REGION",
                     "AWS_REGION", "AWS_ENDPOINT_URL", "AWS_ENDPOINT_URL_S3")


def store_credentials_from_block() -> list[str]:
    """Put the store credentials of the Secret block named by ``$VOLCAP_STORE_SECRET`` into this
    process's environment (variables already set win). Returns the names set; [] without a block."""
    name = os.environ.get(STORE_SECRET_ENV)
    if not name:
        return []
    from prefect.blocks.system import Secret

    try:
        value = Secret.load(name).get()
    except ValueError as exc:
        raise ValueError(f"{STORE_SECRET_ENV}={name}: no such Secret block on the Prefect server ({exc})") from None
    if isinstance(value, str):
        import json

        try:
            value = json.loads(value)
        except ValueError:
            value = None
    if not isinstance(value, dict) or not all(isinstance(v, str) for v in value.values()):
        raise ValueError(f"Secret block {name!r} must hold a JSON object of strings, e.g. "
                         '{"AWS_ACCESS_KEY_ID": "...", "AWS_SECRET_ACCESS_KEY": "..."}')
    unknown = sorted(set(value) - set(STORE_SECRET_KEYS))
    if unknown:
        raise ValueError(f"Secret block {name!r}: unexpected keys {', '.join(unknown)} "
                         f"(allowed: {', '.join(STORE_SECRET_KEYS)})")
    applied = [k for k in value if k not in os.environ]
    for k in applied:
        os.environ[k] = value[k]
    return applied


__all__ = ["STORE_SECRET_ENV", "STORE_SECRET_KEYS", "store_credentials_from_block"]
