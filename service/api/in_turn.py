"""Work that holds a whole file in the API's memory, a few at a time.

Decoding an upload, simulating a frame from an HDR image, and answering a result with
anything but its stored EXR (a PNG preview, the W map, the codes, the histogram) each
read a whole image into the API process and work on copies of it: up to gigabytes at
4096 x 4096 (a colour simulate peaks at 3.6 GB). They share one bound,
``MCAM_MAX_CONCURRENT_DECODES``, because they share one budget, the process's memory:
separate bounds would let both kinds peak together. One more waits for a slot up to
``MCAM_DECODE_WAIT_S`` seconds on the event loop (holding no server thread), then gets
503 ``server_busy`` with ``Retry-After``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

from starlette.concurrency import run_in_threadpool

from service.api.errors import ApiError
from service.api.state import ServiceState

Result = TypeVar("Result")
#: Seconds a refused request is told to wait before asking again.
BUSY_RETRY_AFTER_S = 5


def server_busy(limit: int, wait_s: float) -> ApiError:
    """The 503 for a request that found all ``limit`` slots held for ``wait_s`` s."""
    return ApiError(
        503, "server_busy",
        f"the API is decoding uploads or making result previews {limit} at a time "
        f"(MCAM_MAX_CONCURRENT_DECODES) and none finished within {wait_s:g} s "
        "(MCAM_DECODE_WAIT_S); send the request again after Retry-After",
        headers={"Retry-After": str(BUSY_RETRY_AFTER_S)},
    )  # fmt: skip


async def decode_in_turn(state: ServiceState, work: Callable[..., Result], *args: Any) -> Result:
    """``work(*args)`` on a server thread while holding one of the API's decode slots
    (``MCAM_MAX_CONCURRENT_DECODES``), waited for up to ``MCAM_DECODE_WAIT_S`` seconds;
    503 ``server_busy`` if none came free. The slot is freed however the work ends, and
    only once it has: a request cancelled meanwhile waits for its thread to finish."""
    slots, wait_s = state.decode_slots, state.settings.decode_wait_s
    if not await slots.wait_take(wait_s):
        raise server_busy(slots.limit, wait_s)
    try:
        return await run_in_threadpool(work, *args)
    finally:
        slots.release()
