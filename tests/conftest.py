"""Shared test fixtures: the real data folder, devices."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = (REPO / ".." / "shared" / "data").resolve()

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def shared_data(*parts: str) -> Path:
    """Path of a file in ../shared/data; skips the test with a reason when it is absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real data not available: {p} (../shared/data is absent on this machine)")
    return p


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    return torch.device(request.param)
