"""Freed memory kept for reuse in a batch's processes (glibc's allocator only).

glibc hands an array of more than its *mmap threshold* to the system on every allocation and
gives it back when freed, and trims its heap's free top past a second threshold. The
threshold adapts as blocks are freed, so whether a frame's image-sized temporaries come
back as fresh pages, each a page fault (system time), depends on the order of earlier
allocations: a change elsewhere in a stage could add milliseconds of page faults per frame
to it. Fixed thresholds keep freed blocks up to :data:`KEPT_BLOCK_BYTES` in the heap.

The memory a process keeps so is the wrong thing to fork with: a forked worker's first
allocations reuse its parent's free blocks, and each page it writes there is copied first
(a copy-on-write fault, dearer than a fresh page's). A parent gives its free
memory back (:func:`release_free_memory`) before it forks its workers.
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
    libc = _glibc()
    if libc is None:
        return False
    ok = libc.mallopt(_M_MMAP_THRESHOLD, KEPT_BLOCK_BYTES) == 1
    return libc.mallopt(_M_TRIM_THRESHOLD, TRIM_BYTES) == 1 and ok


def release_free_memory() -> bool:
    """Give the heap's free pages back to the system (``malloc_trim``), before forking
    workers (see the module); False where the C library is not glibc."""
    libc = _glibc()
    if libc is None:
        return False
    libc.malloc_trim(0)  # returns whether any memory went back: either is fine
    return True


def _glibc() -> ctypes.CDLL | None:
    """glibc, or None elsewhere (macOS; musl has neither mallopt nor malloc_trim)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return None
    return libc if hasattr(libc, "mallopt") and hasattr(libc, "malloc_trim") else None
