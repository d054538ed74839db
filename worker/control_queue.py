"""Control commands for a device's daemon: queued only while the daemon keeps up.

The API appends each accepted command to ``control:<device>``; the device's daemon
forwards the ones after its cursor (``control:<device>:done``) and moves the cursor on.
The stream is bounded, and a bound that trims the oldest entries would silently drop
commands the API had accepted while no daemon ran. :func:`queue_command` therefore
appends (in one Lua step) only while fewer than ``backlog`` commands wait beyond the
cursor, and the bound is kept well above that backlog, so a trim only ever removes
commands a daemon has already handled.
"""

from __future__ import annotations

import redis

from models.errors import McamError
from worker.device_registry import DeviceNotFoundError
from worker.redis_keys import DEVICES_SET, control_cursor_key, control_stream

#: Commands that may wait for a device's daemon; more are refused, not queued.
CONTROL_BACKLOG = 100
#: The control stream's bound, far above the backlog (handled commands are trimmed).
CONTROL_MAXLEN = 1000

# KEYS: stream, cursor, devices set. ARGV: backlog, maxlen, device, then field, value
# pairs. -1: the device is not registered (a forget came first); false: backlog full.
_QUEUE = """
if redis.call('SISMEMBER', KEYS[3], ARGV[3]) == 0 then return -1 end
local cursor = redis.call('GET', KEYS[2]) or '0-0'
local backlog = tonumber(ARGV[1])
local waiting = redis.call('XRANGE', KEYS[1], '(' .. cursor, '+', 'COUNT', backlog)
if #waiting >= backlog then return false end
return redis.call('XADD', KEYS[1], 'MAXLEN', '~', ARGV[2], '*', unpack(ARGV, 4))
"""


class ControlBacklogError(McamError):
    """Too many commands already wait for the device's daemon (it is stopped, say)."""

    code = "control_backlog_full"
    http_status = 503
    retry_after_s = 5


def queue_command(client: redis.Redis, device: str, fields: dict[str, str], *,
                  backlog: int = CONTROL_BACKLOG, maxlen: int = CONTROL_MAXLEN) -> str:
    """Append a command's ``fields`` to ``device``'s control stream; its entry id.

    Raises :class:`ControlBacklogError` when ``backlog`` commands already wait unread,
    so that nothing accepted is trimmed away before the daemon reads it, and
    :class:`DeviceNotFoundError` when the device is not registered (checked in the same
    step: a command accepted for a device being forgotten was skipped by its next
    daemon, its cursor gone)."""
    flat = [part for pair in fields.items() for part in pair]
    entry = client.eval(_QUEUE, 3, control_stream(device), control_cursor_key(device),
                        DEVICES_SET, backlog, maxlen, device, *flat)
    if entry == -1:
        raise DeviceNotFoundError(device)
    if entry is None:
        raise ControlBacklogError(
            f"{backlog} commands already wait for the daemon of device {device!r}, which "
            f"has not read them (is it running? see GET /v1/devices/{device}); retry once "
            "it has caught up"
        )
    return entry.decode() if isinstance(entry, bytes) else str(entry)
