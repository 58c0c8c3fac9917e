"""Keep freed memory in the process for the next frame (glibc's malloc settings).

Every frame allocates the same large arrays again (the decoder's maps, the point cloud, the
mesh): 5-35 MB a frame at 1280x1024.  glibc's malloc serves blocks over its *mmap threshold* with
fresh pages from the kernel and gives freed memory at the top of the heap back once more than its
*trim threshold* is free.  Both thresholds adapt to the blocks a process has freed so far, so
whether the next frame's arrays land on pages the process already has, or on fresh ones that
fault in one by one when first written (about 2 us a 4 KiB page on this machine), depends on the
process's history.  ``scripts/bench_heap.py`` scans 1280x960 and 640x480 frames in turn, with and
without the settings below: a 1280x960 scan of the head took 65.4 against 43.5 ms (9 591 page
faults a round against 23).

:func:`keep_freed_memory` fixes both thresholds: blocks up to 32 MiB (glibc's largest mmap
threshold on 64-bit) come from the heap, and up to 512 MiB of freed heap stay in the process.
The price is resident memory: the process keeps the largest working set it has had.  The
``gbscan`` and ``gbcal`` commands and :class:`gbscan.scan.Scanner` call it; a program that
decodes frames with :func:`gbscan.decode.decode` alone can call it once.  Set the environment
variable ``GBSCAN_MALLOC=system`` to keep glibc's own settings.  Elsewhere than glibc (macOS,
Windows, musl) it does nothing.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os
import platform

#: mallopt parameters (glibc's malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
#: blocks up to this size come from the heap (glibc refuses more than 32 MiB on 64-bit)
MMAP_THRESHOLD_BYTES = 32 << 20
#: freed heap memory kept in the process
TRIM_THRESHOLD_BYTES = 512 << 20
#: the environment variable that turns it off (value "system")
ENV = "GBSCAN_MALLOC"

_state: dict[str, bool] = {}


def keep_freed_memory() -> bool:
    """Set glibc's malloc to reuse freed memory for the next frame (see the module docstring);
    returns True when the settings are in force (idempotent), False where they cannot be set
    (not glibc, ``GBSCAN_MALLOC=system``, mallopt refused)."""
    if "applied" in _state:
        return _state["applied"]
    ok = False
    if os.environ.get(ENV, "").strip().lower() != "system" and platform.system() == "Linux" \
            and platform.libc_ver()[0] == "glibc":
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            mallopt = libc.mallopt
            mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
            mallopt.restype = ctypes.c_int
            # (mallopt returns 1 on success; the mmap threshold first: setting either one ends
            # glibc's adaptive thresholds)
            ok = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and \
                bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
        except (OSError, AttributeError):
            ok = False
    _state["applied"] = ok
    return ok
