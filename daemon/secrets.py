"""Secrets never leave the process: the configuration as it is published, recorded and printed.

The effective configuration goes out on ``ballbar/<m>/config`` (and
``last/config``), into every MCAP file's ``/ballbar/config`` records, and to
``ballbar run --print-config``.  :func:`redacted` is what all of them are
given: every value whose key looks secret (passwords, private keys,
certificate or key contents, tokens) becomes ``"<redacted>"``, at any depth
and in Zenoh's path-style keys (``"transport/auth/usrpwd/password"``), and a
password inside a URL (``scheme://user:PASSWORD@host``) is masked.  File
*paths* stay (``listen_private_key`` names a key file: redacted all the same,
since some deployments inline the PEM there); what a Zenoh config file holds is
never read into the configuration at all.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

REDACTED = "<redacted>"
# Matched against each key (and each segment of a path-style key), case-insensitively.
_SECRET_KEY = re.compile(
    r"(password|passwd|passphrase|secret|token|credential|api_?key|private|_base64|\bpem\b|_pem\b|pem_|"
    r"dictionary_file|psk)",
    re.IGNORECASE,
)
_URL_PASSWORD = re.compile(r"(?P<head>[A-Za-z][A-Za-z0-9+.-]*://[^/@:\s]*:)(?P<pw>[^/@\s]+)(?P<tail>@)")


def is_secret_key(key: str) -> bool:
    """Whether a configuration key (``password``, ``transport/link/tls/connect_private_key``) names a secret."""
    return any(_SECRET_KEY.search(part) for part in re.split(r"[/.]", str(key)) if part)


def mask_url(text: str) -> str:
    """``scheme://user:PASSWORD@host`` with the password masked; other text unchanged."""
    return _URL_PASSWORD.sub(lambda m: f"{m['head']}{REDACTED}{m['tail']}", text)


def redacted(value: Any) -> Any:
    """A copy of ``value`` (the configuration as plain data) with every secret replaced by ``"<redacted>"``."""
    if isinstance(value, Mapping):
        out: dict[str, Any] = {}
        for k, v in value.items():
            if is_secret_key(str(k)) and v not in (None, "", [], {}):
                out[k] = REDACTED
            else:
                out[k] = redacted(v)
        return out
    if isinstance(value, list | tuple):
        return [redacted(v) for v in value]
    if isinstance(value, str):
        return mask_url(value)
    return value


__all__ = ["REDACTED", "is_secret_key", "mask_url", "redacted"]
