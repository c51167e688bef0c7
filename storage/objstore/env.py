"""Where an object store's endpoint, region and credentials come from, and keeping credentials out of
every message and log line (see :mod:`storage.objstore.store`)."""

from __future__ import annotations

import logging
import os
import re

from storage.errors import InputError

SECRET_ENV = ("AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN", "AWS_ACCESS_KEY_ID", "AWS_SECURITY_TOKEN")
OPTION_KEYS = {"endpoint_url", "region", "profile", "key", "secret", "token", "anon"}
_SECRET_OPTIONS = ("key", "secret", "token")
_SIGNED = re.compile(r"(?i)(x-amz-signature=|x-amz-credential=|x-amz-security-token=|signature=|credential=)"
                     r"[^&\s,'\"]+")
# botocore logs each signed request (its Authorization header names the access key) at DEBUG
_LOGGERS = ("botocore.endpoint", "botocore.auth", "botocore.hooks", "botocore.parsers", "botocore.credentials",
            "aiobotocore.endpoint", "aiobotocore.parsers", "aiobotocore.credentials", "s3fs", "fsspec")
_USERINFO = re.compile(r"(?i)\b([a-z][a-z0-9+.-]*://)[^/@\s]+@")
# header or field style, as botocore's DEBUG logs print them with credentials that are not in the
# environment (IRSA, profiles, instance roles): ``'X-Amz-Security-Token': b'...'``, ``'Authorization':
# b'AWS4-HMAC-SHA256 Credential=..., Signature=...'``, an STS response's ``<SessionToken>...`` or JSON
_SECRET_FIELDS = r"(?:x-amz-security-token|authorization|x-amz-credential|x-amz-signature|" \
                 r"secretaccesskey|sessiontoken|accesskeyid|secret_?access_?key|session_?token|access_?key_?id|token)"
_FIELD = re.compile(r"(?i)(['\"]" + _SECRET_FIELDS + r"['\"]\s*:\s*b?['\"])[^'\"]*")
_XML_FIELD = re.compile(r"(?i)(<(?:SecretAccessKey|SessionToken|AccessKeyId|Token)>)[^<]*")
# SigV4's canonical request lists ``x-amz-security-token:<token>``; botocore.auth logs ``Signature:\n<hex>``
_CANONICAL = re.compile(r"(?i)(x-amz-security-token:|\bsignature:\s*)[^\s'\"]+")


def redact(text: str, secrets=()) -> str:
    """``text`` with every credential replaced by ``***``: the given ``secrets`` and those of the
    environment (SECRET_ENV), URL user-info (``s3://key:secret@bucket``), signed-URL parameters, and
    credential headers/fields printed as botocore logs them (security token, Authorization, STS keys),
    so credentials that are not in the environment (IRSA, profile, instance role) are caught too."""
    out = str(text)
    known = [s for s in (*secrets, *(os.environ.get(k) for k in SECRET_ENV)) if s and len(s) >= 4]
    for s in sorted(set(known), key=len, reverse=True):
        out = out.replace(s, "***")
    for pattern in (_FIELD, _XML_FIELD, _CANONICAL, _SIGNED):
        out = pattern.sub(lambda m: m.group(1) + "***", out)
    return _USERINFO.sub(lambda m: m.group(1) + "***@", out)


class _RedactingFilter(logging.Filter):
    """Rewrites a log record's message through :func:`redact` (installed on the storage libraries' loggers)."""

    def filter(self, record: logging.LogRecord) -> bool:
        try:
            msg = record.getMessage()
        except (TypeError, ValueError):  # a malformed record is the logging library's problem, not ours
            return True
        clean = redact(msg)
        if clean != msg:
            record.msg, record.args = clean, None
        return True


_FILTER = _RedactingFilter()


def install_log_redaction() -> None:
    for name in _LOGGERS:
        lg = logging.getLogger(name)
        if _FILTER not in lg.filters:
            lg.addFilter(_FILTER)


def resolve_options(options: dict | None = None) -> dict:
    """The effective store options: ``options`` over the environment. Unknown keys raise InputError.

    Returns a dict with keys from OPTION_KEYS whose values are set (endpoint_url and region filled in
    from the environment when absent; credentials only when given explicitly)."""
    options = dict(options or {})
    unknown = sorted(set(options) - OPTION_KEYS)
    if unknown:
        raise InputError(None, f"unknown storage option(s) {unknown}; known: {sorted(OPTION_KEYS)}")
    env = os.environ
    out = {k: v for k, v in options.items() if v not in (None, "")}
    endpoint = env.get("AWS_ENDPOINT_URL_S3") or env.get("AWS_ENDPOINT_URL")
    if "endpoint_url" not in out and endpoint:
        out["endpoint_url"] = endpoint
    region = env.get("AWS_DEFAULT_REGION") or env.get("AWS_REGION")
    if "region" not in out and region:
        out["region"] = region
    if "profile" not in out and env.get("AWS_PROFILE"):
        out["profile"] = env["AWS_PROFILE"]
    return out
