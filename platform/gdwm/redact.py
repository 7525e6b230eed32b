"""Credentials out of everything gdwm prints or logs: URIs' ``user:password@``, secret query parameters and the
values of the secret environment variables gdwm's processes read (``MLFLOW_TRACKING_PASSWORD``, AWS keys, ...).

Only what is displayed or logged goes through here (MLflow params and tags, ``gdwm config show``, messages); what
connects to a store keeps the real URI.
"""

from __future__ import annotations

import os
import re
from typing import Any

__all__ = ["MASK", "SECRET_ENV", "redact", "redact_config"]

MASK = "***"

SECRET_ENV = (
    "MLFLOW_TRACKING_PASSWORD",
    "MLFLOW_TRACKING_TOKEN",
    "AWS_SECRET_ACCESS_KEY",
    "AWS_SESSION_TOKEN",
    "RAY_AUTH_TOKEN",
    "S3_SECRET_ACCESS_KEY",
    "MINIO_ROOT_PASSWORD",
    "POSTGRES_PASSWORD",
    "PGPASSWORD",
    "MLFLOW_AUTH_ADMIN_PASSWORD",
    "MLFLOW_FLASK_SERVER_SECRET_KEY",
)
"""Environment variables that hold secrets (read by gdwm, MLflow, pyarrow/boto or set by k8s/ for our pods)."""

_MIN_ENV_SECRET = 8  # shorter values would mask unrelated text ("1", "on", a stretch of a hex digest)

# scheme://userinfo@ - userinfo stops at the authority's end, so the last '@' before '/' ends it (like urllib).
_USERINFO = re.compile(r"(?P<scheme>\b[A-Za-z][A-Za-z0-9+.-]*://)(?P<info>[^/?#@\s'\"<>]*(?:@[^/?#@\s'\"<>]*)*)@")
_SECRET_NAME = (
    r"x-amz-[\w-]+|sig|key|[\w.-]*(?:token|secret|passw(?:or)?d|pwd|signature|credential|api[_-]?key|auth)[\w.-]*"
    r"|[\w.-]*[_-]key"
)
_QUERY = re.compile(rf"(?P<head>[?&;](?:{_SECRET_NAME})=)(?P<value>[^&#;\s'\"<>]+)", re.IGNORECASE)


def _userinfo(m: re.Match) -> str:
    user, colon, _password = m["info"].partition(":")
    return m["scheme"] + (f"{user}:{MASK}@" if colon else f"{MASK}@")


def redact(text: str) -> str:
    """``text`` with credentials masked: ``https://alice:pw@host`` -> ``https://alice:***@host``, a token-only
    ``https://tok@host`` -> ``https://***@host``, ``?token=abc&x=1`` -> ``?token=***&x=1`` and any verbatim value
    of a :data:`SECRET_ENV` variable -> ``***``. Text without secrets comes back unchanged."""
    if not isinstance(text, str) or not text:
        return text
    for name in SECRET_ENV:
        value = os.environ.get(name)
        if value and len(value) >= _MIN_ENV_SECRET and value in text:
            text = text.replace(value, MASK)
    text = _USERINFO.sub(_userinfo, text)
    return _QUERY.sub(lambda m: m["head"] + MASK, text)


def redact_config(container: Any) -> Any:
    """A copy of a plain config (dicts, lists, scalars) with every string value passed through :func:`redact`."""
    if isinstance(container, dict):
        return {k: redact_config(v) for k, v in container.items()}
    if isinstance(container, list | tuple):
        return type(container)(redact_config(v) for v in container)
    if isinstance(container, str):
        return redact(container)
    return container
