"""Process settings handed to every compute process (common/runtime.py)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from common.runtime import TORCH_PROCESS_ENV, apply_process_env, process_env

ROOT = Path(__file__).resolve().parents[1]


def test_process_env_defaults_and_user_values_win(monkeypatch):
    for key in TORCH_PROCESS_ENV:
        monkeypatch.delenv(key, raising=False)
    assert process_env() == TORCH_PROCESS_ENV
    monkeypatch.setenv("THP_MEM_ALLOC_ENABLE", "0")
    assert process_env()["THP_MEM_ALLOC_ENABLE"] == "0"
    apply_process_env()
    assert os.environ["THP_MEM_ALLOC_ENABLE"] == "0"


def test_launcher_sets_the_env_before_a_subcommand_loads_torch():
    code = (
        "import os, sys, launcher\n"
        "assert 'torch' not in sys.modules, 'importing the launcher loaded torch'\n"
        "launcher.main(['grippers', 'list', '--json'])\n"
        "print('THP', os.environ.get('THP_MEM_ALLOC_ENABLE'))\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in TORCH_PROCESS_ENV}
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "THP 1"


_REUSE = """
import ctypes, resource, sys
from common.runtime import apply_process_env
if sys.argv[1] == "apply":
    assert apply_process_env()
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
size = 256 << 20
for rep in range(2):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    buf = libc.malloc(size)
    ctypes.memset(buf, 1, size)
    libc.free(buf)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
print(faults)
"""


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_applied_process_env_keeps_freed_buffers_for_reuse():
    """With the settings applied in a running process, a freed 256 MiB block comes back without
    page faults; without them glibc unmaps it and every page faults again."""
    env = {k: v for k, v in os.environ.items() if k not in TORCH_PROCESS_ENV}
    faults = {}
    for mode in ("apply", "plain"):
        out = subprocess.run([sys.executable, "-c", _REUSE, mode], cwd=ROOT, env=env, capture_output=True, text=True, check=True)
        faults[mode] = int(out.stdout.strip())
    assert faults["plain"] > 1000, faults
    assert faults["apply"] < 100, faults
