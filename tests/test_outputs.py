"""Output paths (torchtrack.io.outputs) and every command's use of them: nothing a user wrote is deleted or mixed
into, an earlier output of the same kind is replaced only with --overwrite, and every path is checked before any
work. Each refusal leaves what was there byte for byte."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from torchtrack.checks import InputError
from torchtrack.cli import main
from torchtrack.io.outputs import (JSON_REPORT, OBSERVE_DIR, POSES_FILE, SEQUENCE_DIR, TRACK_DIR, check_output,
                                   replacing)


def snapshot(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (hidden ones too) with its bytes."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def user_folder(path: Path) -> Path:
    path.mkdir(parents=True)
    (path / "notes.txt").write_text("my own notes\n")
    (path / "data").mkdir()
    (path / "data" / "take1.bin").write_bytes(os.urandom(64))
    return path


# ------------------------------------------------------------------------------------------------ check_output
def test_new_paths_and_empty_folders_are_written(tmp_path):
    assert check_output(tmp_path / "new" / "deeper", TRACK_DIR, False) is False
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / ".DS_Store").write_bytes(b"x")  # hidden entries do not count
    assert check_output(tmp_path / "empty", TRACK_DIR, False) is False
    assert check_output(tmp_path / "r.json", JSON_REPORT, False) is False


def test_a_folder_with_the_users_files_is_refused_even_with_overwrite(tmp_path):
    folder = user_folder(tmp_path / "mine")
    (folder / "poses.npz").write_bytes(b"looks like ours")
    before = snapshot(folder)
    for overwrite in (False, True):
        with pytest.raises(InputError, match=r"--out .*mine: holds files torchtrack did not write there "
                                             r"\(data, notes.txt\)"):
            check_output(folder, TRACK_DIR, overwrite)
    assert snapshot(folder) == before


def test_files_and_folders_in_each_others_place_are_refused(tmp_path):
    (tmp_path / "f").write_text("x")
    with pytest.raises(InputError, match="is a file; the track output is a folder"):
        check_output(tmp_path / "f", TRACK_DIR, True)
    with pytest.raises(InputError, match="is a folder; the evaluation report is a file"):
        check_output(tmp_path, JSON_REPORT, True, "--json")
    with pytest.raises(InputError, match=r"f is a file, not a folder"):
        check_output(tmp_path / "f" / "out", TRACK_DIR, False)


def test_an_earlier_output_is_replaced_only_with_overwrite(tmp_path):
    track = tmp_path / "track"
    (track / "tb").mkdir(parents=True)
    (track / "tb" / "events.out.tfevents.1.host").write_bytes(b"")
    np.savez(track / "poses.npz", joint_names=np.array(["a"]), joints3d=np.zeros((1, 1, 3)), valid=np.ones(1, bool))
    with pytest.raises(InputError, match="already holds a track output; pass --overwrite to replace it"):
        check_output(track, TRACK_DIR, False)
    assert check_output(track, TRACK_DIR, True) is True
    with pytest.raises(InputError, match="holds files torchtrack did not write there"):  # another kind's output
        check_output(track, OBSERVE_DIR, True)
    seq = tmp_path / "seq"
    seq.mkdir()
    (seq / "meta.toml").write_text("fps = 30\n")  # a user's recording: no [synth] table
    with pytest.raises(InputError, match="something other than a synthetic sequence"):
        check_output(seq, SEQUENCE_DIR, True)
    (seq / "meta.toml").write_text("fps = 30\n[synth]\nseed = 0\n")
    assert check_output(seq, SEQUENCE_DIR, True) is True


def test_file_outputs_are_recognised_by_content(tmp_path):
    mine = tmp_path / "start.npz"
    mine.write_bytes(b"PK not really a zip")
    with pytest.raises(InputError, match="exists and is not a poses file torchtrack wrote"):
        check_output(mine, POSES_FILE, True)
    ours = tmp_path / "ours.npz"
    np.savez(ours, joint_names=np.array(["a"]), joints3d=np.zeros((1, 1, 3)), valid=np.ones(1, bool))
    with pytest.raises(InputError, match="pass --overwrite"):
        check_output(ours, POSES_FILE, False)
    assert check_output(ours, POSES_FILE, True)
    report = tmp_path / "r.json"
    report.write_text(json.dumps({"pred": "a", "gt": "b"}))
    assert check_output(report, JSON_REPORT, True)
    report.write_text(json.dumps({"something": "else"}))
    with pytest.raises(InputError, match="is not an evaluation report torchtrack wrote"):
        check_output(report, JSON_REPORT, True)


def test_own_output_means_its_content_too(tmp_path):
    """A folder with the right names but a user's content is not torchtrack's: a poses.npz that is no poses file,
    a tb/ holding more than TensorBoard event files."""
    track = tmp_path / "track"
    (track / "tb" / "my_experiment").mkdir(parents=True)
    (track / "tb" / "my_experiment" / "events.out.tfevents.1").write_bytes(b"")
    with pytest.raises(InputError, match="something other than a track output"):
        check_output(track, TRACK_DIR, True)
    (track / "tb" / "my_experiment").rename(track / "tb" / "body_refit_1")
    assert check_output(track, TRACK_DIR, True)
    (track / "poses.npz").write_bytes(b"my own bytes")
    with pytest.raises(InputError, match="something other than a track output"):
        check_output(track, TRACK_DIR, True)


def test_an_earlier_output_left_aside_is_reported(tmp_path):
    track = tmp_path / "track"
    (track / ".replaced.abc123" / "tb").mkdir(parents=True)
    with pytest.raises(InputError, match=r"\.replaced\.abc123, an earlier output an interrupted run set aside"):
        check_output(track, TRACK_DIR, True)


def test_replacing_puts_the_earlier_output_back_when_the_run_fails(tmp_path):
    out = tmp_path / "track"
    (out / "tb").mkdir(parents=True)
    (out / "tb" / "events.1").write_bytes(b"old events")
    (out / "poses.npz").write_bytes(b"old poses")
    before = snapshot(out)
    for error in (RuntimeError("crash"), KeyboardInterrupt()):
        with pytest.raises(type(error)), replacing(out, TRACK_DIR):
            assert not (out / "poses.npz").exists() and not (out / "tb").exists()  # moved aside
            (out / "tb").mkdir()
            (out / "tb" / "events.2").write_bytes(b"new events")
            raise error
        assert snapshot(out) == before
    with replacing(out, TRACK_DIR):
        (out / "tb").mkdir()
        (out / "tb" / "events.2").write_bytes(b"new events")
    assert snapshot(out) == {"tb/events.2": b"new events"}  # the old run's events are gone, not mixed in


# ------------------------------------------------------------------------------------------------ commands
def test_synth_never_deletes_a_users_folder_or_file(tmp_path, capsys):
    folder = user_folder(tmp_path / "mine")
    before = snapshot(folder)
    small = ["--duration", "0.1", "--starfish", "0.1", "--cameras", "2", "--size", "64x48", "--background-frames",
             "1", "--format", "png"]
    for extra in ([], ["--overwrite"], ["--reuse"]):
        assert main(["synth", "--out", str(folder), *small, *extra]) == 2
        assert "holds files torchtrack did not write there (data, notes.txt)" in capsys.readouterr().err
    assert snapshot(folder) == before
    hidden = tmp_path / "hidden"
    hidden.mkdir()
    (hidden / ".env").write_text("SECRET=1\n")  # a folder holding only a hidden file is not empty
    assert main(["synth", "--out", str(hidden), *small, "--overwrite"]) == 2
    assert "(.env)" in capsys.readouterr().err and (hidden / ".env").read_text() == "SECRET=1\n"
    file = tmp_path / "a_file"
    file.write_bytes(b"precious")
    assert main(["synth", "--out", str(file), *small]) == 2
    assert "is a file" in capsys.readouterr().err and file.read_bytes() == b"precious"
    # its own earlier sequence: refused, then replaced with --overwrite
    seq = tmp_path / "seq"
    assert main(["synth", "--out", str(seq), *small]) == 0
    assert main(["synth", "--out", str(seq), *small, "--seed", "1"]) == 2
    assert "pass --overwrite" in capsys.readouterr().err
    assert main(["synth", "--out", str(seq), *small, "--seed", "1", "--overwrite"]) == 0
    assert "seed = 1" in (seq / "meta.toml").read_text()
    (seq / "video" / "my_take.txt").write_text("notes")  # a user's file inside it: no longer only ours
    assert main(["synth", "--out", str(seq), *small, "--overwrite"]) == 2
    assert "something other than a synthetic sequence" in capsys.readouterr().err
    assert (seq / "video" / "my_take.txt").read_text() == "notes"


@pytest.mark.parametrize("command", ["track", "observe"])
def test_track_and_observe_check_out_before_reading_anything(tmp_path, capsys, command):
    """--out names an existing file: refused at once (the sequence, which does not exist, is never opened)."""
    file = tmp_path / "out.npz"
    file.write_bytes(b"precious")
    assert main([command, str(tmp_path / "no_such_seq"), "--out", str(file)]) == 2
    err = capsys.readouterr().err
    assert "--out" in err and "is a file" in err and "no_such_seq" not in err and "Traceback" not in err
    assert file.read_bytes() == b"precious"


def test_eval_json_is_checked_before_the_report(tmp_path, capsys):
    pred = tmp_path / "p.npz"
    np.savez(pred, joint_names=np.array(["a"]), joints3d=np.zeros((1, 1, 3)), valid=np.ones(1, bool))
    assert main(["eval", str(pred), str(pred), "--json", str(tmp_path)]) == 2
    out = capsys.readouterr()
    assert out.out == "" and "--json" in out.err and "is a folder" in out.err and "Traceback" not in out.err


def test_init_pose_and_calib_convert_refuse_a_users_file(tmp_path, capsys):
    mine = tmp_path / "mine.npz"
    mine.write_bytes(b"my own npz")
    assert main(["init-pose", str(tmp_path / "any.trc"), "--out", str(mine), "--overwrite"]) == 2
    assert "not a poses file torchtrack wrote" in capsys.readouterr().err and mine.read_bytes() == b"my own npz"
    notes = tmp_path / "notes.toml"
    notes.write_text("title = 'my notes'\n")
    src = tmp_path / "calib.toml"
    src.write_text("")
    assert main(["calib", "convert", str(src), str(notes), "--overwrite"]) == 2
    assert "not a calibration file torchtrack wrote" in capsys.readouterr().err
    assert notes.read_text() == "title = 'my notes'\n"


def test_a_scripts_work_folder_is_deleted_only_when_the_script_wrote_it(tmp_path):
    from torchtrack.io.outputs import script_work_folder

    mine = user_folder(tmp_path / "mine")
    before = snapshot(mine)
    with pytest.raises(InputError, match="not the work folder of bench_busy"):
        script_work_folder(mine, "bench_busy")
    assert snapshot(mine) == before
    work = script_work_folder(tmp_path / "work", "bench_busy")
    (work / "seq").mkdir()
    (work / "seq" / "a").write_bytes(b"x")
    assert script_work_folder(work, "bench_busy", empty=False) == work  # a cache the script checks: kept
    assert (work / "seq" / "a").read_bytes() == b"x"
    with pytest.raises(InputError, match="not the work folder of bench_busy"):
        script_work_folder(mine, "bench_busy", empty=False)
    assert script_work_folder(work, "bench_busy") == work and snapshot(work) == {
        ".bench_busy": b"work folder of scripts/bench_busy.py\n"}
