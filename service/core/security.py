"""API keys with scopes, and a per-key rate limit shared by every API process through Redis.

Keys come from ``MCAM_API_KEYS`` (``KEY`` = read and submit, ``KEY:read``,
``KEY:submit``); when unset, one key is generated on first start and kept in
``<data_dir>/api_keys`` (mode 0600, one entry per line, same syntax).
Keys are never stored in Redis: rate-limit counters are keyed by a short hash.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import os
import secrets
from dataclasses import dataclass
from pathlib import Path

import redis

from models.errors import McamError
from service.core.config import Settings
from worker.private_dirs import make_private_dirs
from worker.redis_keys import rate_limit_key

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


def parse_api_keys(text: str) -> dict[str, frozenset[str]]:
    """Parse ``KEY[:scope]`` entries separated by commas or new lines into key -> scopes."""
    keys: dict[str, frozenset[str]] = {}
    for entry in text.replace("\n", ",").split(","):
        entry = entry.strip()
        if not entry:
            continue
        secret, _, scope = entry.partition(":")
        if not secret or any(ch.isspace() for ch in secret):
            raise ApiKeyConfigError(f"malformed API key entry {entry[:4]!r}...: use KEY[:scope]")
        if scope and scope not in SCOPES:
            raise ApiKeyConfigError(
                f"unknown API key scope {scope!r}; use one of: {', '.join(SCOPES)} "
                "(or no scope for both)"
            )
        keys[secret] = keys.get(secret, frozenset()) | frozenset([scope] if scope else SCOPES)
    return keys


def generate_key() -> str:
    """A new random key (256 bits, URL-safe)."""
    return secrets.token_urlsafe(32)


def ensure_key_file(data_dir: Path) -> tuple[Path, str | None]:
    """The key file in ``data_dir``, created with one new key (mode 0600) if absent; a
missing data dir is created owner-only (0700).

    Returns the path and the new key when one was generated (for printing), else None.
    """
    path = Path(data_dir) / KEY_FILE_NAME
    make_private_dirs(path.parent)
    secret = generate_key()
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        os.chmod(path, 0o600)
        return path, None
    with os.fdopen(fd, "w") as handle:
        handle.write(secret + "\n")
    return path, secret


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
            keys = parse_api_keys(path.read_text())
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
