"""Peak memory of one call: CUDA's allocator statistics, or on a CPU the process's resident-set high-water mark.

tracemalloc does not see torch's CPU allocations, so on a CPU the peak is the rise of `VmHWM` (reset through
/proc/self/clear_refs) over the resident set just before the call. It counts every page the call touched,
allocator slack included; glibc's free heap pages are returned to the OS (malloc_trim) first, so that memory
an earlier call freed does not hide this call's allocations.
"""

import contextlib
import ctypes
import gc
from collections.abc import Callable

import torch

MIB = 1024**2


def synchronize(device: torch.device) -> None:
    """Waits for the work queued on `device` (a no-op on a CPU), so that a clock or a counter read after it
    sees the call finished."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _proc_status_kib(field_name: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field_name + ":"):
                return int(line.split()[1])
    raise KeyError(field_name)


def _release_free_heap() -> None:
    """Returns glibc's free heap pages to the OS (malloc_trim); a no-op elsewhere."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


def peak_memory_mib(fn: Callable[[], object], device: torch.device) -> float | None:
    """Runs `fn` once; returns its peak memory in MiB above the level before it (None where /proc is missing)."""
    if device.type == "cuda":
        synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
        fn()
        synchronize(device)
        return (torch.cuda.max_memory_allocated(device) - base) / MIB
    gc.collect()
    _release_free_heap()  # so that the call's allocations need new pages instead of reusing freed ones
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # resets VmHWM to the current VmRSS (Linux >= 4.0)
        base = _proc_status_kib("VmRSS")
    except OSError:
        fn()
        return None
    fn()
    return (_proc_status_kib("VmHWM") - base) / 1024
