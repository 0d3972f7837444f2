"""The C allocator's settings for a process that drapes (glibc's ``mallopt``).

A drape allocates tens of megabytes of arrays that live for one request: the layer stage keeps a
face grid per frame of each outer layer (~1.6 MB each), the guard its candidate blocks, the final
stage its winding grids. With glibc's defaults, a block above the (adaptive) mmap threshold gets
pages of its own, and the heap's free top is handed back to the kernel past twice that threshold,
so every request touches fresh pages again: a minor fault and a zeroed page per 4 KB. Measured on
this project's 2-core machine (``inference.pipeline.drape``, 30 frames of 02_02, the neutral body,
one thread, four drapes after a warm one):

    T-shirt + jacket: 25-38 k minor faults a drape, 1.3-2.5 ms of kernel time a frame, 16.6-17.6 ms
    a frame; with the settings below: 0-30 faults, 0.0 ms, 15.0-15.5 ms a frame

Blocks below MMAP_THRESHOLD_BYTES come from the heap, and up to TRIM_THRESHOLD_BYTES of free heap
top stay mapped for the next request. Larger blocks (a long motion's frames) are still mapped and
unmapped one by one, so what a worker keeps beyond its live arrays is bounded by the trim
threshold plus the heap's fragmentation.

musl and other C libraries have no ``mallopt`` (or ignore it): then nothing changes.
"""
from __future__ import annotations

import ctypes
import logging
import sys

log = logging.getLogger(__name__)

# glibc's parameter numbers (malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
# Allocations from this size up get pages of their own (returned at once when freed).
MMAP_THRESHOLD_BYTES = 32 << 20
# Free memory at the heap's top kept for the next request, at most.
TRIM_THRESHOLD_BYTES = 128 << 20


def keep_freed_memory() -> bool:
    """Set the thresholds above for this process's heap; True where the C library took both
    (glibc), False elsewhere (no ``mallopt``, or not Linux)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library this process runs on
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    ok = mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES) == 1 and mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES) == 1
    if not ok:
        log.info("mallopt did not take the allocator settings; the defaults stay")
    return ok
