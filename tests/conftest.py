"""Shared test fixtures: the real data folder, devices, small synthetic walks."""

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


def small_walk(out: Path, *, duration_s: float, video_format: str, starfish_s: float = 0.2,
               background_frames: int = 4, size_wh: tuple[int, int] = (320, 240), noise: bool = True) -> Path:
    """A short synthetic 4-camera walk at 20 fps rendered into ``out`` (sequence folder with gt.npz)."""
    import dataclasses

    from torchtrack.synth.scene import SceneConfig
    from torchtrack.synth.sequence import RigConfig, SynthConfig, write_sequence

    scene = dataclasses.replace(SceneConfig(), noise_std=1 / 255) if noise else SceneConfig()
    cfg = SynthConfig(motion="walk", duration_s=duration_s, starfish_s=starfish_s, fps=20,
                      background_frames=background_frames, video_format=video_format,
                      rig=RigConfig(num_cameras=4, width=size_wh[0], height=size_wh[1]), scene=scene)
    return write_sequence(cfg, out, progress=False)
