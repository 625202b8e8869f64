"""Keep a long-running process lean: startup objects out of GC passes, large arrays in
mappings of their own, free pages returned."""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import time
from collections.abc import Callable

GC_THRESHOLDS = (50_000, 20, 10)
"""The cyclic collector's thresholds in a running process: a young collection after 50,000
new container objects instead of Python's 700. The API validates and forwards thousands of
samples a second, each a few objects, all freed by reference counting: at Python's
thresholds it spends much of its time in collections that free nothing, and carries fewer
updates (``bench/load.py`` at thousands of devices shows it). Objects in reference cycles
wait longer to be freed, never unboundedly."""


def settle_heap() -> None:
    """Collect, move every object alive now out of the collector's reach, and collect the
    young generation less often (``GC_THRESHOLDS``).

    A process that has started holds hundreds of thousands of long-lived objects (the app
    alone 200,000; its modules, sites and caches), and each full collection walked them
    all: a pause under load long enough to land in the latency tail. Frozen, they are
    never scanned again; what is created later is collected as usual.
    """
    gc.collect()
    gc.freeze()
    gc.set_threshold(*GC_THRESHOLDS)


def _libc_function(name: str) -> Callable[..., int] | None:
    """Return the C library's function ``name``, or None where it has none (glibc's
    ``malloc_trim`` and ``mallopt`` are not in macOS's, for one)."""
    library = ctypes.util.find_library("c")
    if library is None:
        return None
    try:
        return getattr(ctypes.CDLL(library), name)
    except (OSError, AttributeError):
        return None


_TRIM = _libc_function("malloc_trim")
_MALLOPT = _libc_function("mallopt")
M_MMAP_THRESHOLD = -3
"""``mallopt``'s parameter for the size from which glibc maps a request on its own."""


M_ARENA_MAX = -8
"""``mallopt``'s parameter for the most arenas (heaps for concurrent threads) glibc keeps."""


def limit_arenas(count: int) -> bool:
    """Let the C allocator keep at most ``count`` arenas in this process; False where the C
    library cannot, or for 0 (its default: eight a core).

    Call it before a second thread allocates: glibc fixes the limit when a thread first
    needs an arena of its own. The API runs one event loop, but reads the database and
    checks keys in a pool of threads, each of which glibc gives an arena of its own, and
    pages freed in one arena serve no other, so the API's resident memory creeps up with
    many arenas (``python -m bench.soak`` follows its trend over a long run).
    """
    if _MALLOPT is None or count <= 0:
        return False
    return bool(_MALLOPT(M_ARENA_MAX, count))


def map_large_allocations(threshold: int) -> bool:
    """Serve every C allocation of ``threshold`` bytes or more from a mapping of its own,
    returned to the system when freed; False where the C library cannot.

    glibc starts at 128 KiB but raises its threshold to the size of each mapped block
    freed (up to 32 MiB), so after a worker's first rounds its large transient arrays
    came from the heap, and the small long-lived chunks placed above them kept the heap
    growing while the bytes in use held steady. Setting the threshold at all stops the
    raising, and the heap stays flat (``python -m bench.soak`` follows the workers' memory).
    """
    if _MALLOPT is None or threshold <= 0:
        return False
    return bool(_MALLOPT(M_MMAP_THRESHOLD, threshold))


def trim_allocator() -> bool:
    """Hand the C allocator's free pages back to the system; False where it cannot.

    glibc keeps the pages of freed chunks mapped and resident: a process whose
    requests allocate and free arrays, SQLite pages and buffers of many sizes
    holds ever more of them. A worker that never trims grows under steady load;
    trimmed now and then it stays flat (``python -m bench.soak``).
    """
    if _TRIM is None:
        return False
    _TRIM(0)
    return True


class PeriodicTrim:
    """Trim the allocator from a process's own loop at most once every ``every_s`` wall
    seconds (0: never), so a worker's loop need not keep the time of its last trim."""

    def __init__(self, every_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.every_s = every_s
        self.clock = clock
        self.last = clock()

    def __call__(self) -> bool:
        """Trim if a period has passed since the last trim; True when it trimmed."""
        if not self.every_s or self.clock() - self.last < self.every_s:
            return False
        self.last = self.clock()
        return trim_allocator()
