"""Keep freed memory in the process heap, so numpy's frame-sized temporaries reuse pages.

glibc's malloc serves every block above 128 KiB with its own ``mmap`` and unmaps it on
``free``, and gives the top of the heap back to the kernel once more than 128 KiB of it
is free. A 256x256 float64 map is 512 KiB, so each temporary of the refinement, the
scene analysis or the temporal step faults its pages in afresh: on this project's
2-core VMs ``np.maximum(g, h - 1)`` on 256x256 maps took 360 us instead of 22 us
(2026-11-25). glibc raises its mmap threshold by itself after such frees, so how much
this costs depends on what the process ran before: auto at best took 75-83 ms a
val-256 frame after itoh, fast and balanced had run in the same process (as in a
worker) and 62-65 ms with the thresholds set, while a fresh process that runs only
best measured 63-66 ms either way. The networks' own times did not change.

:func:`keep_freed_memory` raises both thresholds (``mallopt``), so such blocks come from
the heap and stay there once freed: a process keeps up to :data:`TRIM_THRESHOLD_BYTES`
of freed memory for reuse. The command line (``mcam``, hence the API and every worker)
and the benchmarks call it once at start. Elsewhere than on glibc it changes nothing.
"""

from __future__ import annotations

import ctypes

#: ``mallopt`` parameters (glibc's ``malloc.h``).
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
#: Blocks up to this size come from the heap (glibc's largest allowed value on 64-bit:
#: a 2048x2048 float64 map).
MMAP_THRESHOLD_BYTES = 32 << 20
#: Free memory at the top of the heap kept for reuse before it is returned.
TRIM_THRESHOLD_BYTES = 128 << 20


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds (module doc). Returns whether both were
    set; False where the C library has no ``mallopt`` (nothing changed)."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    mmap_set = mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1
    trim_set = mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1
    return mmap_set and trim_set
