"""Per-thread scratch storage for the working arrays the kernels reuse frame after frame (no per-frame
allocation): `planes(name, key, make)` is the one cache every stage uses. Also `interleaved`, the one way a
parallel kernel shares its chunks of rows between the threads.

`threading.local()` cannot do this job inside GStreamer: its data lives in the Python thread state, and
the Python bindings create a thread state when a streaming thread calls into a Python element and destroy it
when the call returns (PyGILState_Ensure / PyGILState_Release). Under gst-launch-1.0 a `threading.local()`
is then empty at most frames and the planes are allocated again; at 1080p the fresh pages cost ~3,200 page
faults per frame (perf stat: 350 k faults for 90 frames against 58 k in-process), which makes nrreconstruct
`preview` take 22-26 ms per frame instead of 14-15 ms. `ThreadScratch` keys the storage by the OS thread
instead, so it outlives the Python thread state.
"""
from __future__ import annotations

import os
import threading

from numba import njit

MAX_THREADS = 64   # entries kept where thread liveness cannot be checked (no /proc/self/task)


def _alive(native_id: int) -> bool:
    return os.path.exists(f"/proc/self/task/{native_id}")


class ThreadScratch:
    """Attributes per OS thread (`threading.get_ident()`): a drop-in for `threading.local()` whose values
    survive the Python thread state being recreated around each GStreamer callback.

    Values stay private to the thread that stored them. When a thread stores for the first time, the entries
    of threads that have exited are dropped (Linux: `/proc/self/task`; elsewhere the oldest beyond
    MAX_THREADS), so pipelines started and stopped in a long-running process do not keep dead threads'
    planes."""

    __slots__ = ("_d", "_lock")

    def __init__(self) -> None:
        object.__setattr__(self, "_d", {})
        object.__setattr__(self, "_lock", threading.Lock())

    def __getattr__(self, name: str):
        entry = self._d.get(threading.get_ident())
        if entry is None or name not in entry[1]:
            raise AttributeError(name)
        return entry[1][name]

    def __setattr__(self, name: str, value) -> None:
        key = threading.get_ident()
        entry = self._d.get(key)
        if entry is None or entry[0] != threading.get_native_id():   # new thread, or a reused ident
            with self._lock:
                self._prune()
                entry = self._d[key] = (threading.get_native_id(), {})
        entry[1][name] = value

    def _prune(self) -> None:
        d = self._d
        if os.path.isdir("/proc/self/task"):
            for k in [k for k, (nid, _) in d.items() if not _alive(nid)]:
                del d[k]
        while len(d) >= MAX_THREADS:
            del d[next(iter(d))]

    def threads(self) -> int:
        """Number of threads holding values (for tests)."""
        return len(self._d)


_STORE = ThreadScratch()


def planes(name: str, key, make):
    """The calling OS thread's working arrays called `name`, made by `make()` the first time and again
    whenever `key` (e.g. the frame shape) differs from the one they were made for. Nothing returned to a
    caller of the core may live in them."""
    entry = getattr(_STORE, name, None)
    if entry is None or entry[0] != key:
        entry = (key, make())
        setattr(_STORE, name, entry)
    return entry[1]



@njit(cache=True, nogil=True, inline="always")
def interleaved(i, per, nt):
    """The chunk of prange index i (0 <= i < per x nt, per = ceil(chunks / nt)) when the chunks are
    interleaved over `nt` threads: prange hands each thread one contiguous run of i, so thread t gets chunks
    t, t + nt, ..., and work that sits at one end of the frame (highlights, dark areas) is shared. A result
    >= the chunk count is no chunk. `nt` is passed in by the kernel's caller (`numba.get_num_threads()`):
    calling it inside a kernel would stop numba caching the kernel."""
    return (i % per) * nt + i // per
