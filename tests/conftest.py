"""Shared pytest fixtures."""

import pytest
import torch

from common.config import Config, load_config


@pytest.fixture
def default_cfg() -> Config:
    """The packaged default config (configs/default.yaml)."""
    return load_config("default")


@pytest.fixture
def paper_cfg() -> Config:
    """The packaged paper-scale config (configs/paper.yaml)."""
    return load_config("paper")


@pytest.fixture
def one_torch_thread():
    """Small models run faster on one torch thread on a shared machine; restored afterwards."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
