"""Process settings that gpupro's CPU path needs to run at speed, applied once when gpupro is imported.

XLA:CPU allocates every buffer of a call afresh: outputs, and the temporaries of the loops inside it.
glibc's ``malloc`` serves blocks above its mmap threshold (128 KiB, raised on the fly up to 32 MiB) with
new mappings, which the kernel faults in and zeroes page by page, and unmaps them when they are freed, so
every call pays for its memory again. Measured on the 2-core CPU (JAX 0.10.2, glibc 2.36): ``rasterize``
of 100k triangles at 640×360 took 11,000 page faults and 20 ms of system time per call (62 → 50 ms without
them), of 10k triangles at 1920×1080 45,000 faults (130 → 64 ms). With the threshold at 1 GiB and the
heap's trimming off, freed blocks stay in the process and are reused: the process keeps its peak memory
instead of returning it to the system between calls.

``GPUPRO_KEEP_FREED_MEMORY=0`` in the environment leaves ``malloc`` as it is. Nothing is done where the C
library is not glibc (``mallopt`` is glibc's).
"""

from __future__ import annotations

import ctypes
import os
import platform

_M_TRIM_THRESHOLD = -1  # glibc's malloc.h
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 1 << 30
"""Bytes from which ``malloc`` maps blocks of their own (and unmaps them when freed)."""
TRIM_THRESHOLD = (1 << 31) - 1
"""Free bytes at the top of the heap from which ``free`` returns memory to the system (the largest int)."""


def keep_freed_memory() -> bool:
    """Sets glibc's ``malloc`` to keep freed memory for reuse (module docstring); returns whether it did.

    False where ``GPUPRO_KEEP_FREED_MEMORY`` is ``0``, or the C library is not glibc."""
    if os.environ.get("GPUPRO_KEEP_FREED_MEMORY", "1") == "0" or platform.libc_ver()[0] != "glibc":
        return False
    libc = ctypes.CDLL(None)  # the process's own symbols: the C library Python runs on
    mmap = libc.mallopt(_M_MMAP_THRESHOLD, ctypes.c_int(MMAP_THRESHOLD))
    trim = libc.mallopt(_M_TRIM_THRESHOLD, ctypes.c_int(TRIM_THRESHOLD))
    return bool(mmap and trim)


KEPT_FREED_MEMORY = keep_freed_memory()
"""Whether :func:`keep_freed_memory` took effect in this process."""
