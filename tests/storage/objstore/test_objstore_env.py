"""Credential redaction (storage.objstore.env) of what botocore logs when the credentials are NOT in the
environment (IRSA, profile, instance role): the token and signature must go without redact() knowing them."""

from __future__ import annotations

import logging

import pytest

from storage.objstore.env import SECRET_ENV, install_log_redaction, redact

KEY_ID = "ASIAMS3DROLEKEY00042"
SECRET = "role-secret-never-in-env-9c1e"
TOKEN = "IQoJb3JpZ2luX2VjEMS3DsessionTOKEN/abc+def=="


@pytest.fixture
def no_env_credentials(monkeypatch):
    for k in SECRET_ENV:
        monkeypatch.delenv(k, raising=False)


def _signed_request():
    """A real botocore SigV4-signed S3 request with a session token (offline: signing needs no network)."""
    from botocore.auth import S3SigV4Auth
    from botocore.awsrequest import AWSRequest
    from botocore.credentials import Credentials

    req = AWSRequest(method="PUT", url="https://bucket.s3.us-east-1.amazonaws.com/work/.lock.json", data=b"{}")
    S3SigV4Auth(Credentials(KEY_ID, SECRET, TOKEN), "s3", "us-east-1").add_auth(req)
    return req.prepare()


def _text(value) -> str:
    return value.decode() if isinstance(value, bytes) else value


def test_header_dict_repr_is_redacted(no_env_credentials):
    prepared = _signed_request()
    text = repr(prepared)  # what botocore.endpoint logs: "Sending http request: <AWSPreparedRequest ...>"
    auth = _text(prepared.headers["Authorization"])
    signature = auth.rsplit("Signature=", 1)[1]
    assert TOKEN in text and KEY_ID in text and signature in text  # the leak this guards against
    out = redact(text)
    for secret in (TOKEN, KEY_ID, signature):
        assert secret not in out
    assert "x-amz-content-sha256" in out.lower() and "bucket.s3.us-east-1.amazonaws.com" in out  # rest kept
    headers = {"X-Amz-Security-Token": TOKEN.encode(), "Authorization": auth.encode(), "host": "h"}
    out = redact(repr(headers))
    assert TOKEN not in out and KEY_ID not in out and signature not in out and "'host': 'h'" in out


def test_sts_response_and_canonical_request_are_redacted(no_env_credentials):
    xml = (f"<Credentials><AccessKeyId>{KEY_ID}</AccessKeyId><SecretAccessKey>{SECRET}</SecretAccessKey>"
           f"<SessionToken>{TOKEN}</SessionToken><Expiration>2026-12-02T00:00:00Z</Expiration></Credentials>")
    as_json = repr({"AccessKeyId": KEY_ID, "SecretAccessKey": SECRET, "Token": TOKEN, "Expiration": "x"})
    canonical = f"PUT\n/work/.lock.json\n\nhost:h\nx-amz-security-token:{TOKEN}\n\nSignature:\n{'ab12' * 16}"
    for text in (xml, as_json, canonical):
        out = redact(text)
        assert TOKEN not in out and SECRET not in out and KEY_ID not in out and "ab12ab12" not in out, out
    assert "2026-12-02T00:00:00Z" in redact(xml)


def test_botocore_debug_logs_carry_no_credentials(no_env_credentials, caplog):
    install_log_redaction()
    with caplog.at_level(logging.DEBUG):
        prepared = _signed_request()  # botocore.auth logs the canonical request and the signature
        logging.getLogger("botocore.endpoint").debug("Sending http request: %s", prepared)
    signature = _text(prepared.headers["Authorization"]).rsplit("Signature=", 1)[1]
    assert "Signature:" in caplog.text and "Sending http request" in caplog.text
    for secret in (TOKEN, KEY_ID, SECRET, signature):
        assert secret not in caplog.text
