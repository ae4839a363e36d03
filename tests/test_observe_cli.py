"""`torchtrack observe` end to end on a tiny rendered sequence."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from torchtrack.cli import main
from torchtrack.synth.scene import SceneConfig
from torchtrack.synth.sequence import RigConfig, SynthConfig, write_sequence


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    cfg = SynthConfig(motion="squat", duration_s=0.3, starfish_s=0.2, fps=10, background_frames=4,
                      video_format="png", rig=RigConfig(num_cameras=4, width=160, height=120),
                      scene=dataclasses.replace(SceneConfig(), noise_std=1 / 255))
    return write_sequence(cfg, tmp_path_factory.mktemp("obs") / "seq", progress=False)


@pytest.mark.parametrize("model", ["bayes", "hull", "silhouette"])
def test_observe_writes_occupancy_and_logs(seq, tmp_path, model, capsys):
    out = tmp_path / model
    assert main(["observe", str(seq), "--out", str(out), "--model", model, "--voxel", "0.04",
                 "--log-every", "2"]) == 0
    occ = np.load(out / "occupancy.npz")
    assert list(occ["frame_index"]) == list(range(5))
    counts = np.diff(occ["frame_offsets"])
    assert (counts > 20).all()  # a body in every frame
    gt = np.load(seq / "gt.npz")
    # occupied voxels lie around the body: their mean near the ground-truth pelvis in x, y
    c0 = occ["centres"][: counts[0]]
    assert np.linalg.norm(c0[:, :2].mean(0) - gt["joints3d"][0, 0, :2]) < 0.15
    events = list((out / "tb").glob("events.out.tfevents.*"))
    assert events, "no TensorBoard event file"
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(out / "tb"))
    acc.Reload()
    assert "voxels" in acc.Tags()["scalars"]
    assert any(t.startswith("foreground/probability") for t in acc.Tags()["images"])


def test_observe_missing_sequence(tmp_path, capsys):
    assert main(["observe", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert "nope" in capsys.readouterr().err


def test_observe_without_background_frames_fill_static_subject(seq, tmp_path, caplog):
    """No background/ folder: the background is estimated from the video, and ``--fill-static-subject`` paints
    the subject's static parts out of it (logged per camera); a body is still found in every frame."""
    import logging
    import shutil

    bare = tmp_path / "bare"
    shutil.copytree(seq, bare, ignore=shutil.ignore_patterns("background"))
    out = tmp_path / "out"
    with caplog.at_level(logging.INFO, logger="torchtrack.background"):
        assert main(["observe", str(bare), "--out", str(out), "--voxel", "0.04", "--log-every", "0",
                     "--fill-static-subject"]) == 0
    assert "estimating it from" in caplog.text and "static subject painted out" in caplog.text
    counts = np.diff(np.load(out / "occupancy.npz")["frame_offsets"])
    assert (counts > 20).all()
