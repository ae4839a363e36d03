"""The user documentation against the code: the README's commands run as printed (with short durations), and
docs/formats.md lists every key the writers write."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO, SHARED_DATA, small_walk

README = REPO / "README.md"
FORMATS = REPO / "docs" / "formats.md"
TORCHTRACK = f"{sys.executable} -m torchtrack.cli"


def readme_section(title: str) -> str:
    """The text of the README's ``## title`` section, up to the next ``## `` heading."""
    text = README.read_text(encoding="utf-8")
    m = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", text, flags=re.S | re.M)
    assert m, f"README.md has no section '## {title}'"
    return m.group(1)


def code_blocks(section: str, lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", section, flags=re.S)


def shell_lines(section: str) -> list[str]:
    """The commands of the section's bash blocks (comments and continuation lines joined)."""
    lines = []
    for block in code_blocks(section, "bash"):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split("  #")[0].strip()
            if line and not line.startswith("#"):
                lines.append(line)
    return lines


def shortened(line: str, out: Path) -> str:
    """``line`` runnable from the repository root without a shell setup: torchtrack through this interpreter,
    ``out/`` under ``out``, synthetic sequences a fraction of a second long and tracks a few frames long."""
    line = line.replace(".venv/bin/torchtrack", TORCHTRACK).replace(" out/", f" {out}/")
    line = re.sub(r"(?<=[ \"])out/", f"{out}/", line)
    if " synth " in line:
        line = re.sub(r"--duration \S+", "", line) + " --duration 0.1 --starfish 0.4"
    if " track " in line:
        line += " --stop 4"
    return line


def run(line: str) -> subprocess.CompletedProcess:
    res = subprocess.run(["bash", "-c", line], cwd=REPO, capture_output=True, text=True, timeout=1200)
    assert res.returncode == 0, f"README command failed: {line}\n{res.stdout[-2000:]}\n{res.stderr[-3000:]}"
    return res


def documented_keys(heading: str) -> set[str]:
    """Keys in backticks in the first column of the tables under the formats document's ``heading``."""
    text = FORMATS.read_text(encoding="utf-8")
    m = re.search(rf"^## {re.escape(heading)}.*?\n(.*?)(?=^## |\Z)", text, flags=re.S | re.M)
    assert m, f"docs/formats.md has no section '## {heading}'"
    keys = set()
    for row in re.findall(r"^\| (.*?) \|", m.group(1), flags=re.M):
        keys.update(re.findall(r"`([^`]+)`", row))
    return keys


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory) -> Path:
    """The README's synthetic demo, run as printed (shortened): returns its out/ folder."""
    out = tmp_path_factory.mktemp("readme") / "out"
    for line in shell_lines(readme_section("Track the synthetic demo")):
        if ".bvh" in line and not SHARED_DATA.exists():
            continue  # the CMU motion is in ../shared/data
        run(shortened(line, out))
    return out


def test_readme_is_a_short_guide_with_its_sections():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 300, f"README.md has {len(lines)} lines; the user guide should stay within ~300"
    for title in ("Install", "The two commands", "Track the synthetic demo", "Track your own recording",
                  "Evaluate against ground truth", "Inspect a run in TensorBoard", "Call it from Python",
                  "Observation models: which to pick", "Results", "Limitations"):
        readme_section(title)
    for link in re.findall(r"\]\(((?:docs|scripts)/[^)#]+)", "\n".join(lines)):
        assert (REPO / link).exists(), f"README.md links to {link}, which does not exist"


def test_every_option_the_readme_names_exists():
    """Options written in the README's prose (`--device cuda`, `--translation-scale 0.001`, ...) are options of
    the CLI (or of scripts/demo.sh, which passes its own on to `torchtrack track`)."""
    import argparse

    from torchtrack.cli import build_parser

    known, parsers = set(), [build_parser()]
    while parsers:
        p = parsers.pop()
        for action in p._actions:
            known.update(action.option_strings)
            if isinstance(action, argparse._SubParsersAction):
                parsers.extend(action.choices.values())
    text = "\n".join(ln for ln in README.read_text(encoding="utf-8").splitlines() 
                     if "bin/tensorboard" not in ln and "scripts/" not in ln and "bin/pip" not in ln)
    named = set(re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", text))
    assert named, "no option found in README.md"
    assert named <= known, f"README.md names options no command has: {sorted(named - known)}"


@pytest.mark.slow
def test_readme_demo_commands_run_as_printed(demo_run):
    from torchtrack.io.poses import load_poses

    poses = load_poses(demo_run / "demo" / "track" / "poses.npz")
    assert poses.num_frames == 4 and poses.valid.all()
    gt = load_poses(demo_run / "demo" / "seq" / "gt.npz")
    # started from the starfish frames: every landmark within 15 cm of the truth
    err = np.linalg.norm(poses.landmarks() - gt.landmarks()[:4], axis=-1)
    assert err.mean() < 0.05 and err.max() < 0.15, err.mean()
    assert (demo_run / "kick4" / "calibration.toml").is_file()
    assert any((demo_run / "demo" / "track" / "tb").iterdir())


@pytest.mark.slow
def test_readme_evaluation_and_python_sections_run(demo_run):
    import json

    for line in shell_lines(readme_section("Evaluate against ground truth")):
        res = run(shortened(line, demo_run))
        assert "MPJPE" in res.stdout
    report = json.loads((demo_run / "demo" / "eval.json").read_text())
    assert report
    (python,) = code_blocks(readme_section("Call it from Python"), "python")
    script = python.replace('"out/', f'"{demo_run}/').replace("stop=20, refit_passes=1", "stop=4, refit_passes=0")
    assert "stop=4" in script and str(demo_run) in script
    res = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=1200)
    assert res.returncode == 0, res.stderr[-3000:]
    from torchtrack.io.poses import load_poses

    assert load_poses(demo_run / "demo" / "python.npz").valid.all()


def test_readme_calibration_commands_run_as_printed(tmp_path):
    if not SHARED_DATA.exists():
        pytest.skip(f"real data not available: {SHARED_DATA}")
    section = readme_section("Track your own recording")
    lines = [ln for ln in shell_lines(section) if " calib " in ln]
    assert lines
    for line in lines:
        run(shortened(line, tmp_path / "out"))
    assert (tmp_path / "out" / "qualisys.toml").is_file()


@pytest.mark.slow
def test_readme_pose2sim_example_runs_as_printed(tmp_path):
    """The worked example's commands, its track a few frames long without refinement passes."""
    if not SHARED_DATA.exists():
        pytest.skip(f"real data not available: {SHARED_DATA}")
    section = readme_section("Track your own recording")
    lines = [ln for ln in shell_lines(section) if "p2s" in ln]
    assert any(" init-pose " in ln for ln in lines) and any(" track " in ln for ln in lines)
    out = tmp_path / "out"
    for line in lines:
        line = shortened(line, out)
        if " track " in line:
            line += " --refine-passes 0 --refit-passes 0"
        run(line)
    from torchtrack.io.poses import load_poses

    start = load_poses(out / "p2s" / "start.npz")
    assert start.num_frames == 1 and "body_urdf" in start.extra
    for name in ("track", "given"):  # started from the detected keypoints, and from the given pose
        track = load_poses(out / "p2s" / name / "poses.npz")
        assert track.num_frames == 4 and track.valid[0]
        # the figure the README quotes is printed by the evaluation script's --score, here on the first 4 frames
        res = run(f"{sys.executable} scripts/eval_pose2sim_tracking.py --score {out / 'p2s' / name / 'poses.npz'}")
        mpjpe = [float(m) for m in re.findall(r"MPJPE ([0-9.]+) mm", res.stdout)]
        # an unrefined first pass on the estimated background is rough, but on the subject (not metres off)
        assert len(mpjpe) == 2 and all(0 < m < 500 for m in mpjpe), res.stdout


def _keys(path: Path) -> set[str]:
    with np.load(path) as z:
        return set(z.files)


@pytest.mark.slow
def test_formats_document_lists_every_key_written(demo_run, tmp_path):
    poses_doc = documented_keys("`poses.npz`")
    written = _keys(demo_run / "demo" / "track" / "poses.npz")
    # the background refinement adds refinement_pass: a walk without background frames, one pass
    seq = small_walk(tmp_path / "seq", duration_s=1.0, video_format="png")
    shutil.rmtree(seq / "background")
    run(f"{TORCHTRACK} track {seq} --out {tmp_path / 'track'} --scale 1 --start 2 --stop 10 --log-every 0 "
        "--refine-passes 1 --refit-passes 0")
    refined = _keys(tmp_path / "track" / "poses.npz")
    assert "refinement_pass" in refined
    assert written | refined <= poses_doc, f"poses.npz keys missing from docs/formats.md: {(written | refined) - poses_doc}"
    gt = _keys(demo_run / "demo" / "seq" / "gt.npz")
    assert gt <= poses_doc, f"gt.npz keys missing from docs/formats.md: {gt - poses_doc}"
    run(f"{TORCHTRACK} observe {demo_run / 'demo' / 'seq'} --out {tmp_path / 'obs'} --stop 2")
    occ = _keys(tmp_path / "obs" / "occupancy.npz")
    occ_doc = documented_keys("`occupancy.npz`")
    assert occ <= occ_doc, f"occupancy.npz keys missing from docs/formats.md: {occ - occ_doc}"
    meta = tomllib.loads((demo_run / "demo" / "seq" / "meta.toml").read_text())
    for key, value in meta.items():  # top-level keys and tables
        key = f"[{key}]" if isinstance(value, dict) else key
        assert key in documented_keys("Sequence folder"), f"meta.toml key {key} missing from docs/formats.md"


def test_readme_marker_commands_run_as_printed(tmp_path):
    """The marker section's commands, the capture 1 s long, the video of balls 0.5 s after a 0.5 s starfish."""
    if not SHARED_DATA.exists():
        pytest.skip(f"real data not available: {SHARED_DATA}")
    lines = shell_lines(readme_section("Track markers"))
    assert [ln.split()[1] for ln in lines] == ["synth", "track", "eval", "synth", "detect", "track", "eval"]
    out = tmp_path / "out"
    for line in lines:
        line = line.replace(".venv/bin/torchtrack", TORCHTRACK)
        line = re.sub(r"(?<=[ \"])out/", f"{out}/", line)
        if " synth " in line:
            line += " --duration 0.5 --starfish 0.5" if "--markers" in line else " --duration 1.0"
        res = run(line)
        if " eval " in line:
            assert "MMTA@50mm" in res.stdout and "MMTP" in res.stdout
