"""The library call `torchtrack.track` (torchtrack.tracking.pipeline): what `torchtrack track` runs, with the
tracker's intra-op threads set for the call and restored after."""

from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
from conftest import small_walk

FAST = dict(refit_passes=0, log_every=0, workers=0)


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return small_walk(tmp_path_factory.mktemp("pipeline") / "seq", duration_s=0.4, video_format="png")


def test_import_torchtrack_stays_light_and_track_is_the_pipeline():
    code = ("import sys, torchtrack; assert 'torch' not in sys.modules, 'torch imported'; "
            "from torchtrack.tracking.pipeline import track; assert torchtrack.track is track; print('ok')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.stdout.strip() == "ok", out.stderr


def test_the_library_call_writes_what_the_cli_writes(seq, tmp_path):
    import torchtrack
    from torchtrack.cli import main
    from torchtrack.io.poses import load_poses

    result = torchtrack.track(seq, **FAST, progress=False)
    assert main(["track", str(seq), "--out", str(tmp_path / "cli"), "--refit-passes", "0", "--log-every", "0",
                 "--workers", "0"]) == 0
    cli = load_poses(tmp_path / "cli" / "poses.npz")
    assert result.poses.valid.all() and result.refinement_tracks == 1 and result.refits == ()
    np.testing.assert_array_equal(result.poses.angles, cli.angles)
    np.testing.assert_array_equal(result.poses.joints3d, cli.joints3d)
    assert set(result.poses.extra) == set(cli.extra)


def test_the_tracker_runs_with_the_threads_asked_for(seq, monkeypatch):
    import torchtrack
    from torchtrack.tracking.markerless import MarkerlessTracker

    seen = []
    step = MarkerlessTracker.step

    def recording(self, obs):
        seen.append(torch.get_num_threads())
        return step(self, obs)

    monkeypatch.setattr(MarkerlessTracker, "step", recording)
    before = torch.get_num_threads()
    torchtrack.track(seq, **FAST, stop=2, progress=False)  # the default: one thread
    assert seen and set(seen) == {1} and torch.get_num_threads() == before
    seen.clear()
    torchtrack.track(seq, **FAST, stop=2, progress=False, threads=None)  # as they are
    assert set(seen) == {before}


def test_nobody_in_the_video_is_an_error_naming_the_sequence(seq, tmp_path):
    import torchtrack
    from torchtrack.checks import InputError
    from torchtrack.tracking.pipeline import NothingTracked

    empty = tmp_path / "empty"
    shutil.copytree(seq, empty)
    shutil.rmtree(empty / "video")
    shutil.copytree(empty / "background", empty / "video")
    with pytest.raises(NothingTracked, match=f"none of the 4 frames of {empty} was tracked") as exc:
        torchtrack.track(empty, **FAST, progress=False)
    assert not exc.value.poses.valid.any()
    with pytest.raises(InputError, match="threads must be >= 1"):
        torchtrack.track(seq, **FAST, threads=0)
    with pytest.raises(InputError, match="frame_cache_mb must be >= 0"):
        torchtrack.track(seq, **FAST, frame_cache_mb=-1)


def test_a_given_background_is_the_one_tracked_on_and_each_pass_is_reported(seq):
    """``background=``: the track is the one on that model (here the model the folder's background frames give,
    built by hand: the same track as the call's own), and a different model changes it; ``on_pass`` hears of the
    one pass; a background and a track to re-estimate one from are refused together."""
    import torchtrack
    from torchtrack.background import BackgroundConfig, BackgroundModel
    from torchtrack.checks import InputError
    from torchtrack.io.sequence import SequenceFolder

    folder = SequenceFolder(seq)
    W, H = (int(round(float(v) * 0.5)) for v in folder.rig.image_size_wh[0])
    own = torchtrack.track(seq, **FAST, scale=0.5, progress=False)
    passes = []
    given = torchtrack.track(seq, **FAST, scale=0.5, progress=False, on_pass=lambda p, q: passes.append((p, q)),
                             background=BackgroundModel.from_folder(folder, BackgroundConfig(), size_wh=(W, H)))
    np.testing.assert_array_equal(given.poses.angles, own.poses.angles)
    assert [p for p, _ in passes] == [0] and passes[0][1].num_frames == own.poses.num_frames
    brighter = BackgroundModel.from_folder(folder, BackgroundConfig(), size_wh=(W, H))
    brighter.mean_yuv[:, 0] += 0.02  # every background pixel a little brighter: a different observation
    moved = torchtrack.track(seq, **FAST, scale=0.5, progress=False, background=brighter)
    assert not np.array_equal(np.nan_to_num(moved.poses.angles), np.nan_to_num(own.poses.angles))
    with pytest.raises(InputError, match="not both"):
        torchtrack.track(seq, **FAST, background=brighter, background_from_track=own.poses)


def test_the_observation_section_sets_the_grid_sensor_model(seq):
    """``observation: {bayes: {...}}`` reaches the grid (its capture volume stays the observation's); left out,
    the detection probability is the grid's default, and the tracking config's is the rig's (4 cameras: 0.99);
    unknown keys and ``min_views`` inside it are refused naming the section."""
    from torchtrack.background import BackgroundConfig, BackgroundModel
    from torchtrack.checks import InputError
    from torchtrack.io.sequence import SequenceFolder
    from torchtrack.synth.sequence import RigConfig, make_ring_rig
    from torchtrack.tracking.pipeline import load_config, observer_from_config

    folder = SequenceFolder(seq)
    bg = BackgroundModel.from_folder(folder, BackgroundConfig())
    given = observer_from_config(folder.rig, bg, {"bayes": {"pd": 0.9, "window": 3}, "min_views": 4}, "bayes", 0.05)
    assert (given.grid.config.pd, given.grid.config.window, given.grid.config.min_views) == (0.9, 3, 4)
    default = observer_from_config(folder.rig, bg, {}, "bayes", 0.05)
    assert folder.rig.num_cameras == 4 and default.grid.config.pd == 0.99
    assert default.grid.config.min_views == default.min_views == 3  # half of them, at least three
    tracking = load_config("markerless.yaml")["observation"]
    assert tracking["bayes"]["pd"] is None  # the rig's: 0.99 for these 4 cameras (tests/test_bayes.py: 7 and more)
    assert observer_from_config(folder.rig, bg, tracking, "bayes", 0.05).grid.config.pd == 0.99
    rig8 = make_ring_rig(RigConfig(num_cameras=8, width=32, height=24))
    bg8 = BackgroundModel.from_frames(torch.rand(5, 8, 3, 24, 32, generator=torch.Generator().manual_seed(0)))
    assert observer_from_config(rig8, bg8, tracking, "bayes", 0.1).grid.config.pd == 0.95  # 7 cameras and more
    assert observer_from_config(rig8, bg8, {}, "bayes", 0.1).grid.config.pd == 0.99
    for doc, match in (({"bayes": {"pdd": 0.9}}, "bayes.*pdd"), ({"bayes": {"min_views": 2}}, "bayes.*min_views"),
                       ({"bayes": {"pd": 1.5}}, "pd")):
        with pytest.raises(InputError, match=match):
            observer_from_config(folder.rig, bg, doc, "bayes", 0.05)


def test_the_tracking_config_keeps_each_cameras_foreground_with_the_bayesian_grid(seq):
    """``observation.silhouettes: null`` (the tracking config's): each observation of the Bayesian grid carries each
    camera's foreground, on rigs of 4 and 8 cameras, the hull's none; true and false say so on any rig; another
    value is refused, naming the key.
    The foreground kept is the pixels' evidence pooled per cell: a frame of the background's own mean has none."""
    from torchtrack.background import BackgroundConfig, BackgroundModel
    from torchtrack.checks import InputError
    from torchtrack.io.sequence import SequenceFolder
    from torchtrack.synth.sequence import RigConfig, make_ring_rig
    from torchtrack.tracking.pipeline import load_config, observer_from_config

    tracking = load_config("markerless.yaml")["observation"]
    assert tracking["silhouettes"] is None
    folder = SequenceFolder(seq)
    bg = BackgroundModel.from_folder(folder, BackgroundConfig())
    assert observer_from_config(folder.rig, bg, tracking, "bayes", 0.05).silhouettes  # 4 cameras
    assert not observer_from_config(folder.rig, bg, {**tracking, "silhouettes": False}, "bayes", 0.05).silhouettes
    assert not observer_from_config(folder.rig, bg, tracking, "hull", 0.05).silhouettes
    rig8 = make_ring_rig(RigConfig(num_cameras=8, width=32, height=24))
    frames = 0.5 + 0.01 * torch.randn(5, 8, 3, 24, 32, generator=torch.Generator().manual_seed(0))  # a grey room
    bg8 = BackgroundModel.from_frames(frames)
    observer = observer_from_config(rig8, bg8, tracking, "bayes", 0.1)
    assert observer.silhouettes
    assert not observer_from_config(rig8, bg8, {**tracking, "silhouettes": False}, "bayes", 0.1).silhouettes
    lit = torch.where(torch.arange(32) < 16, 1.0, 0.0).expand(1, 8, 3, 24, 32)  # half white, half black
    for images, any_fg in ((frames[:1], False), (lit, True)):
        sil = observer(images)[0].silhouettes
        assert sil is not None and tuple(sil.fg.shape) == (8, 6, 8)  # 4-pixel cells
        assert bool(sil.fg.any()) == any_fg
    with pytest.raises(InputError, match="silhouettes"):
        observer_from_config(rig8, bg8, {**tracking, "silhouettes": "yes"}, "bayes", 0.1)
