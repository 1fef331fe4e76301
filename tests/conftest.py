"""Shared fixtures: the real data folder, a seeded generator, float dtypes."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parent.parent


def find_shared_data() -> Path | None:
    """The shared real data: ``$SVS_TORCH_DATA`` if set, else ``../shared/data`` beside the repository."""
    env = os.environ.get("SVS_TORCH_DATA")
    path = Path(env) if env else REPO_ROOT.parent / "shared" / "data"
    return path if (path / "MANIFEST.md").is_file() else None


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared data folder; a missing folder fails under CI (CI always has it) and skips elsewhere."""
    path = find_shared_data()
    if path is None:
        message = "shared data not found: set SVS_TORCH_DATA or place it at ../shared/data"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return path


@pytest.fixture
def generator() -> torch.Generator:
    return torch.Generator().manual_seed(1234)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request) -> torch.dtype:
    return request.param
