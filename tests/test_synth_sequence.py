"""A rendered sequence folder, read back through the sequence reader, agrees with its ground truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from conftest import shared_data
from torchtrack.cameras import load_calibration
from torchtrack.checks import InputError
from torchtrack.conventions import LANDMARKS
from torchtrack.io.poses import load_poses
from torchtrack.io.sequence import SequenceFolder
from torchtrack.synth.scene import SceneConfig
from torchtrack.synth.sequence import RigConfig, SynthConfig, make_ring_rig, write_sequence


def _cfg(**kw) -> SynthConfig:
    base = SynthConfig(motion="arm_raise", duration_s=0.4, starfish_s=0.4, fps=10, background_frames=3,
                       video_format="png", rig=RigConfig(num_cameras=3, width=96, height=72),
                       scene=dataclasses.replace(SceneConfig(), noise_std=0.0))
    return dataclasses.replace(base, **kw)


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return write_sequence(_cfg(), tmp_path_factory.mktemp("synth") / "seq", progress=False)


def test_ring_rig_looks_at_target():
    rig = make_ring_rig(RigConfig(num_cameras=5))
    uv, valid = rig.project(torch.tensor([[0.0, 0.0, 0.95]], dtype=torch.float64))
    assert bool(valid.all())
    # the target lands on the principal point, up to the mild distortion (none at the centre)
    torch.testing.assert_close(uv[:, 0], rig.K[:, :2, 2], atol=1e-6, rtol=0)
    centres = rig.centers()
    torch.testing.assert_close(centres[:, :2].norm(dim=1), torch.full((5,), 3.5, dtype=torch.float64))
    # the world's up projects upwards in every image (v decreases with height)
    uv_hi, _ = rig.project(torch.tensor([[0.0, 0.0, 1.5]], dtype=torch.float64))
    assert bool((uv_hi[:, 0, 1] < uv[:, 0, 1]).all())


def test_folder_contents_and_ground_truth(seq):
    rig = load_calibration(seq / "calibration.toml")
    assert rig.names == ["cam0", "cam1", "cam2"]
    gt = load_poses(seq / "gt.npz")
    T = round(0.8 * 10)
    assert gt.num_frames == T and gt.fps == 10
    assert list(gt.joint_names[:16]) == list(LANDMARKS)
    assert gt.valid.all()
    # the first frames are the starfish pose: wrists far out to the sides
    lm = gt.landmarks()
    assert np.linalg.norm(lm[0, LANDMARKS.index("l_wrist"), :2] - lm[0, 0, :2]) > 0.45
    with SequenceFolder(seq) as folder:
        assert folder.num_frames == T and folder.has_background


def test_body_pixels_where_ground_truth_projects(seq):
    """Blob centres projected with the calibration (independent of the renderer) fall on pixels that
    differ from the empty background, and points well outside the body do not."""
    rig = load_calibration(seq / "calibration.toml").double()
    gt = np.load(seq / "gt.npz")
    centres = torch.from_numpy(gt["blob_centres"]).double()  # (T, K, 3)
    big = gt["blob_semi_axes"].min(axis=1) > 0.07  # torso, head, pelvis, thighs: several pixels wide
    with SequenceFolder(seq) as folder:
        bg = folder.background_frames(3).mean(0)  # (C, 3, H, W)
        for t in (0, 5):
            img = folder.read_frame(t)
            diff = (img - bg).abs().amax(dim=1)  # (C, H, W)
            uv, valid = rig.project(centres[t][big])  # (C, Kb, 2)
            px = uv.round().long()
            for c in range(rig.num_cameras):
                for k in range(px.shape[1]):
                    if valid[c, k]:
                        assert diff[c, px[c, k, 1], px[c, k, 0]] > 0.05, (t, c, k)
            # far from the body: a point 1.5 m to the side of the pelvis, at floor level
            away, _ = rig.project(torch.tensor([[centres[t, 0, 0] + 1.5, centres[t, 0, 1], 0.0]],
                                               dtype=torch.float64))
            for c in range(rig.num_cameras):
                u, v = away[c, 0].round().long().tolist()
                if 0 <= u < 96 and 0 <= v < 72:
                    assert diff[c, v, u] < 0.05


def test_atomic_replace_and_bad_motion(seq, tmp_path):
    out = tmp_path / "s"
    out.mkdir()
    (out / "keep.txt").write_text("old")
    with pytest.raises(InputError, match="not one of"):
        write_sequence(_cfg(motion="moonwalk"), out, progress=False)
    assert (out / "keep.txt").read_text() == "old"  # nothing half-written
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".s.")]


def test_a_sequence_without_background_frames_is_read_as_one(tmp_path):
    """No empty frames (a recording made elsewhere): no background/ folder, in either video format; the reader
    finds none and the video frames are as the ground truth's count."""
    for fmt in ("mp4", "png"):
        out = write_sequence(_cfg(background_frames=0, video_format=fmt, duration_s=0.2, starfish_s=0.0),
                             tmp_path / fmt, progress=False)
        assert not (out / "background").exists()
        folder = SequenceFolder(out)
        assert folder.background_frames(5) is None and folder.num_frames == load_poses(out / "gt.npz").num_frames


def test_cli_synth(tmp_path, capsys):
    from torchtrack.cli import main

    rc = main(["synth", "--out", str(tmp_path / "c"), "--motion", "squat", "--duration", "0.2", "--starfish",
               "0.2", "--fps", "10", "--cameras", "2", "--size", "64x48", "--background-frames", "2"])
    assert rc == 0
    assert "wrote synthetic sequence" in capsys.readouterr().out
    assert (tmp_path / "c" / "video" / "cam1.mp4").is_file()
    assert main(["synth", "--out", str(tmp_path / "d"), "--size", "big"]) == 2
    assert "--size" in capsys.readouterr().err
    # --reuse keeps a folder that holds the same sequence, and renders one of other settings
    args = ["synth", "--out", str(tmp_path / "c"), "--motion", "squat", "--duration", "0.2", "--starfish", "0.2",
            "--fps", "10", "--cameras", "2", "--size", "64x48", "--background-frames", "2", "--reuse"]
    stamp = (tmp_path / "c" / "gt.npz").stat().st_mtime_ns
    assert main(args) == 0
    assert "kept" in capsys.readouterr().out
    assert (tmp_path / "c" / "gt.npz").stat().st_mtime_ns == stamp
    assert main(args + ["--seed", "3"]) == 0
    assert "wrote synthetic sequence" in capsys.readouterr().out


def test_saved_calibration_keeps_the_float64_rig(seq):
    """The renderer works in float32 on its own copy; the calibration written is the float64 ring rig."""
    saved = load_calibration(seq / "calibration.toml", dtype=torch.float64)
    ring = make_ring_rig(RigConfig(num_cameras=3, width=96, height=72))
    torch.testing.assert_close(saved.R_cam_world, ring.R_cam_world, atol=1e-12, rtol=0)
    torch.testing.assert_close(saved.t_cam_world, ring.t_cam_world, atol=1e-12, rtol=0)


def test_is_current_sees_other_settings_and_body_model(seq, tmp_path, monkeypatch):
    """A kept sequence is current for the config that rendered it, not for another one, nor after the body model
    (configs/blobs.yaml, body.urdf) changed, nor when half-written."""
    import shutil

    from torchtrack import resources
    from torchtrack.synth import sequence as synth_sequence

    assert synth_sequence.is_current(seq, _cfg())
    assert not synth_sequence.is_current(seq, _cfg(seed=1))
    assert not synth_sequence.is_current(seq, _cfg(video_format="mp4"))
    assert not synth_sequence.is_current(seq, _cfg(rig=RigConfig(num_cameras=4, width=96, height=72)))
    assert not synth_sequence.is_current(tmp_path / "missing", _cfg())
    # the built-in body model, also from inside a sequence folder (which holds its subject's own body.urdf)
    digest = synth_sequence.body_model_digest()
    monkeypatch.chdir(seq)
    assert synth_sequence.body_model_digest() == digest
    assert synth_sequence.is_current(seq, _cfg())
    # a scene and rig of other than default values (tuples, None, bools) read back equal
    scene = dataclasses.replace(SceneConfig(), noise_std=0.0, shadow=True, distractor=True, distractor_cameras=(0, 2),
                                illumination_change=0.25)
    other = _cfg(scene=scene, rig=RigConfig(num_cameras=3, width=64, height=48, radius_m=3.0, k1=0.0), seed=4)
    written = write_sequence(other, tmp_path / "other", progress=False)
    assert synth_sequence.is_current(written, other)
    assert not synth_sequence.is_current(written, dataclasses.replace(other, scene=dataclasses.replace(
        scene, distractor_cameras=None)))
    monkeypatch.undo()
    # another blobs.yaml: the kept sequence is no longer current
    configs = tmp_path / "configs"
    shutil.copytree(resources.CONFIG_DIR, configs)
    text = (configs / "blobs.yaml").read_text()
    moved = text.replace("offset: 0.45, along: 0.55", "offset: 0.50, along: 0.55")  # the shanks' blobs
    assert moved != text
    (configs / "blobs.yaml").write_text(moved)
    monkeypatch.setattr(resources, "CONFIG_DIR", configs)
    assert not synth_sequence.is_current(seq, _cfg())
    monkeypatch.undo()
    # a folder without its ground truth (a half-written copy) is not current
    half = tmp_path / "half"
    shutil.copytree(seq, half)
    (half / "gt.npz").unlink()
    assert not synth_sequence.is_current(half, _cfg())


def test_overhead_camera_looks_straight_down():
    """The overhead camera sits above the target and sees world +X as image +x; a point on the floor at
    (x, y) projects to the closed-form pinhole position (no distortion)."""
    rig = make_ring_rig(RigConfig(num_cameras=4, k1=0.0, overhead=True, overhead_height_m=3.0,
                                  overhead_hfov_deg=90.0))
    assert rig.names[-1] == "cam4" and rig.num_cameras == 5
    torch.testing.assert_close(rig.centers()[-1], torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64))
    f = 640 / 2 / np.tan(np.radians(45.0))
    pts = torch.tensor([[0.4, 0.0, 0.0], [0.0, 0.5, 1.0]], dtype=torch.float64)
    uv, valid = rig.project(pts)
    expect = torch.tensor([[319.5 + f * 0.4 / 3.0, 239.5], [319.5, 239.5 - f * 0.5 / 2.0]], dtype=torch.float64)
    assert bool(valid[-1].all())
    torch.testing.assert_close(uv[-1], expect, atol=1e-9, rtol=0)


def test_body_path_and_start_style_reach_the_ground_truth(tmp_path):
    """Bone scale, girth and colours change the rendered body; the path carries a motion other than the walk by the
    eased waypoint offsets; the starfish style sets the arms' abduction (read back from gt.npz, against the plain
    sequence's)."""
    from torchtrack.synth.sequence import BodyConfig

    import tomllib

    plain = load_poses(write_sequence(_cfg(motion="turn"), tmp_path / "a", progress=False) / "gt.npz")
    body = BodyConfig(bone_scale=(("l_thigh", 1.2),), girth=1.3, colours=(("chest", (0.1, 0.9, 0.2)),))
    cfg = _cfg(motion="turn", body=body, path=((0.0, 0.0, 0.0), (0.6, 1.0, -0.5)), starfish_arms=0.9)
    other = load_poses(write_sequence(cfg, tmp_path / "b", progress=False) / "gt.npz")
    height = [tomllib.loads((tmp_path / n / "meta.toml").read_text())["subject_height_m"] for n in "ab"]
    bones = list(plain.extra["bone_names"])
    ratio = other.extra["bone_lengths"] / plain.extra["bone_lengths"]
    assert ratio[bones.index("l_thigh")] == pytest.approx(1.2, rel=1e-5)
    assert ratio[bones.index("r_thigh")] == pytest.approx(1.0, rel=1e-5)
    girth = 1.3 * height[1] / height[0]  # the cross semi-axes also scale with the height the longer thigh adds
    np.testing.assert_allclose(other.extra["blob_semi_axes"][:, 1:], girth * plain.extra["blob_semi_axes"][:, 1:],
                               rtol=1e-3)
    # the pelvis moved by the path's offset: 0 at t = 0, the last waypoint from 0.6 s on, halfway at 0.3 s
    pelvis = plain.joint_names.index("pelvis")
    shift = other.joints3d[:, pelvis, :2] - plain.joints3d[:, pelvis, :2]
    np.testing.assert_allclose(shift[0], [0.0, 0.0], atol=1e-5)
    np.testing.assert_allclose(shift[3], [0.5, -0.25], atol=1e-5)  # 10 fps: smoothstep(0.5) = 0.5
    np.testing.assert_allclose(shift[-1], [1.0, -0.5], atol=1e-5)
    dof = list(plain.dof_names).index("l_shoulder_abd")
    assert other.angles[0, dof] == pytest.approx(0.9, abs=1e-5) and plain.angles[0, dof] == pytest.approx(1.25, abs=1e-5)
    with pytest.raises(InputError, match="unknown blob"):
        write_sequence(_cfg(body=BodyConfig(colours=(("tail", (0, 0, 0)),))), tmp_path / "c", progress=False)


def test_a_kept_capture_sequence_goes_stale_when_the_retargeting_changes(tmp_path, monkeypatch):
    """A sequence rendered from a capture is current for its config until the retargeting's revision changes; a
    procedural one does not depend on it."""
    from torchtrack.synth import sequence as synth_sequence

    capture = _cfg(motion=str(shared_data("mocap", "cmu", "131_01.bvh")), duration_s=0.2, starfish_s=0.0)
    written = write_sequence(capture, tmp_path / "capture", progress=False)
    assert synth_sequence.is_current(written, capture)
    procedural = write_sequence(_cfg(duration_s=0.2, starfish_s=0.0), tmp_path / "procedural", progress=False)
    monkeypatch.setattr(synth_sequence, "RETARGET_REVISION", synth_sequence.RETARGET_REVISION + 1)
    assert not synth_sequence.is_current(written, capture)
    assert synth_sequence.is_current(procedural, _cfg(duration_s=0.2, starfish_s=0.0))


def test_a_kept_walk_on_a_path_goes_stale_when_the_path_walk_changes(tmp_path, monkeypatch):
    """A walk on a path is current for its config until ``PATH_WALK_REVISION`` changes (a sequence kept from when
    the walk was carried along its path is not current); a walk without a path does not depend on it."""
    from torchtrack.skeleton import Skeleton
    from torchtrack.synth import sequence as synth_sequence

    walk = _cfg(motion="walk", duration_s=0.2, starfish_s=0.0, path=((0.0, 0.0, 0.0), (0.2, 0.3, 0.0)))
    written = write_sequence(walk, tmp_path / "walk", progress=False)
    circle = write_sequence(_cfg(motion="walk", duration_s=0.2, starfish_s=0.0), tmp_path / "circle",
                            progress=False)
    assert synth_sequence.is_current(written, walk)
    # walked once, not also carried: the root ends on the last waypoint, not twice as far
    skel, angles = synth_sequence.motion_angles(dataclasses.replace(walk, duration_s=1.0), Skeleton.from_urdf())
    np.testing.assert_allclose(angles[-1, skel.dof_index(["root_tx", "root_ty"])].numpy(), [0.3, 0.0], atol=1e-6)
    monkeypatch.setattr(synth_sequence, "PATH_WALK_REVISION", synth_sequence.PATH_WALK_REVISION + 1)
    assert not synth_sequence.is_current(written, walk)
    assert synth_sequence.is_current(circle, _cfg(motion="walk", duration_s=0.2, starfish_s=0.0))
