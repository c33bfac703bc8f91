"""Process settings shared by every compute process of a run: the launcher itself and Ray workers.

Torch's CPU allocator hands large activation buffers back to the C library on every free, and
glibc returns blocks this large to the OS at once (they are mmap'ed), so each training step and
each inference faults its 3-D convolution activations back in and the kernel zeroes them again.
Two settings stop that:

- ``THP_MEM_ALLOC_ENABLE=1`` asks torch's allocator for transparent huge pages (read by torch on
  its first allocation): far fewer page faults per fresh buffer. Measured on the 2-core laptop,
  default config, one torch thread, batch-8 training step, median of 3: 6.06 s without, 5.60 s
  with; minor page faults 1.61 M -> 0.16 M, system time 9.6 s -> 5.1 s.
- ``MALLOC_MMAP_MAX_=0`` and a huge ``MALLOC_TRIM_THRESHOLD_`` make glibc serve every block from
  its heap and keep freed memory there, so a step reuses the previous step's buffers instead of
  asking the kernel for zeroed pages (the process keeps its peak memory, as a caching allocator
  does). glibc reads these at process start: Ray workers get them through the job's
  ``runtime_env``; the running launcher process applies the same values with ``mallopt``.
  Measured figures: tests/bench/bench_model.py ``--process-env`` against a run without it
  (docs/RESULTS.md). Memory: in a 42-minute default-config training run the learner's
  anonymous resident memory grew to 4.4 GB in its first 30 minutes and then stayed there.

Where the kernel offers no transparent huge pages, or the C library is not glibc, the
corresponding setting changes nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import platform

TORCH_PROCESS_ENV = {
    "THP_MEM_ALLOC_ENABLE": "1",
    "MALLOC_MMAP_MAX_": "0",
    "MALLOC_TRIM_THRESHOLD_": "1000000000000",
}
"""Environment every compute process gets unless the user set the variable already."""
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4
"""glibc ``mallopt`` parameter numbers (malloc.h)."""


def process_env() -> dict[str, str]:
    """:data:`TORCH_PROCESS_ENV` with the user's own values of those variables taking precedence."""
    return {key: os.environ.get(key, value) for key, value in TORCH_PROCESS_ENV.items()}


def _glibc_mallopt(env: dict[str, str]) -> bool:
    """Apply the ``MALLOC_*`` values of ``env`` to this running process; False where the C
    library is not glibc. ``mallopt`` takes an int: a trim threshold beyond it means never trim."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    trim = int(env["MALLOC_TRIM_THRESHOLD_"])
    ok = libc.mallopt(_M_MMAP_MAX, int(env["MALLOC_MMAP_MAX_"]))
    ok &= libc.mallopt(_M_TRIM_THRESHOLD, trim if trim < 2**31 else -1)
    if not ok:
        raise OSError(f"mallopt rejected MALLOC_MMAP_MAX_={env['MALLOC_MMAP_MAX_']} or MALLOC_TRIM_THRESHOLD_={trim}")
    return True


def apply_process_env() -> bool:
    """Set :func:`process_env` in this process; call before torch allocates its first tensor.
    Returns whether the glibc settings took effect in this process (see :func:`_glibc_mallopt`)."""
    env = process_env()
    os.environ.update(env)
    return _glibc_mallopt(env)


def cluster_address(address: str | None) -> str | None:
    """The Ray cluster a command joins: ``address`` (--address), else ``RAY_ADDRESS`` from the
    environment (set by ``ray job submit``, and what ``ray.init`` would join anyway), else None for a
    local instance."""
    return address or os.environ.get("RAY_ADDRESS") or None


def ray_init(address: str | None, num_cpus: int) -> str | None:
    """Join the Ray cluster at :func:`cluster_address`, or start a local one with ``num_cpus``
    logical CPUs; returns the cluster's dashboard URL (None for a local instance, which runs none).

    Every worker process (actors, learner, shards) gets :func:`process_env`.
    """
    import ray

    runtime_env = {"env_vars": process_env()}
    address = cluster_address(address)
    if address:
        context = ray.init(address=address, log_to_driver=False, runtime_env=runtime_env)
        return getattr(context, "dashboard_url", None) or None
    ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False, runtime_env=runtime_env)
    return None
