"""Conditional writes on an object store (S3 ``If-None-Match: *`` / ``If-Match: etag``): the only arbiter
between writers where there is no rename and no flock. Mixed into :class:`storage.objstore.store.Store`."""

from __future__ import annotations


class PreconditionFailed(Exception):
    """A conditional write lost: the object exists (If-None-Match) or changed (If-Match)."""


def backend_errors() -> tuple[type[BaseException], ...]:
    """What a remote call may raise: OSError (s3fs translates most S3 errors), or botocore's own errors."""
    from botocore.exceptions import BotoCoreError, ClientError

    return (OSError, BotoCoreError, ClientError)


class ConditionalOps:
    """put_if_absent / put_if_match / get_with_etag / delete_if_match of a remote :class:`Store`."""


    def _bucket_key(self, key: str) -> tuple[str, str]:
        bucket, _, rest = self.path(key).partition("/")
        return bucket, rest

    def _put_object(self, key: str, data: bytes, **cond) -> str:
        bucket, k = self._bucket_key(key)
        self._count("PutObject")
        try:
            out = self._fs.call_s3("put_object", Bucket=bucket, Key=k, Body=data, **cond)
        except backend_errors() as exc:
            if _is_precondition(exc):
                raise PreconditionFailed(key) from None
            raise self._fail(key, "write", exc) from None
        return out.get("ETag", "")

    def put_if_absent(self, key: str, data: bytes) -> str:
        """Create ``key`` only if no object has it (``If-None-Match: *``); returns the new ETag.
        Raises PreconditionFailed when it exists."""
        self._remote_only("put_if_absent")
        self.stats.add(written=len(data))
        return self._put_object(key, data, IfNoneMatch="*")

    def put_if_match(self, key: str, data: bytes, etag: str) -> str:
        """Replace ``key`` only if its ETag is still ``etag`` (compare-and-swap); returns the new ETag.
        Raises PreconditionFailed when it changed (or vanished)."""
        self._remote_only("put_if_match")
        self.stats.add(written=len(data))
        return self._put_object(key, data, IfMatch=etag)

    def _get_object(self, key: str, start: int | None = None, end: int | None = None) -> tuple[bytes, str]:
        """One GET (ranged when start/end are given: bytes [start, end)); (bytes, ETag) of that response.
        FileNotFoundError when absent. (s3fs's cat_file sends a HEAD first for a whole object.)"""
        from fsspec.asyn import sync

        bucket, k = self._bucket_key(key)
        self._count("GetObject")
        rng = {} if start is None and end is None else \
            {"Range": f"bytes={start or 0}-{'' if end is None else end - 1}"}

        async def fetch():
            resp = await self._fs._call_s3("get_object", Bucket=bucket, Key=k, **rng)
            async with resp["Body"] as body:
                return await body.read(), resp["ETag"]
        try:
            data, etag = sync(self._fs.loop, fetch)
        except FileNotFoundError:
            raise
        except backend_errors() as exc:
            raise self._fail(key, "read", exc) from None
        self.stats.add(read=len(data))
        return data, etag

    def get_with_etag(self, key: str) -> tuple[bytes, str] | None:
        """(bytes, ETag) of one GET, so content and ETag belong together; None when absent."""
        self._remote_only("get_with_etag")
        try:
            return self._get_object(key)
        except FileNotFoundError:
            return None

    def delete_if_match(self, key: str, etag: str) -> bool:
        """Delete ``key`` only if its ETag is ``etag``; False when it changed or is gone."""
        self._remote_only("delete_if_match")
        bucket, k = self._bucket_key(key)
        self._count("DeleteObject")
        try:
            self._fs.call_s3("delete_object", Bucket=bucket, Key=k, IfMatch=etag)
        except FileNotFoundError:
            return False
        except backend_errors() as exc:
            if _is_precondition(exc):
                return False
            raise self._fail(key, "delete", exc) from None
        return True

    def _remote_only(self, what: str) -> None:
        if self.is_local:
            raise NotImplementedError(f"{what} is for object stores; a local work dir uses flock and rename")



def _is_precondition(exc: BaseException) -> bool:
    """True when ``exc`` (or its cause) is S3's 412 PreconditionFailed or 409 ConditionalRequestConflict."""
    while exc is not None:
        if isinstance(exc, FileExistsError):
            return True
        resp = getattr(exc, "response", None)
        if isinstance(resp, dict):
            err = resp.get("Error", {})
            code = str(err.get("Code", ""))
            status = resp.get("ResponseMetadata", {}).get("HTTPStatusCode")
            if code in ("PreconditionFailed", "ConditionalRequestConflict", "412") or status == 412:
                return True
        exc = exc.__cause__ or exc.__context__
    return False

