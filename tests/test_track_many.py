"""Several sequences tracked together (torchtrack.tracking.pipeline.track_many, `torchtrack track SEQ SEQ ...`):
each as alone, their track passes in lockstep; one that fails does not stop the others."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from conftest import small_walk
from torchtrack.checks import InputError
from torchtrack.cli import main
from torchtrack.io.poses import load_poses

FAST = dict(refit_passes=0, log_every=0)


@pytest.fixture(scope="module")
def walks(tmp_path_factory):
    root = tmp_path_factory.mktemp("many")
    a = small_walk(root / "walk_a", duration_s=1.2, video_format="png")
    b = small_walk(root / "walk_b", duration_s=0.8, video_format="png", size_wh=(256, 192))  # shorter, smaller
    return a, b


def test_sequences_in_lockstep_are_tracked_as_each_alone(walks, tmp_path, monkeypatch):
    """Two sequences of different lengths and image sizes and a missing one, in one batch: the missing one fails
    naming its folder, the other two come out as each alone (float32: the batch's rounding differs, so within
    3 mm on average; tests/test_lockstep.py checks the arithmetic in float64), and their frames went through
    batched steps of both."""
    import torchtrack.tracking.lockstep as lockstep
    from torchtrack.tracking.pipeline import track, track_many

    sizes = []
    step = lockstep.track_step

    def counting(sub, obs, *args, **kw):
        sizes.append(obs.points.shape[0])
        return step(sub, obs, *args, **kw)

    monkeypatch.setattr(lockstep, "track_step", counting)
    missing = tmp_path / "nowhere"
    results = track_many([walks[0], missing, walks[1]], batch_size=3, progress=False, **FAST)
    assert isinstance(results[1], InputError) and str(missing) in str(results[1])
    assert sizes.count(2) >= 3  # the two sequences stepped together (after their starts and races)
    for seq, got in zip(walks, (results[0], results[2])):
        alone = track(seq, progress=False, workers=0, **FAST)
        np.testing.assert_array_equal(got.poses.valid, alone.poses.valid)
        assert got.poses.valid.all()
        err = np.linalg.norm(got.poses.joints3d - alone.poses.joints3d, axis=-1).mean()
        assert err < 0.003, (seq, err)
    with pytest.raises(InputError, match="batch size"):
        track_many(list(walks), batch_size=0)


def test_the_cli_writes_each_sequence_into_its_own_folder_and_refuses_bad_batches(walks, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["track", str(walks[0]), str(walks[1]), "--out", str(out), "--refit-passes", "0", "--log-every",
                 "0", "--stop", "12", "--batch-size", "2"]) == 0
    for seq in walks:
        poses = load_poses(out / seq.name / "poses.npz")
        assert poses.num_frames == 12 and poses.valid.any()
    # one sequence that cannot be read: reported with its name, the other written
    broken = shutil.copytree(walks[1], tmp_path / "broken")
    (broken / "calibration.toml").unlink()
    out2 = tmp_path / "out2"
    capsys.readouterr()
    assert main(["track", str(walks[0]), str(broken), "--out", str(out2), "--refit-passes", "0", "--log-every", "0",
                 "--stop", "6"]) == 1
    err = capsys.readouterr().err
    assert "broken" in err and "calibration" in err
    assert (out2 / walks[0].name / "poses.npz").is_file() and not (out2 / "broken" / "poses.npz").exists()
    # bad batches: refused before any work, nothing written
    twin = shutil.copytree(walks[0], tmp_path / "other" / walks[0].name)
    afile = tmp_path / "a_file"
    afile.write_text("x")
    for more, args, message in (([], ["--batch-size", "0"], "batch-size"), ([twin], [], "two sequences are named"),
                                ([], ["--out", str(afile)], "is a file")):
        target = tmp_path / "never"
        cmd = ["track", str(walks[0]), str(walks[1]), *map(str, more), "--out", str(target), *args]
        assert main(cmd) == 2, args
        assert message in capsys.readouterr().err, args
        assert not target.exists()
    assert afile.read_text() == "x"
