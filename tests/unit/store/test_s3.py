"""The S3 tile store (store/s3) against a real SeaweedFS on 127.0.0.1 (tests/s3server.py):
tiles round-trip in the file format, a damaged object is quarantined and never returned, and
writes are fenced by the object's ETag, so a store that missed a newer copy never overwrites
it.  Credentials reach boto3 through the AWS environment, as on a site."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sogm_service.client.session import free_tcp_endpoint
from sogm_service.store.directory import DirectoryStore
from sogm_service.store.s3 import S3Store, holds_all
from sogm_service.store.s3objects import S3Location, s3_client
from sogm_service.wire.errors import ConfigError, StoreConflictError
from sogm_service.wire.tilefile import tile_file_name
from tests.s3server import BUCKET

RES, T = 0.1, 16
KEY = "ism/r1/laser/obstacle"
pytestmark = pytest.mark.integration


@pytest.fixture
def s3env(seaweedfs: Any, monkeypatch: pytest.MonkeyPatch) -> Any:
    for name, value in seaweedfs.env.items():
        monkeypatch.setenv(name, value)
    return seaweedfs


def _store(s3env: Any, base: str, prefix: str = "site/a", **kw: Any) -> S3Store:
    return S3Store(f"s3://{BUCKET}/{base}/{prefix}", "lab", RES, T,
                   endpoint_url=s3env.endpoint_url, **kw)


def _data(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(-900, 900, (1, T, T)).astype(np.int16)


def _key(base: str, i: int, j: int) -> str:
    return f"{base}/site/a/{tile_file_name('lab', RES, T, i, j)}"


def _object(s3env: Any, base: str, i: int, j: int) -> bytes:
    return bytes(s3env.client().get_object(Bucket=BUCKET, Key=_key(base, i, j))["Body"].read())


def test_tiles_round_trip_with_their_header(s3env: Any) -> None:
    base = s3env.new_prefix()
    store = _store(s3env, base)
    marks = {KEY: (12.5, 77)}
    store.write(3, -2, ["r1/laser/obstacle"], _data(1), 12.5, applied=marks, version=9)
    store.write(0, 0, ["r1/laser/obstacle"], _data(2), 3.0)
    fresh = _store(s3env, base)  # another server on the same base
    index = fresh.index()
    assert set(index) == {(3, -2), (0, 0)} and not fresh.problems
    got = fresh.load(3, -2)
    assert got is not None and np.array_equal(got.data, _data(1))
    assert got.header.stamp == 12.5 and got.header.tile_version == 9
    assert dict((k, (t, d)) for k, t, d in got.header.applied) == marks
    assert fresh.read_bytes(3, -2) == _object(s3env, base, 3, -2)
    assert fresh.load(5, 5) is None
    other = _store(s3env, base, prefix="site/b")  # prefixes keep sites apart
    assert other.index() == {}


@pytest.mark.parametrize("damage", ["truncate", "flip", "empty"])
def test_a_damaged_object_is_quarantined_and_never_returned(s3env: Any, damage: str) -> None:
    base = s3env.new_prefix()
    store = _store(s3env, base)
    store.write(1, 1, ["r1/laser/obstacle"], _data(3), 1.0)
    blob = _object(s3env, base, 1, 1)
    bad = {"truncate": blob[:-7], "empty": b"",
           "flip": blob[:-3] + bytes([blob[-3] ^ 0xFF]) + blob[-2:]}[damage]
    key = _key(base, 1, 1)
    s3 = s3env.client()
    s3.put_object(Bucket=BUCKET, Key=key, Body=bad)
    fresh = _store(s3env, base)
    if damage == "flip":  # the header is intact: the index takes it, the load refuses it
        assert set(fresh.index()) == {(1, 1)}
        assert fresh.load(1, 1) is None
    else:
        assert fresh.index() == {}
    assert len(fresh.problems) == 1 and fresh.problems[0].moved_to is not None
    names = [o["Key"] for o in s3.list_objects_v2(Bucket=BUCKET, Prefix=base)["Contents"]]
    assert key not in names  # moved away
    held = [n for n in names
            if n.startswith(f"{base}/site/a/quarantine/") and n.endswith(".reason.txt")]
    assert len(held) == 1
    quarantined = s3.get_object(Bucket=BUCKET, Key=held[0][:-len(".reason.txt")])
    assert quarantined["Body"].read() == bad  # kept as it was, for a person to look at
    assert _store(s3env, base).index() == {}  # a later index does not see it again


def test_a_store_that_missed_a_newer_copy_never_overwrites_it(s3env: Any) -> None:
    """The fence: B saw the tile at ISM 1; A (the new owner) wrote ISM 2 since.  B's write of
    its ISM-1 copy is refused and the stored tile stays A's; once B's copy holds ISM 2 too (a
    replica that fused the same ISMs), it may write."""
    base = s3env.new_prefix()
    a, b = _store(s3env, base), _store(s3env, base)
    a.write(0, 0, ["r1/laser/obstacle"], _data(1), 1.0, applied={KEY: (1.0, 11)})
    assert b.load(0, 0) is not None  # b has seen it (its ETag)
    a.write(0, 0, ["r1/laser/obstacle"], _data(2), 2.0, applied={KEY: (2.0, 22)})
    newer = _object(s3env, base, 0, 0)
    with pytest.raises(StoreConflictError) as caught:
        b.write(0, 0, ["r1/laser/obstacle"], _data(9), 1.5, applied={KEY: (1.0, 11)})
    assert caught.value.code == "store_conflict" and caught.value.index == (0, 0)
    assert _object(s3env, base, 0, 0) == newer and b.writes_fenced == 1
    # A store that never saw the tile may not create it over an existing one either.
    c = _store(s3env, base)
    with pytest.raises(StoreConflictError):
        c.write(0, 0, ["r1/laser/obstacle"], _data(8), 0.5, applied={"ism/r2/x": (0.5, 1)})
    assert _object(s3env, base, 0, 0) == newer
    # B's copy now holds ISM 2 and one more key: it replaces the stored one.
    b.write(0, 0, ["r1/laser/obstacle"], _data(3), 2.0,
            applied={KEY: (2.0, 22), "ism/r2/x": (1.0, 5)})
    got = a.load(0, 0)
    assert got is not None and np.array_equal(got.data, _data(3))


def test_remove_deletes_only_the_object_it_saw(s3env: Any) -> None:
    base = s3env.new_prefix()
    a, b = _store(s3env, base), _store(s3env, base)
    a.write(2, 2, ["r1/laser/obstacle"], _data(1), 1.0, applied={KEY: (1.0, 1)})
    assert b.load(2, 2) is not None
    a.write(2, 2, ["r1/laser/obstacle"], _data(2), 2.0, applied={KEY: (2.0, 2)})
    assert b.remove(2, 2) is False  # changed since b saw it: left in place
    assert _store(s3env, base).load(2, 2) is not None
    assert a.remove(2, 2) is True
    assert _store(s3env, base).load(2, 2) is None


def test_a_readonly_store_writes_and_moves_nothing(s3env: Any) -> None:
    base = s3env.new_prefix()
    _store(s3env, base).write(0, 1, ["r1/laser/obstacle"], _data(1), 1.0)
    s3env.client().put_object(Bucket=BUCKET, Key=_key(base, 0, 1), Body=b"not a tile")
    ro = _store(s3env, base, readonly=True)
    assert ro.index() == {} and ro.problems and ro.problems[0].moved_to is None
    with pytest.raises(PermissionError):
        ro.write(0, 1, ["r1/laser/obstacle"], _data(1), 1.0)
    assert _object(s3env, base, 0, 1) == b"not a tile"


def test_credentials_come_from_the_aws_environment(s3env: Any,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    base = s3env.new_prefix()
    assert _store(s3env, base).index() == {}
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "someone-else")
    with pytest.raises(Exception, match=r"InvalidAccessKeyId|AccessDenied"):
        S3Store(f"s3://{BUCKET}/{base}/site/a", "lab", RES, T,
                client=s3_client(s3env.endpoint_url)).index()


def test_locations_and_marks() -> None:
    assert S3Location.parse("s3://sogm-tiles/site/a/") == S3Location("sogm-tiles", "site/a")
    assert S3Location.parse("s3://sogm-tiles").key("x.tile") == "x.tile"
    assert S3Location.parse("s3://sogm-tiles/p").url == "s3://sogm-tiles/p"
    for bad in ("sogm-tiles/p", "s3://", "s3://Upper/p", "file:///tmp"):
        with pytest.raises(ConfigError):
            S3Location.parse(bad)
    assert holds_all({"a": (2.0, 1)}, {"a": (1.0, 9)})
    assert holds_all({"a": (1.0, 9), "b": (1.0, 1)}, {"a": (1.0, 9)})
    assert not holds_all({"a": (1.0, 8)}, {"a": (1.0, 9)})  # same stamp, another ISM
    assert not holds_all({}, {"a": (1.0, 9)})


def _tiles(argv: list[str]) -> tuple[int, str]:
    from sogm_service.apps.tiletool import build_parser, run_tiles

    out = io.StringIO()
    return run_tiles(build_parser().parse_args(argv), out), out.getvalue()


def test_tiles_ls_export_and_import_on_a_url(s3env: Any, tmp_path: Path) -> None:
    """``sogm-service tiles`` on s3://bucket/prefix: ls lists the objects and flags a bad
    one, export mosaics them, import copies files in (fenced: a newer stored tile stays)."""
    base = s3env.new_prefix()
    url, ep = f"s3://{BUCKET}/{base}/site/a", ["--endpoint-url", s3env.endpoint_url]
    with DirectoryStore(tmp_path / "backup", "lab", RES, T) as local:
        local.write(0, 0, ["r1/laser/obstacle"], _data(1), 1.0, applied={KEY: (1.0, 1)})
        local.write(1, 0, ["r1/laser/obstacle"], _data(2), 1.0, applied={KEY: (1.0, 1)})
    code, text = _tiles(["import", str(tmp_path / "backup"), "--into", url, *ep])
    assert code == 0 and "2 imported, 0 skipped, 0 rejected" in text
    code, text = _tiles(["ls", url, *ep, "--verify"])
    assert code == 0 and "2 tile(s), 0 bad" in text and "i+0001_j+0000.tile" in text
    code, text = _tiles(["export", url, *ep, "--range", "0", "0", "1", "0",
                         "--out", str(tmp_path / "region.npy")])
    assert code == 0
    region = np.load(tmp_path / "region.npy")
    assert np.array_equal(region[:, :, :T], _data(1)) and np.array_equal(region[:, :, T:],
                                                                          _data(2))
    # A server fused ISM 2 into tile (0, 0) since: importing the old copy over it is refused.
    live = _store(s3env, base)
    live.index()
    live.write(0, 0, ["r1/laser/obstacle"], _data(5), 2.0, applied={KEY: (2.0, 2)})
    code, text = _tiles(["import", str(tmp_path / "backup"), "--into", url, *ep,
                         "--on-conflict", "overwrite"])
    assert code == 0 and "1 imported, 1 skipped" in text  # (1, 0) unchanged: same ISMs
    assert "tile (0, 0)" in text and "holds ISMs this copy lacks" in text
    got = live.load(0, 0)
    assert got is not None and np.array_equal(got.data, _data(5))
    s3env.client().put_object(Bucket=BUCKET, Key=_key(base, 3, 3), Body=b"junk")
    code, text = _tiles(["ls", url, *ep])
    assert code == 1 and "BAD" in text and "3 tile(s), 1 bad" not in text
    code, text = _tiles(["ls", f"s3://no-such-bucket-{base}/x", *ep])
    assert code == 2


def test_the_store_settings(tmp_path: Path) -> None:
    """``[store] url`` and ``endpoint_url`` as written; with ``[storage] directory`` too, or
    a URL that is not s3://bucket/prefix, the config is refused."""
    from sogm_service.service.config import load_config

    good = tmp_path / "good.toml"
    good.write_text('[store]\nurl = "s3://sogm-tiles/site-a"\n'
                    'endpoint_url = "http://127.0.0.1:8333"\n')
    config = load_config(good)
    assert (config.store.url, config.store.endpoint_url) == ("s3://sogm-tiles/site-a",
                                                            "http://127.0.0.1:8333")
    for bad in ('[store]\nurl = "s3://sogm-tiles/p"\n[storage]\ndirectory = "/tmp/t"\n',
                '[store]\nurl = "/var/lib/tiles"\n', '[store]\nendpoint_url = "127.0.0.1"\n'):
        path = tmp_path / "bad.toml"
        path.write_text(bad)
        with pytest.raises(ConfigError):
            load_config(path)


def test_serve_on_a_bucket_it_cannot_list_refuses_in_one_line(s3env: Any,
                                                              tmp_path: Path) -> None:
    config = tmp_path / "c.toml"
    config.write_text(f'[store]\nurl = "s3://no-such-bucket-{s3env.new_prefix()}/x"\n'
                      f'endpoint_url = "{s3env.endpoint_url}"\n'
                      f'[zenoh]\nlisten = ["{free_tcp_endpoint()}"]\n')
    done = subprocess.run([sys.executable, "-m", "sogm_service", "serve", "--config",
                           str(config)], capture_output=True, text=True, timeout=120,
                          env={**os.environ, **s3env.env})
    assert done.returncode == 2
    assert "cannot be listed" in done.stderr and "Traceback" not in done.stderr
