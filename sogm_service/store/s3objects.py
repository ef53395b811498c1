"""S3 objects for the object-store tile store (:mod:`sogm_service.store.s3`): a store's
location (``s3://bucket/prefix``), a boto3 client (credentials and region from boto3's usual
chain), and the tile objects under a location: listed, read whole or by their header alone,
written with a condition.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import PurePath, PurePosixPath
from typing import Any, Final

from sogm_service.wire import encodings
from sogm_service.wire.errors import ConfigError
from sogm_service.wire.tilefile import _PREFIX, SUFFIX, TileHeader, parse_header, parse_prefix

SCHEME: Final = "s3://"
HEAD_BYTES: Final = 4096  # one ranged GET reads a tile's header (longer ones take a second)
_BUCKET = re.compile(r"[a-z0-9][a-z0-9.\-]{1,61}[a-z0-9]")
PRECONDITION: Final = frozenset({"PreconditionFailed", "ConditionalRequestConflict", "412"})
ABSENT: Final = frozenset({"NoSuchKey", "404", "NotFound"})


@dataclass(frozen=True)
class S3Location:
    """A bucket and a key prefix (no slash at either end; empty: the bucket's root)."""

    bucket: str
    prefix: str = ""

    @classmethod
    def parse(cls, url: str) -> S3Location:
        """``s3://bucket/prefix`` (the prefix optional); ConfigError for anything else."""
        if not url.startswith(SCHEME):
            raise ConfigError(f"a store URL starts with {SCHEME} (got {url!r})", "store.url")
        bucket, _, prefix = url[len(SCHEME):].partition("/")
        if not _BUCKET.fullmatch(bucket):
            raise ConfigError(f"{bucket!r} is not an S3 bucket name (3-63 characters: "
                              "lower-case letters, digits, dots and hyphens)", "store.url")
        return cls(bucket, prefix.strip("/"))

    @property
    def url(self) -> str:
        return f"{SCHEME}{self.bucket}/{self.prefix}" if self.prefix else f"{SCHEME}{self.bucket}"

    def key(self, name: str) -> str:
        """The object key of ``name`` under the prefix."""
        return f"{self.prefix}/{name}" if self.prefix else name

    def where(self, key: str) -> PurePath:
        """How problems and listings name an object: ``bucket/key``."""
        return PurePosixPath(self.bucket, key)


def s3_client(endpoint_url: str | None = None) -> Any:
    """A boto3 S3 client (credentials and region from boto3's usual chain)."""
    try:
        import boto3
        from botocore.config import Config
    except ImportError:  # pragma: no cover - the s3 extra is part of the test extra
        raise ConfigError("an s3:// store needs boto3: pip install 'sogm-service[s3]'",
                          "store.url") from None
    config = Config(retries={"max_attempts": 5, "mode": "standard"}, connect_timeout=5,
                    read_timeout=30, s3={"addressing_style": "path"})
    # A session of its own: boto3's default session keeps the credentials it first found.
    return boto3.session.Session().client("s3", endpoint_url=endpoint_url, config=config)


def error_code(exc: BaseException) -> str | None:
    """The S3 error code of a botocore ``ClientError`` (None for any other exception)."""
    response = getattr(exc, "response", None)
    if not isinstance(response, dict):
        return None
    return str(response.get("Error", {}).get("Code", "")) or None


class S3Objects:
    """The tile objects under one location: listing, reading and writing whole objects."""

    def __init__(self, location: S3Location, client: Any) -> None:
        self.location = location
        self.client = client

    def list(self, start: str = "") -> Iterator[tuple[str, int, str]]:
        """``(key, size, etag)`` of every tile object directly under the prefix whose name
        starts with ``start`` (quarantined ones, in a sub-folder, are left out)."""
        base = self.location.key("")
        pages = self.client.get_paginator("list_objects_v2").paginate(
            Bucket=self.location.bucket, Prefix=base + start)
        for page in pages:
            for obj in page.get("Contents", []):
                key = str(obj["Key"])
                if key.endswith(SUFFIX) and "/" not in key[len(base):]:
                    yield key, int(obj["Size"]), str(obj["ETag"])

    def get(self, key: str, first: int | None = None) -> tuple[bytes, str] | None:
        """``(bytes, etag)`` of an object (only its ``first`` bytes if given), or None."""
        extra = {} if first is None else {"Range": f"bytes=0-{first - 1}"}
        try:
            got = self.client.get_object(Bucket=self.location.bucket, Key=key, **extra)
        except Exception as exc:
            code = error_code(exc)
            if code in ABSENT:
                return None
            if code == "InvalidRange":  # an empty object
                return b"", self.etag(key) or ""
            raise
        return got["Body"].read(), str(got["ETag"])

    def etag(self, key: str) -> str | None:
        try:
            return str(self.client.head_object(Bucket=self.location.bucket, Key=key)["ETag"])
        except Exception as exc:
            if error_code(exc) in ABSENT:
                return None
            raise

    def put(self, key: str, blob: bytes, **condition: str) -> str:
        """Store ``blob`` (``IfMatch``/``IfNoneMatch`` as given); the new object's ETag."""
        got = self.client.put_object(Bucket=self.location.bucket, Key=key, Body=blob,
                                     ContentType=encodings.TILE, **condition)
        return str(got["ETag"])

    def header(self, key: str) -> tuple[TileHeader, int, str] | None:
        """``(header, size the header implies, etag)`` read with one or two ranged GETs, or
        None when absent; TileFormatError when the object does not start like a tile."""
        got = self.get(key, HEAD_BYTES)
        if got is None:
            return None
        head, etag = got
        _, start = parse_prefix(head[:_PREFIX.size])
        if start > len(head):
            more = self.get(key, start)
            if more is None:
                return None
            head, etag = more
        header, fields, start = parse_header(head[:start])
        return header, start + int(fields["payload_len"]), etag
