"""A started process's objects are kept out of the collector's full passes; free pages go back."""

from __future__ import annotations

import ctypes.util
import gc
import subprocess
import sys
import weakref

import pytest

from app.core.heap import PeriodicTrim, limit_arenas, map_large_allocations, settle_heap


class _Node:
    """An object that can sit in a reference cycle."""

    def __init__(self) -> None:
        self.me: _Node | None = None


def test_objects_alive_at_start_are_frozen_and_later_ones_still_collected() -> None:
    gc.unfreeze()  # what other tests' apps froze: the count below is this test's own
    started = [_Node() for _ in range(1000)]
    try:
        settle_heap()
        assert gc.get_freeze_count() >= len(started)
        # a cycle made afterwards is garbage the collector still finds
        later = _Node()
        later.me = later
        alive = weakref.ref(later)
        del later
        gc.collect()
        assert alive() is None
    finally:
        gc.unfreeze()


def test_a_settled_process_still_collects_young_cycles_without_being_asked() -> None:
    before = gc.get_threshold()
    try:
        settle_heap()
        young = gc.get_threshold()[0]
        later = _Node()
        later.me = later
        alive = weakref.ref(later)
        del later
        # more new container objects than the young generation's threshold
        kept = [[] for _ in range(young + 1000)]
        assert alive() is None, "the cycle went with the next young collection"
        assert len(kept) > young
    finally:
        gc.unfreeze()
        gc.set_threshold(*before)


_FREED_BETWEEN_LIVE_CHUNKS = """
import ctypes, ctypes.util
from app.core.heap import trim_allocator

libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
libc.memset.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_size_t]

def resident_mb():
    return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20

blocks, pins = [], []
for _ in range(2000):  # 100 MB in 50 KB chunks, below the size glibc maps on its own
    p = libc.malloc(50_000)
    libc.memset(p, 1, 50_000)
    blocks.append(p)
    pins.append(libc.malloc(64))  # live chunks between them: free() cannot give them back
for p in blocks:
    libc.free(p)
before = resident_mb()
assert trim_allocator()
print(before - resident_mb())
"""


@pytest.mark.skipif(
    ctypes.util.find_library("c") is None or sys.platform != "linux", reason="glibc's allocator"
)
def test_trimming_returns_freed_pages_that_live_chunks_hold_in_the_heap() -> None:
    out = subprocess.run(
        [sys.executable, "-c", _FREED_BETWEEN_LIVE_CHUNKS],
        capture_output=True,
        text=True,
        check=True,
    )
    released_mb = float(out.stdout)
    assert released_mb > 60.0


_MAPPED_AFTER_A_LARGER_BLOCK_FREED = """
import ctypes, sys
from app.core.heap import map_large_allocations

class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks",
        "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL("libc.so.6")
libc.mallinfo2.restype = MallInfo2
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]

if sys.argv[1] == "fixed":
    assert map_large_allocations(128 * 1024)
libc.free(libc.malloc(4 * 2**20))  # a 4 MiB block, mapped on its own, then freed
mapped = libc.mallinfo2().hblks
block = libc.malloc(512 * 1024)
print(libc.mallinfo2().hblks - mapped)
libc.free(block)
"""


def _mapped_blocks_gained(mode: str) -> int:
    out = subprocess.run(
        [sys.executable, "-c", _MAPPED_AFTER_A_LARGER_BLOCK_FREED, mode],
        capture_output=True,
        text=True,
        check=True,
    )
    return int(out.stdout)


@pytest.mark.skipif(
    ctypes.util.find_library("c") is None or sys.platform != "linux", reason="glibc's allocator"
)
def test_a_fixed_threshold_keeps_large_blocks_out_of_the_heap_after_a_larger_one_is_freed() -> None:
    # glibc's own threshold rose to 4 MiB with the freed block: 512 KiB comes from the heap
    assert _mapped_blocks_gained("adaptive") == 0
    assert _mapped_blocks_gained("fixed") == 1


def test_no_threshold_leaves_the_allocator_as_it_is() -> None:
    assert map_large_allocations(0) is False


def test_a_periodic_trim_trims_once_per_period_and_never_at_zero() -> None:
    now = [100.0]
    trim = PeriodicTrim(5.0, clock=lambda: now[0])
    now[0] = 104.9
    assert trim() is False, "not a period since it was made"
    now[0] = 105.0
    assert trim() is (ctypes.util.find_library("c") is not None and sys.platform == "linux")
    now[0] = 109.0
    assert trim() is False, "not a period since the last trim"
    never = PeriodicTrim(0.0, clock=lambda: now[0])
    now[0] = 1e9
    assert never() is False


_ARENAS_OF_CONCURRENT_THREADS = """
import ctypes, sys, tempfile, threading
from app.core.heap import limit_arenas

limit = int(sys.argv[1])
assert limit_arenas(limit) == (limit > 0)
libc = ctypes.CDLL("libc.so.6")
libc.fopen.restype = ctypes.c_void_p
libc.fopen.argtypes = [ctypes.c_char_p, ctypes.c_char_p]
libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
libc.fclose.argtypes = [ctypes.c_void_p]
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]

started = threading.Barrier(6)
done = threading.Barrier(6)

def allocate():
    started.wait()  # all six threads alive and allocating at once
    blocks = [libc.malloc(4096) for _ in range(100)]
    done.wait()
    for p in blocks:
        libc.free(p)

threads = [threading.Thread(target=allocate) for _ in range(6)]
for t in threads:
    t.start()
for t in threads:
    t.join()
with tempfile.NamedTemporaryFile(suffix=".xml") as report:
    stream = libc.fopen(report.name.encode(), b"w")
    libc.malloc_info(0, stream)
    libc.fclose(stream)
    print(open(report.name).read().count("<heap nr="))
"""


@pytest.mark.skipif(
    ctypes.util.find_library("c") is None or sys.platform != "linux", reason="glibc's allocator"
)
def test_limited_arenas_are_shared_by_concurrent_threads() -> None:
    def arenas(limit: int) -> int:
        out = subprocess.run(
            [sys.executable, "-c", _ARENAS_OF_CONCURRENT_THREADS, str(limit)],
            capture_output=True,
            text=True,
            check=True,
        )
        return int(out.stdout)

    assert arenas(2) == 2
    assert arenas(0) > 2, "glibc's default gives concurrent threads arenas of their own"
    assert not limit_arenas(0)
