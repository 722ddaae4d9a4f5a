"""Freed memory kept for reuse in a batch's processes (glibc's allocator only).

glibc hands an array of more than its *mmap threshold* to the system on every allocation and
gives it back when freed, and trims its heap's free top past a second threshold. The
threshold adapts as blocks are freed, so whether a frame's image-sized temporaries come
back as fresh pages, each a page fault (system time), depends on the order of earlier
allocations: a change elsewhere in a stage could add milliseconds of page faults per frame
to it. Fixed thresholds keep freed blocks up to :data:`KEPT_BLOCK_BYTES` in the heap.
Elsewhere (macOS, musl) this does nothing.
"""

from __future__ import annotations

import ctypes
import sys

#: Blocks up to this size (bytes) come from the heap: glibc's own ceiling for its adaptive
#: threshold on 64-bit systems.
KEPT_BLOCK_BYTES = 32 << 20
#: Free memory at the heap's top past this (bytes) goes back to the system.
TRIM_BYTES = 128 << 20

# mallopt's parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def keep_freed_memory() -> bool:
    """Fix glibc's thresholds in this process (forked children inherit them); False where
    the C library is not glibc."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    ok = mallopt(_M_MMAP_THRESHOLD, KEPT_BLOCK_BYTES) == 1
    return mallopt(_M_TRIM_THRESHOLD, TRIM_BYTES) == 1 and ok
