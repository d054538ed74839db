"""API keys with scopes, and a per-key rate limit shared by every API process through Redis.

Keys come from ``MCAM_API_KEYS`` (``KEY`` = read and submit, ``KEY:read``,
``KEY:submit``); when unset, one key is generated on first start and kept in
``<data_dir>/api_keys`` (mode 0600, one entry per line, same syntax).
Keys are never stored in Redis: rate-limit counters are keyed by a short hash.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import math
import os
import secrets
import stat
import tempfile
from dataclasses import dataclass
from pathlib import Path

import redis

from models.errors import McamError
from service.core.config import Settings
from worker.private_dirs import make_private_dirs
from worker.redis_keys import rate_limit_key

log = logging.getLogger(__name__)

SCOPES: tuple[str, ...] = ("read", "submit")
KEY_FILE_NAME = "api_keys"
#: Length of a rate-limit window in seconds.
RATE_WINDOW_S = 60


class ApiKeyConfigError(McamError):
    """The operator's key configuration is malformed."""

    code = "invalid_configuration"
    http_status = 500


@dataclass(frozen=True)
class ApiKey:
    """An authenticated caller: ``id`` is a hash prefix (safe to log), never the key."""

    id: str
    scopes: frozenset[str]


def key_id(secret: str) -> str:
    """A short, stable, non-reversible name for a key (rate-limit counters, logs)."""
    return hashlib.sha256(secret.encode()).hexdigest()[:16]


def parse_api_keys(text: str, source: str = "MCAM_API_KEYS") -> dict[str, frozenset[str]]:
    """Parse ``KEY[:scope]`` entries separated by commas or new lines into key -> scopes.
    A malformed entry is named by its position in ``source`` (words for where ``text``
    was read), never by its text (a key is a secret)."""
    keys: dict[str, frozenset[str]] = {}
    entries = [entry.strip() for entry in text.replace("\n", ",").split(",")]
    for number, entry in enumerate((e for e in entries if e), start=1):
        secret, colon, scope = entry.partition(":")
        if not secret or any(ch.isspace() or not ch.isprintable() for ch in secret):
            raise ApiKeyConfigError(
                f"API key entry {number} of {source} is malformed: use KEY[:scope], a key of "
                "printable characters without spaces"
            )
        if colon and scope not in SCOPES:
            raise ApiKeyConfigError(
                f"API key entry {number} of {source} has the scope {scope!r}; use one of: "
                f"{', '.join(SCOPES)} (or no colon at all for both)"
            )
        keys[secret] = keys.get(secret, frozenset()) | frozenset([scope] if scope else SCOPES)
    return keys


def generate_key() -> str:
    """A new random key (256 bits, URL-safe)."""
    return secrets.token_urlsafe(32)


def ensure_key_file(data_dir: Path) -> tuple[Path, str | None]:
    """The key file in ``data_dir``, created with one new key (mode 0600) if absent; a
missing data dir is created owner-only (0700).

    The key is written and synced to a temporary file first, then linked into place,
    which fails if the file exists: two services starting at once on a fresh data dir,
    or a full disk, never leave an empty key file. Returns the path and the new key when
    one was generated (for printing), else None.
    """
    path = Path(data_dir) / KEY_FILE_NAME
    make_private_dirs(path.parent)
    if path.exists():
        _narrow_mode(path)
        return path, None
    secret = generate_key()
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{KEY_FILE_NAME}-")
    try:
        with os.fdopen(fd, "w") as handle:
            handle.write(secret + "\n")
            handle.flush()
            os.fsync(handle.fileno())
        os.link(temporary, path)
    except FileExistsError:
        return path, None  # another process made it first: its key stands
    finally:
        os.unlink(temporary)
    return path, secret


def _narrow_mode(path: Path) -> None:
    """Make the key file owner-only when others may read it. A file mounted read-only
    (a container secret) that is owner-only already is left alone; one others can read
    and that cannot be changed is logged."""
    if not stat.S_IMODE(path.stat().st_mode) & 0o077:
        return
    try:
        os.chmod(path, 0o600)
    except OSError as exc:
        log.warning("the API key file %s is readable by others and cannot be narrowed "
                    "to mode 0600: %s", path, exc.strerror)


def read_key_file(path: Path) -> dict[str, frozenset[str]]:
    """The keys in the key file (UTF-8, a byte-order mark allowed); a file that is not
    UTF-8 or holds no key is named with what to do."""
    data = path.read_bytes()
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ApiKeyConfigError(
            f"the API key file {path} is not UTF-8 text (byte {exc.start}); write one "
            "KEY[:scope] per line"
        ) from None
    keys = parse_api_keys(text, f"the API key file {path}")
    if not keys:
        raise ApiKeyConfigError(
            f"the API key file {path} holds no key: put KEY[:scope] lines in it, or delete "
            "it to have a new key generated"
        )
    return keys


@dataclass(frozen=True)
class KeyRing:
    """The accepted keys and their scopes."""

    keys: dict[str, frozenset[str]]

    @classmethod
    def from_settings(cls, settings: Settings) -> tuple[KeyRing, str | None]:
        """Keys from ``MCAM_API_KEYS``, else from the data-dir key file (generated if absent).

        The second value is a newly generated key (to print once), else None.
        """
        if settings.api_keys:
            keys = parse_api_keys(settings.api_keys)
            new = None
        else:
            path, new = ensure_key_file(settings.data_dir)
            keys = read_key_file(path)
        if not keys:
            raise ApiKeyConfigError(
                "no API keys configured: set MCAM_API_KEYS or put keys in the data dir's api_keys"
            )
        return cls(keys), new

    def authenticate(self, token: str) -> ApiKey | None:
        """The key matching ``token`` (constant-time comparisons), or None."""
        found: ApiKey | None = None
        for secret, scopes in self.keys.items():
            if hmac.compare_digest(secret.encode(), token.encode()):
                found = ApiKey(key_id(secret), scopes)
        return found


#: Keep a request in a key's log while it is younger than the window; a rejected request is
#: not logged, so a client that retries too early does not push its own wait further out.
#: Times are Redis's own clock (ms) unless the caller passes ``now_ms``, so API processes on
#: hosts with skewed clocks still share one window. Returns -1 when allowed, else ms to wait.
_SLIDING_WINDOW = """
local now_ms = tonumber(ARGV[1])
if now_ms == nil then
  local t = redis.call('TIME')
  now_ms = tonumber(t[1]) * 1000 + math.floor(tonumber(t[2]) / 1000)
end
local window_ms = tonumber(ARGV[2])
local limit = tonumber(ARGV[3])
redis.call('ZREMRANGEBYSCORE', KEYS[1], '-inf', now_ms - window_ms)
if redis.call('ZCARD', KEYS[1]) < limit then
  redis.call('ZADD', KEYS[1], now_ms, ARGV[4])
  redis.call('PEXPIRE', KEYS[1], window_ms)
  return -1
end
local oldest = redis.call('ZRANGE', KEYS[1], 0, 0, 'WITHSCORES')
return tonumber(oldest[2]) + window_ms - now_ms
"""


class RateLimiter:
    """At most ``per_minute`` requests per key in any sliding 60 s window, logged in Redis
    so every API process shares the budget (no burst of twice the limit at a window edge)."""

    def __init__(self, client: redis.Redis, per_minute: int) -> None:
        self.per_minute = per_minute
        self._check = client.register_script(_SLIDING_WINDOW)

    def retry_after(self, key: ApiKey, now_s: float | None = None) -> int | None:
        """Count one request at ``now_s`` (s since the epoch; default: Redis's clock);
        seconds until the oldest logged request leaves the window when over the limit,
        else None (and the request is logged)."""
        now_ms = "" if now_s is None else str(round(now_s * 1000))
        wait_ms = int(
            self._check(
                keys=[rate_limit_key(key.id)],
                args=[now_ms, RATE_WINDOW_S * 1000, self.per_minute, secrets.token_hex(8)],
            )
        )
        if wait_ms < 0:
            return None
        return max(1, math.ceil(wait_ms / 1000))
