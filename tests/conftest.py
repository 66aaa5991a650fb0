"""Shared fixtures: where the real data lives, and which torch device tests run on."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` next to the repository; the test is skipped when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real RGB-D data not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="session")
def device() -> str:
    """"cuda" when a GPU is present, else "cpu" (everything must also run on the CPU)."""
    return "cuda" if torch.cuda.is_available() else "cpu"
