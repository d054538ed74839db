"""API keys, the key file, and the Redis-backed rate limit (real redis-server)."""

from __future__ import annotations

import errno
import os
import stat
import threading
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from service.core.config import Settings
from service.core.security import (
    ApiKey,
    ApiKeyConfigError,
    KeyRing,
    RateLimiter,
    ensure_key_file,
    key_id,
    parse_api_keys,
)
from worker.embedded_redis import connect


def test_parse_scopes() -> None:
    keys = parse_api_keys("alpha, beta:read,\ngamma:submit,beta:submit")
    assert keys == {
        "alpha": frozenset({"read", "submit"}),
        "beta": frozenset({"read", "submit"}),
        "gamma": frozenset({"submit"}),
    }


@pytest.mark.parametrize(
    "text", ["zqx9secret:admin", ":read", "two words", "secretkey:", "ok,k\x00ey"]
)
def test_malformed_entries_are_refused_without_echoing_the_key(text: str) -> None:
    """'KEY:' (an unset scope variable) granted both scopes; errors showed the key's
    first four characters."""
    with pytest.raises(ApiKeyConfigError) as refused:
        parse_api_keys(text)
    secret = text.split(",")[-1].partition(":")[0]
    assert "entry" in refused.value.message
    assert not secret[:3] or secret[:3] not in refused.value.message


@given(st.text(alphabet="abcdefXYZ0123456789_-", min_size=1, max_size=40))
def test_any_plain_key_authenticates_only_itself(secret: str) -> None:
    ring = KeyRing(parse_api_keys(secret))
    assert ring.authenticate(secret) == ApiKey(key_id(secret), frozenset({"read", "submit"}))
    assert ring.authenticate(secret + "x") is None


def test_key_file_is_generated_once_with_mode_0600(tmp_path: Path) -> None:
    path, first = ensure_key_file(tmp_path / "data")
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    assert first is not None and path.read_text().strip() == first
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    again, second = ensure_key_file(tmp_path / "data")
    assert again == path and second is None and path.read_text().strip() == first


def test_two_services_starting_at_once_share_one_whole_key_file(tmp_path: Path) -> None:
    """The file was created empty and written after: the loser of the race (24 in 300
    tries) read it empty and refused to start."""
    for attempt in range(30):
        data = tmp_path / str(attempt)
        results: list[tuple[Path, str | None]] = []
        threads = [threading.Thread(target=lambda d=data, r=results: r.append(ensure_key_file(d)))
                   for _ in range(2)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        generated = [key for _, key in results if key is not None]
        assert len(generated) == 1
        assert (data / "api_keys").read_text() == generated[0] + "\n"
        assert [p.name for p in data.iterdir()] == ["api_keys"]  # no temporary left


def test_a_key_file_with_a_byte_order_mark_works(tmp_path: Path) -> None:
    (tmp_path / "api_keys").write_bytes("\ufeffbomkey-0123456789:read\n".encode())
    ring, _ = KeyRing.from_settings(Settings(_env_file=None, data_dir=tmp_path))
    assert ring.authenticate("bomkey-0123456789") is not None  # it read as '\ufeffbomkey-'


@pytest.mark.parametrize(
    ("content", "fragment"),
    [(b"Ren\xe9key\n", r"not UTF-8 text \(byte 3\)"), (b"", "holds no key"),
     (b"\n \n", "holds no key"),
     (b"ok-key\ntwo words\n", "entry 2 of the API key file .* malformed"),
     (b"ok-key:admin\n", "entry 1 of the API key file .* scope 'admin'")],
)
def test_an_unusable_key_file_is_named_with_what_to_do(
    tmp_path: Path, content: bytes, fragment: str
) -> None:
    """A Latin-1 file gave a bare traceback; an empty one (a full disk at creation) 'no
    API keys configured' without naming the file; a malformed entry was named like one
    of MCAM_API_KEYS ('API key entry 2 is malformed'), the file unnamed."""
    (tmp_path / "api_keys").write_bytes(content)
    with pytest.raises(ApiKeyConfigError, match=fragment) as refused:
        KeyRing.from_settings(Settings(_env_file=None, data_dir=tmp_path))
    assert str(tmp_path / "api_keys") in refused.value.message


def test_an_owner_only_key_file_is_not_touched(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A key file mounted read-only (a container secret) stopped the service: it was
    chmodded whatever its mode, and the read-only file system refused."""
    path, _ = ensure_key_file(tmp_path)

    def read_only(*_: object) -> None:
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(os, "chmod", read_only)
    assert ensure_key_file(tmp_path) == (path, None)


def test_keyring_from_settings(tmp_path: Path) -> None:
    ring, new = KeyRing.from_settings(Settings(_env_file=None, data_dir=tmp_path))
    assert new is not None and ring.authenticate(new) is not None
    ring, again = KeyRing.from_settings(Settings(_env_file=None, data_dir=tmp_path))
    assert again is None and ring.authenticate(new) is not None
    ring, none = KeyRing.from_settings(
        Settings(_env_file=None, data_dir=tmp_path / "x", api_keys="k1:read")
    )
    assert none is None and ring.authenticate("k1") == ApiKey(key_id("k1"), frozenset({"read"}))
    assert not (tmp_path / "x" / "api_keys").exists()


def test_rate_limit_counts_per_key_in_a_sliding_minute(redis_url: str) -> None:
    limiter = RateLimiter(connect(redis_url), per_minute=3)
    key, other = ApiKey("a" * 16, frozenset()), ApiKey("b" * 16, frozenset())
    start = 6000.0 + 55.0  # five seconds before a minute boundary: no fixed window helps
    assert [limiter.retry_after(key, start + dt) for dt in (0, 10, 20)] == [None] * 3
    assert limiter.retry_after(key, start + 21) == 39  # until the first request is 60 s old
    assert limiter.retry_after(other, start + 21) is None
    shared = RateLimiter(connect(redis_url), per_minute=3)  # another API process
    assert shared.retry_after(key, start + 59.5) == 1
    assert shared.retry_after(key, start + 60) is None  # the first request left the window
    assert limiter.retry_after(key, start + 60.5) == 10  # rejected requests were not logged


def test_rate_limit_uses_the_redis_clock_by_default(redis_url: str) -> None:
    limiter = RateLimiter(connect(redis_url), per_minute=2)
    key = ApiKey("c" * 16, frozenset())
    assert [limiter.retry_after(key) for _ in range(2)] == [None, None]
    assert 55 <= (limiter.retry_after(key) or 0) <= 60  # a slow machine may take seconds
