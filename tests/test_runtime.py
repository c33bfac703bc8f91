"""Process settings handed to every compute process (common/runtime.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

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
