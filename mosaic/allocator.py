"""Keep freed memory for reuse: glibc's malloc otherwise hands the video's per-frame buffers
back to the system and faults them in again, zeroed, on the next frame.

Every frame allocates and frees the same few large arrays: the UNet's activations (a 660x352
frame's full-resolution level is ~15 MB a tensor), the descriptors' tables, the canvas tiles.
glibc serves such blocks by `mmap` (above its mmap threshold) or trims them off the heap top
(above its trim threshold), so each frame page-faults them in anew until glibc's dynamic
thresholds have risen far enough, which takes a few hundred frames: measured ~5,500 minor
faults and ~9 ms a frame in the detector on the 80-frame benchmark video, ~400 faults with the
thresholds raised. Raising them keeps the freed memory in the process for the next frame from
the start; memory is not returned between frames (a 2000-frame build's peak: 845 against
778 MB; its streaming rate, glibc's warm-up long over, is the same).

Process-wide and idempotent; a no-op off glibc, and where the user set either threshold
(MALLOC_MMAP_THRESHOLD_, MALLOC_TRIM_THRESHOLD_ or GLIBC_TUNABLES), which is left alone.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os

log = logging.getLogger(__name__)

M_TRIM_THRESHOLD = -1  # mallopt parameter numbers, <malloc.h>
M_MMAP_THRESHOLD = -3
#: Blocks up to this size come from the heap (glibc's maximum on 64-bit: 32 MiB).
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
#: Free memory kept at the heap top before it is returned to the system.
TRIM_THRESHOLD_BYTES = 512 * 1024 * 1024
_USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "GLIBC_TUNABLES")

_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds once per process; whether they are raised."""
    global _applied
    if _applied is None:
        _applied = _raise_thresholds()
    return _applied


def _raise_thresholds() -> bool:
    if any(name in os.environ for name in _USER_SETTINGS):
        return False
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):  # not glibc (musl, macOS, Windows)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    ok = bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES))
    ok &= bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
    log.debug("malloc thresholds raised: %s", ok)
    return ok
