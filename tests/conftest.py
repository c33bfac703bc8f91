"""Shared pytest fixtures."""

import pytest

from common.config import Config, load_config


@pytest.fixture
def default_cfg() -> Config:
    """The packaged default config (configs/default.yaml)."""
    return load_config("default")


@pytest.fixture
def paper_cfg() -> Config:
    """The packaged paper-scale config (configs/paper.yaml)."""
    return load_config("paper")
