"""Background refinement from the track (torchtrack.tracking.refine) against plain loops and a synthetic scene."""

from __future__ import annotations

import dataclasses
import math
import shutil

import numpy as np
import pytest
import torch

from torchtrack.background import BackgroundConfig, BackgroundModel
from torchtrack.checks import InputError
from torchtrack.skeleton import Skeleton
from torchtrack.tracking.clearance import body_masks
from torchtrack.tracking.refine import RefineConfig, refined_background

from conftest import facing_pair_rig as _rig
from conftest import pose_at as _pose

W, H = 64, 64


@pytest.fixture(scope="module")
def skel() -> Skeleton:
    return Skeleton.from_urdf()


def test_refined_background_removes_the_ghost_of_a_subject_who_stands_still(skel):
    """A body stands in one place in 20 of 30 frames and elsewhere in the others: the temporal median keeps it
    as a ghost; re-estimated from the frames the true poses leave each pixel clearest of, the background is the
    room's (this scene's ground truth) wherever the body ever stood."""
    rig = _rig()
    gen = torch.Generator().manual_seed(1)
    room = 0.25 + 0.5 * torch.rand(2, 3, H, W, generator=gen)
    angles = torch.stack([_pose(skel, 0.0)] * 20 + [_pose(skel, 0.9, -0.9)] * 10)
    body = body_masks(rig, skel, angles)  # (30, 2, H, W): the body's silhouette
    shirt = torch.tensor([0.9, 0.1, 0.1])[None, None, :, None, None]
    frames = torch.where(body[:, :, None], shirt, room[None]) + 0.004 * torch.randn(30, 2, 3, H, W, generator=gen)
    frames = frames.clamp(0, 1)
    ghost = body[0] & ~body[-1]  # (2, H, W): covered where the subject stands still
    assert ghost.sum() > 200
    truth = BackgroundModel.from_frames(room[None].expand(5, -1, -1, -1, -1).contiguous())

    def error(bg):  # mean |mean - room| in YUV over the ghost pixels
        return float((bg.mean_yuv - truth.mean_yuv).abs().sum(1)[ghost].mean())

    plain = BackgroundModel.from_sequence(frames, BackgroundConfig())
    assert error(plain) > 0.3  # the ghost: the median is the shirt
    refined = refined_background(frames, angles, rig, skel, BackgroundConfig(), RefineConfig())
    assert error(refined) < 0.02, error(refined)
    # a track that is off by 10 cm still finds the room: its body is still nearer the pixels it covers
    off = refined_background(frames, angles + 0.1 * (torch.arange(angles.shape[1]) ==
                                                     skel.dof_names.index("root_ty")), rig, skel,
                             BackgroundConfig(), RefineConfig())
    assert error(off) < 0.05, error(off)


def _sways(skel, t: int) -> torch.Tensor:
    """The body swaying sideways, up to 0.2 m: the pixels nearest its feet stay near them."""
    a = _pose(skel, 0.0)
    a[skel.dof_names.index("root_ty")] = 0.2 * math.sin(t / 3)
    return a


@pytest.mark.parametrize("field, value, bones, seed", [
    ("near_fraction", 0.15, None, 2),  # the whole body: 20 frames in one place, 10 in another
    ("near_feet_fraction", 0.1, ("l_foot", "r_foot"), 4),  # the feet alone, of a body that sways
])
def test_refined_background_keeps_the_sequence_estimate_where_the_body_stays_near(skel, field, value, bones, seed):
    """near_fraction (near_feet_fraction): the pixels with fewer than clear_frames frames that far from the drawn
    body (feet), a plain count over cv2's distance transform of its masks, take the plain sequence estimate
    (passes 1-3), the others what they take without it."""
    import cv2

    rig = _rig()
    gen = torch.Generator().manual_seed(seed)
    room = 0.25 + 0.5 * torch.rand(2, 3, H, W, generator=gen)
    if bones is None:
        angles = torch.stack([_pose(skel, 0.0)] * 20 + [_pose(skel, 0.3, -0.3)] * 10)
    else:
        angles = torch.stack([_sways(skel, t) for t in range(30)])
    body = body_masks(rig, skel, angles)
    drawn = body_masks(rig, skel, angles, bones=bones)
    assert bool((body | ~drawn).all())  # the feet are part of the body
    shirt = torch.tensor([0.9, 0.1, 0.1])[None, None, :, None, None]
    frames = torch.where(body[:, :, None], shirt, room[None]) + 0.004 * torch.randn(30, 2, 3, H, W, generator=gen)
    frames = frames.clamp(0, 1)
    config = RefineConfig(blob_scale=1.0, **{field: value})
    near_px = value * max(H, W)
    far = np.zeros((2, H, W), int)  # frames at least near_px from the drawn body (feet), per pixel
    for t in range(30):
        for c in range(2):
            d = cv2.distanceTransform((~drawn[t, c]).numpy().astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
            far[c] += d >= near_px
    near = torch.from_numpy(far < config.clear_frames)
    assert 20 < int(near.sum()) < 0.8 * near.numel()
    plain = BackgroundModel.from_sequence(frames, BackgroundConfig())
    without = refined_background(frames, angles, rig, skel, BackgroundConfig(), dataclasses.replace(
        config, **{field: 0.0}))
    got = refined_background(frames, angles, rig, skel, BackgroundConfig(), config)
    for c in range(2):
        torch.testing.assert_close(got.mean_yuv[c][:, near[c]], plain.mean_yuv[c][:, near[c]])
        torch.testing.assert_close(got.mean_yuv[c][:, ~near[c]], without.mean_yuv[c][:, ~near[c]])
    assert not torch.allclose(got.mean_yuv, without.mean_yuv)


def test_refine_config_names_bad_settings():
    assert RefineConfig.from_dict(None) == RefineConfig()
    with pytest.raises(InputError, match="unknown background_refinement settings"):
        RefineConfig.from_dict({"pases": 2}, "my.yaml")
    for bad in ({"passes": -1}, {"blob_scale": 0.5}, {"clear_frames": 2}, {"clear_fraction": 0.0},
                {"near_fraction": -0.01}, {"near_fraction": 1.0}, {"near_feet_fraction": -0.1},
                {"near_feet_fraction": 1.0}, {"near_feet_fraction": float("nan")},
                {"passes": 2.5}, {"passes": True}, {"blob_scale": "big"}, {"keep": "best"}, {"keep": 1},
                {"patience": 0}, {"patience": 1.5}):
        with pytest.raises(InputError, match=next(iter(bad))):
            RefineConfig.from_dict(bad)
    for section in (False, 0, "off"):
        with pytest.raises(InputError, match="must be a mapping"):
            RefineConfig.from_dict(section, "my.yaml")


def test_initial_pose_needs_one_of_height_and_skeleton(skel):
    """(Tracking from a given skeleton: tests/test_bone_fit.py.)"""
    from torchtrack.tracking.markerless import MarkerlessTracker, TrackerConfig

    tracker = MarkerlessTracker(skel, TrackerConfig())
    tall = skel.scaled_to_height(1.93)
    with pytest.raises(InputError, match="height_m or its skeleton"):
        tracker.initialize_from_pose(skel.rest_angles())
    with pytest.raises(InputError, match="height_m or its skeleton"):
        tracker.initialize_from_pose(skel.rest_angles(), 1.8, skeleton=tall)


def test_track_cli_refines_an_estimated_background(tmp_path, capsys):
    """A synthetic sequence without background/ frames, from frame 2: the CLI tracks it three times (the first
    pass, one refinement, and the kept refined pass again for its logs), writes complete poses that name the kept
    pass and logs that pass only. The clip is small (4 cameras at 240x180, a background estimated from 24 frames):
    the tracker's fit checks may leave a few frames invalid (which ones varies with the threads' float sums)."""

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from torchtrack.cli import main
    from torchtrack.io.poses import load_poses
    from torchtrack.synth.scene import SceneConfig
    from torchtrack.synth.sequence import RigConfig, SynthConfig, write_sequence

    cfg = SynthConfig(motion="walk", duration_s=1.0, starfish_s=0.2, fps=20, background_frames=1,
                      video_format="png", rig=RigConfig(num_cameras=4, width=240, height=180),
                      scene=dataclasses.replace(SceneConfig(), noise_std=1 / 255))
    seq = write_sequence(cfg, tmp_path / "seq", progress=False)
    shutil.rmtree(seq / "background")
    gt = load_poses(seq / "gt.npz")
    errors = {}
    for passes in (1, 0):
        out = tmp_path / f"out{passes}"
        assert main(["track", str(seq), "--out", str(out), "--scale", "1", "--refine-passes", str(passes),
                     "--start", "2", "--log-every", "0", "--refit-passes", "0"]) == 0
        out_text = capsys.readouterr().out
        # one refinement: the first pass, the refined one, and the kept (refined) pass once more for the logs
        assert ("3 tracks of the background refinement, track 2 kept" in out_text) == (passes == 1), out_text
        poses = load_poses(out / "poses.npz")
        assert poses.num_frames == gt.num_frames - 2 and int((~poses.valid).sum()) <= 3, poses.valid
        assert poses.frame_index.tolist() == list(range(2, gt.num_frames))
        assert int(poses.extra.get("refinement_pass", 0)) == (2 if passes == 1 else 0)
        errors[passes] = float(np.nanmean(np.linalg.norm(poses.landmarks() - gt.landmarks()[2:], axis=-1)))
        acc = EventAccumulator(str(out / "tb"))
        acc.Reload()
        assert len(acc.Scalars("voxels")) == poses.num_frames  # one pass logged
    # this short walk moves through its whole clip, so its median has little ghost: refining must not hurt
    assert errors[1] < 0.08 and errors[1] < errors[0] + 0.005, errors
    assert main(["track", str(seq), "--out", str(tmp_path / "bad"), "--refine-passes", "-1"]) == 2
    assert "passes must be >= 0" in capsys.readouterr().err


def test_a_first_pass_that_tracks_nothing_is_returned_with_a_warning(monkeypatch, skel):
    """Nothing to render a body from: no refinement, the first pass's poses come back."""
    from types import SimpleNamespace

    from torchtrack.io.poses import Poses
    from torchtrack.io.video import DataWarning
    from torchtrack.tracking import refine
    from torchtrack.tracking.markerless import MarkerlessTracker, TrackerConfig

    T, D = 8, skel.num_dofs
    empty = Poses(fps=10.0, frame_index=np.arange(T), joint_names=["pelvis"], joints3d=np.full((T, 1, 3), np.nan),
                  dof_names=list(skel.dof_names), angles=np.full((T, D), np.nan, np.float32),
                  valid=np.zeros(T, bool), confidence=np.zeros((T, 1), np.float32))
    calls = []
    monkeypatch.setattr(refine, "track_sequence", lambda *a, **k: (calls.append(k) or empty, 1.0))
    folder = SimpleNamespace(num_frames=T, root="seq", fps=10.0)
    observer = SimpleNamespace(rig=_rig())
    with pytest.warns(DataWarning, match="tracked no frame"):
        poses, _, bg = refine.track_with_background_refinement(
            folder, "first background", lambda b: observer, MarkerlessTracker(skel, TrackerConfig()),
            RefineConfig(passes=2), BackgroundConfig())
    assert poses is empty and bg == "first background" and len(calls) == 1
    with pytest.raises(InputError, match="at least 5 frames"):
        refine.track_with_background_refinement(
            folder, "first background", lambda b: observer, MarkerlessTracker(skel, TrackerConfig()),
            RefineConfig(passes=2), BackgroundConfig(), start=4)


@pytest.fixture(scope="module")
def standing_then_walking(tmp_path_factory):
    """A rendered sequence whose subject holds the starfish pose for 16 of its 31 frames, then walks away: the
    temporal median keeps the starfish as a ghost. Its background/ frames are the truth; the copy without them
    is what ``background_from_track`` is for."""

    from torchtrack.synth.scene import SceneConfig
    from torchtrack.synth.sequence import RigConfig, SynthConfig, write_sequence

    cfg = SynthConfig(motion="walk", duration_s=3.0, starfish_s=3.2, fps=5, background_frames=5,
                      video_format="png", rig=RigConfig(num_cameras=4, width=160, height=120),
                      scene=dataclasses.replace(SceneConfig(), noise_std=1 / 255))
    root = tmp_path_factory.mktemp("standing")
    seq = write_sequence(cfg, root / "seq", progress=False)
    bare = root / "bare"
    shutil.copytree(seq, bare, ignore=shutil.ignore_patterns("background"))
    return seq, bare


def _track_file(seq, path, first: int = 0, **extra):
    """The ground truth of ``seq`` from frame ``first`` on as a track's poses.npz, with ``extra`` fields (the
    body: ``body_urdf=...``)."""

    from torchtrack.io.poses import load_poses, save_poses

    gt = load_poses(seq / "gt.npz")
    keep = slice(first, None)
    track = dataclasses.replace(gt, frame_index=gt.frame_index[keep], joints3d=gt.joints3d[keep],
                                angles=gt.angles[keep], valid=gt.valid[keep], confidence=gt.confidence[keep],
                                markers3d=None, marker_names=None,
                                extra={k: np.asarray(v) for k, v in extra.items()})
    save_poses(track, path)
    return path


def test_background_from_a_track_file_is_the_room_where_the_subject_stood(standing_then_walking, tmp_path):
    """Against the background measured from the empty frames: where the subject stood for most of the clip the
    plain estimate is the subject; from the track (its frames 2 on, with its body) it is the room."""
    from torchtrack.io.poses import load_poses
    from torchtrack.io.sequence import SequenceFolder
    from torchtrack.tracking.refine import background_from_track

    seq, bare = standing_then_walking
    body = (seq / "body.urdf").read_text()
    truth = BackgroundModel.from_folder(SequenceFolder(seq))
    folder = SequenceFolder(bare)
    gt = load_poses(seq / "gt.npz")
    skeleton = Skeleton(body)
    angles = torch.as_tensor(gt.angles, dtype=torch.float32)
    covered = body_masks(folder.rig.float(), skeleton, angles)  # (T, C, H, W)
    grown = body_masks(folder.rig.float(), skeleton, angles, blob_scale=1.5)
    # covered in most frames (the median is the subject), yet well clear of the body in enough frames to see the
    # room (the fewest a pixel's background is estimated from, and a margin)
    ghost = (covered.float().mean(0) > 0.5) & ((~grown[2:]).sum(0) >= 7)
    assert ghost.sum() > 300

    def error(bg):  # mean |mean - room| in YUV over the ghost pixels
        return float((bg.mean_yuv - truth.mean_yuv).abs().sum(1)[ghost].mean())

    plain = BackgroundModel.from_folder(folder)
    track = load_poses(_track_file(seq, tmp_path / "track.npz", first=2, body_urdf=body))
    refined = background_from_track(folder, track)
    assert error(plain) > 0.15, error(plain)
    assert error(refined) < 0.02, (error(refined), error(plain))
    # the template scaled to the track's height draws nearly the same body
    scaled = background_from_track(folder, load_poses(_track_file(seq, tmp_path / "h.npz", first=2,
                                                                  subject_height_m=skeleton.height())))
    assert error(scaled) < 0.05, error(scaled)


def test_background_from_a_track_names_what_is_missing(standing_then_walking, tmp_path, caplog):
    import logging

    from torchtrack.io.poses import load_poses
    from torchtrack.io.sequence import SequenceFolder
    from torchtrack.tracking.refine import background_from_track

    seq, bare = standing_then_walking
    folder = SequenceFolder(bare)
    # a sequence with background/ frames: the estimate from the track replaces them, with a warning
    short = load_poses(_track_file(seq, tmp_path / "short.npz", subject_height_m=1.75))
    with caplog.at_level(logging.WARNING, logger="torchtrack.tracking.refine"):
        background_from_track(SequenceFolder(seq), short)
    assert "has background/ frames" in caplog.text
    nobody = load_poses(_track_file(seq, tmp_path / "nobody.npz"))
    with pytest.raises(InputError, match="nobody.npz: no subject body .field 'body_urdf'"):
        background_from_track(folder, nobody, source=str(tmp_path / "nobody.npz"))
    unfitted = load_poses(_track_file(seq, tmp_path / "unfitted.npz", subject_height_m=float("nan")))
    with pytest.raises(InputError, match="unfitted.npz: no subject body .* 'subject_height_m': nan"):
        background_from_track(folder, unfitted, source=str(tmp_path / "unfitted.npz"))
    late = load_poses(_track_file(seq, tmp_path / "late.npz", first=folder.num_frames - 3, subject_height_m=1.7))
    with pytest.raises(InputError, match="spans 3 frames"):
        background_from_track(folder, late)

    elsewhere = dataclasses.replace(late, frame_index=late.frame_index + 100)
    with pytest.raises(InputError, match="are not frames of"):
        background_from_track(folder, elsewhere)
    with pytest.raises(InputError, match="holds no frame"):
        background_from_track(folder, dataclasses.replace(late, frame_index=late.frame_index[:0]))


def test_background_from_a_track_draws_each_sampled_frame_at_its_own_pose(standing_then_walking, tmp_path,
                                                                          monkeypatch):
    """A track of frames 2-30 with frames 20-23 missing: each sampled frame is drawn at the track's pose of that
    frame (looked up by frame number, not by row), and a frame the track lacks at NaN (covering every pixel)."""
    from torchtrack.io.poses import load_poses
    from torchtrack.io.sequence import SequenceFolder
    from torchtrack.tracking import refine

    seq, bare = standing_then_walking
    gt = load_poses(seq / "gt.npz")
    track = load_poses(_track_file(seq, tmp_path / "track.npz", first=2, subject_height_m=1.75))
    keep = ~np.isin(track.frame_index, [20, 21, 22, 23])
    track = dataclasses.replace(track, frame_index=track.frame_index[keep], joints3d=track.joints3d[keep],
                                angles=track.angles[keep], valid=track.valid[keep], confidence=track.confidence[keep])
    seen = {}
    monkeypatch.setattr(refine, "refined_background", lambda frames, angles, *a, **k: seen.setdefault("a", angles))
    refine.background_from_track(SequenceFolder(bare), track)
    angles = seen["a"].numpy()
    frames = list(range(2, gt.num_frames))  # the track's span, all sampled (fewer than max_frames)
    assert angles.shape == (len(frames), gt.angles.shape[1])
    for k, t in enumerate(frames):
        if 20 <= t <= 23:
            assert np.isnan(angles[k]).all(), t
        else:
            np.testing.assert_allclose(angles[k], gt.angles[t], atol=1e-6)


def test_observe_cli_with_the_background_from_a_track(standing_then_walking, tmp_path, capsys):
    """`torchtrack observe --background-from-track`: in the frames where the subject stands, the voxels are
    those of the background measured from empty frames, not of the ghost-ridden estimate."""
    from torchtrack.cli import main

    seq, bare = standing_then_walking
    track = _track_file(seq, tmp_path / "track.npz", body_urdf=(seq / "body.urdf").read_text())
    voxels = {}  # per standing frame, the set of occupied voxels (their centres in voxel units)
    for name, folder, extra in (("truth", seq, []), ("plain", bare, []),
                                ("track", bare, ["--background-from-track", str(track)])):
        out = tmp_path / name
        assert main(["observe", str(folder), "--out", str(out), "--voxel", "0.04", "--log-every", "0",
                     *extra]) == 0
        occ = np.load(out / "occupancy.npz")
        offsets, keys = occ["frame_offsets"], np.floor(occ["centres"] / 0.04).astype(int)
        voxels[name] = [set(map(tuple, keys[offsets[t]:offsets[t + 1]].tolist())) for t in range(16)]

    def iou(name):
        return np.mean([len(a & b) / len(a | b) for a, b in zip(voxels[name], voxels["truth"])])

    assert min(len(v) for v in voxels["truth"]) > 500
    assert iou("plain") < 0.5, iou("plain")  # the standing subject is the background
    assert iou("track") > 0.97, iou("track")
    bad = _track_file(seq, tmp_path / "bad.npz")
    assert main(["observe", str(bare), "--out", str(tmp_path / "bad"), "--background-from-track", str(bad)]) == 2
    assert "bad.npz: no subject body" in capsys.readouterr().err
    assert main(["observe", str(bare), "--out", str(tmp_path / "bad"), "--near-fraction", "0.02"]) == 2
    assert "give --background-from-track" in capsys.readouterr().err
    assert main(["observe", str(bare), "--out", str(tmp_path / "bad"), "--background-from-track", str(track),
                 "--near-fraction", "1.5"]) == 2
    assert "near-fraction must be in [0, 1)" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_track_cli_starts_from_the_background_of_an_earlier_track(standing_then_walking, tmp_path, capsys):
    """`torchtrack track --background-from-track`: from the plain estimate without the static-subject fill the
    subject who stands for the first 16 frames is the background (no frame of them tracked); with the fill (the
    default) they are tracked; from an earlier track's background (here the truth, with its body) they are all
    tracked, nearer the truth."""
    from torchtrack.cli import main
    from torchtrack.io.poses import load_poses

    seq, bare = standing_then_walking
    track = _track_file(seq, tmp_path / "track.npz", body_urdf=(seq / "body.urdf").read_text())
    gt = load_poses(seq / "gt.npz")
    runs = {}
    for name, extra in (("plain", ["--no-fill-static-subject"]), ("fill", []),
                        ("track", ["--background-from-track", str(track)])):
        out = tmp_path / name
        assert main(["track", str(bare), "--out", str(out), "--init-pose", str(track), "--refine-passes", "0",
                     "--scale", "1", "--log-every", "0", *extra]) == 0
        runs[name] = load_poses(out / "poses.npz")
    assert not runs["plain"].valid[:16].any()
    fill = runs["fill"]
    # the default, the static-subject fill, paints the standing subject out: every frame tracked (measured 30-48 mm)
    fill_error = np.linalg.norm(fill.landmarks() - gt.landmarks(), axis=-1).mean(-1)[:16]
    assert fill.valid[:16].all() and fill_error.max() < 0.06, fill_error
    poses = runs["track"]
    assert poses.valid[:16].all()
    # where the subject stands, within 1.5 cm (measured 5-8 mm); the walk after it, at 5 frames/s (15 cm a frame),
    # is too fast a motion for this test to score
    error = np.linalg.norm(poses.landmarks() - gt.landmarks(), axis=-1).mean(-1)[:16]
    assert error.max() < 0.015, error
    assert main(["track", str(bare), "--out", str(tmp_path / "bad"), "--init-pose", str(track),
                 "--background-from-track", str(tmp_path / "missing.npz")]) == 2
    assert "missing.npz" in capsys.readouterr().err


def _poses_at(landmarks: np.ndarray, valid: np.ndarray, skel, residual_m: float = 0.02):
    """A track whose 16 landmarks are ``landmarks (T, 16, 3)``, its IK residual ``residual_m`` in every frame."""
    from torchtrack.conventions import LANDMARKS
    from torchtrack.io.poses import Poses

    T = landmarks.shape[0]
    return Poses(fps=10.0, frame_index=np.arange(T), joint_names=list(LANDMARKS), joints3d=landmarks,
                 dof_names=list(skel.dof_names), angles=np.zeros((T, skel.num_dofs), np.float32), valid=valid,
                 confidence=np.ones((T, len(LANDMARKS)), np.float32),
                 extra={"ik_residual_m": np.full(T, residual_m)})


def test_track_change_is_the_mean_landmark_distance_over_frames_both_tracked(skel):
    from torchtrack.tracking.refine import track_change_m

    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(2, 6, 16, 3))
    va, vb = np.array([1, 1, 0, 1, 1, 0], bool), np.array([1, 0, 1, 1, 1, 0], bool)
    total, count = 0.0, 0
    for t in range(6):  # the plain loop
        if va[t] and vb[t]:
            total += sum(math.dist(a[t, j], b[t, j]) for j in range(16)) / 16
            count += 1
    got = track_change_m(_poses_at(a, va, skel), _poses_at(b, vb, skel))
    assert got == pytest.approx(total / count)
    assert math.isnan(track_change_m(_poses_at(a, va, skel), _poses_at(b, ~va, skel)))
    shorter = _poses_at(a[:5], va[:5], skel)
    with pytest.raises(InputError, match="different frames"):
        track_change_m(shorter, _poses_at(b, vb, skel))


def test_refinement_stops_one_pass_after_the_track_settles(monkeypatch, skel):
    """Passes whose tracks move 40, 20, 10, 5 mm ...: with ``min_change_m`` 0.015, the fourth pass (10 mm from
    the third) is the first under it, and one more pass, on the background from it, is the last (logged)."""
    from types import SimpleNamespace

    from torchtrack.tracking import refine

    T = 8
    base = np.zeros((T, 16, 3))
    calls, lose_at = [], []

    def fake_track(*args, **kwargs):
        p = len(calls)
        calls.append(kwargs.get("logger"))
        offset = sum(0.04 / 2 ** k for k in range(p))  # pass p is 40 / 2^(p-1) mm from pass p - 1
        moved = base.copy()
        moved[..., 0] += offset
        valid = np.ones(T, bool)
        valid[0] = p not in lose_at  # lose_at: the passes that lose frame 0
        return _poses_at(moved, valid, skel), 1.0

    monkeypatch.setattr(refine, "track_sequence", fake_track)
    monkeypatch.setattr(refine, "refined_background", lambda *a, **k: "refined")
    monkeypatch.setattr(refine, "MovingSequence", lambda frames, *a, **k: frames)  # no frames here
    folder = SimpleNamespace(num_frames=T, root="seq", fps=10.0, camera_names=["a", "b"],
                             sample_frames=lambda *a, **k: (list(range(T)), None))
    tracker = SimpleNamespace(initialized=True, angles=torch.zeros(skel.num_dofs), floor_z=0.0, body_version=0,
                              subject=SimpleNamespace(skeleton=skel, blobs=None),
                              initialize_from_pose=lambda *a, **k: None)
    observer = SimpleNamespace(rig=_rig())
    logger = object()
    poses, _, bg = refine.track_with_background_refinement(
        folder, "first", lambda b: observer, tracker, RefineConfig(passes=8, min_change_m=0.015, keep="last"),
        BackgroundConfig(), logger=logger)
    assert len(calls) == 5 and calls[-1] is logger and all(c is None for c in calls[:-1])
    assert bg == "refined" and poses.joints3d[0, 0, 0] == pytest.approx(0.04 + 0.02 + 0.01 + 0.005)
    calls.clear()
    refine.track_with_background_refinement(folder, "first", lambda b: observer, tracker,
                                            RefineConfig(passes=8, min_change_m=0.0, keep="last"),
                                            BackgroundConfig(),
                                            logger=logger)
    assert len(calls) == 9 and calls[-1] is logger  # min_change_m 0: every pass
    # a pass that settles where both tracked but loses a frame the one before tracked has not settled
    calls.clear()
    lose_at.append(3)
    refine.track_with_background_refinement(
        folder, "first", lambda b: observer, tracker, RefineConfig(passes=8, min_change_m=0.015, keep="last"),
        BackgroundConfig(), logger=logger)
    assert len(calls) == 6 and calls[-1] is logger
    with pytest.raises(InputError, match="min_change_m"):
        RefineConfig(min_change_m=-1.0)


def test_a_fast_sequence_is_refined_on_every_nth_frame_and_tracked_at_the_full_rate(monkeypatch, skel):
    """60 frames/s with ``max_fps`` 30: the passes track every 2nd frame, each sampled frame is drawn at the pose of
    the nearest frame they tracked, and the kept pass's background is tracked once more at the full rate (with
    the logger); ``max_fps`` 0 tracks every frame."""
    from types import SimpleNamespace

    from torchtrack.tracking import refine

    T = 9
    calls, drawn = [], []

    def fake_track(folder, observer, tracker, start, stop, *args, step=1, **kwargs):
        calls.append((step, kwargs.get("logger"), observer.background))
        index = np.arange(0, T, step)
        poses = _poses_at(np.zeros((len(index), 16, 3)), np.ones(len(index), bool), skel, 0.01 * len(calls))
        poses.frame_index = index
        poses.angles[:, 0] = index  # the frame each pose was tracked at
        return poses, 1.0

    def fake_background(frames, angles, *args, **kwargs):
        drawn.append(angles[:, 0].tolist())
        return f"background {len(drawn)}"

    monkeypatch.setattr(refine, "track_sequence", fake_track)
    monkeypatch.setattr(refine, "refined_background", fake_background)
    monkeypatch.setattr(refine, "MovingSequence", lambda frames, *a, **k: frames)
    folder = SimpleNamespace(num_frames=T, root="seq", fps=60.0, camera_names=["a", "b"],
                             sample_frames=lambda *a, **k: ([0, 3, 5, 8], None))
    tracker = SimpleNamespace(initialized=True, angles=torch.zeros(skel.num_dofs), floor_z=0.0, body_version=0,
                              subject=SimpleNamespace(skeleton=skel, blobs=None),
                              initialize_from_pose=lambda *a, **k: None)
    logger = object()
    poses, _, bg = refine.track_with_background_refinement(
        folder, "first", lambda b: SimpleNamespace(rig=_rig(), background=b), tracker,
        RefineConfig(passes=2, min_change_m=0.0, keep="last"), BackgroundConfig(), logger=logger)
    assert [c[0] for c in calls] == [2, 2, 2, 1] and all(c[1] is None for c in calls[:3])
    assert calls[-1][1:] == (logger, "background 2") and bg == "background 2"
    assert np.array_equal(poses.frame_index, np.arange(T))
    assert drawn[0] == [0.0, 2.0, 4.0, 8.0]  # frames 0, 3, 5, 8 at the nearest of 0, 2, 4, 6, 8 (a tie: the first)
    calls.clear()
    refine.track_with_background_refinement(
        folder, "first", lambda b: SimpleNamespace(rig=_rig(), background=b), tracker,
        RefineConfig(passes=2, min_change_m=0.0, keep="last", max_fps=0.0), BackgroundConfig(), logger=logger)
    assert [c[0] for c in calls] == [1, 1, 1] and calls[-1][1] is logger  # the last pass logged as it runs
    assert [RefineConfig().frame_step(f) for f in (25, 29.97, 30, 50, 59.94, 60, 120)] == [1, 1, 1, 1, 2, 2, 4]
    with pytest.raises(InputError, match="max_fps"):
        RefineConfig(max_fps=-1.0)


def test_the_refinement_uses_the_frames_the_first_background_came_from(monkeypatch, skel):
    """The frames (and passes 1-3) the first background was estimated from are not read again when they are the
    frames the refinement samples at its settings; other frames or settings are read."""
    from types import SimpleNamespace

    from torchtrack.tracking import refine

    T, reads, used = 9, [], []

    def fake_track(*args, **kwargs):
        return _poses_at(np.zeros((T, 16, 3)), np.ones(T, bool), skel), 1.0

    def fake_background(frames, *args, **kwargs):
        used.append(frames)
        return "refined"

    monkeypatch.setattr(refine, "track_sequence", fake_track)
    monkeypatch.setattr(refine, "refined_background", fake_background)
    monkeypatch.setattr(refine, "MovingSequence", lambda frames, *a, **k: "read again")
    folder = SimpleNamespace(num_frames=T, root="seq", fps=10.0, camera_names=["a", "b"],
                             sample_frames=lambda *a, **k: reads.append(a) or (list(range(T)), None))
    tracker = SimpleNamespace(initialized=True, angles=torch.zeros(skel.num_dofs), floor_z=0.0, body_version=0,
                              subject=SimpleNamespace(skeleton=skel, blobs=None),
                              initialize_from_pose=lambda *a, **k: None)
    config = BackgroundConfig()
    first = SimpleNamespace(indices=list(range(T)), config=config, shape=(T, 2, 3, H, W))
    for sequence, start, bg_config, read in ((first, 0, config, False), (first, 1, config, True),
                                             (first, 0, BackgroundConfig(max_frames=5), True),
                                             (SimpleNamespace(**{**vars(first), "shape": (T, 2, 3, 8, 8)}), 0,
                                              config, True)):
        reads.clear()
        used.clear()
        refine.track_with_background_refinement(folder, "first", lambda b: SimpleNamespace(rig=_rig()), tracker,
                                                RefineConfig(passes=2, keep="last", min_change_m=0.0), bg_config,
                                                start=start, sequence=sequence)
        assert len(used) == 2 and used[0] is used[1] and (used[0] == "read again") == read and len(reads) == read


def test_fit_keeps_the_refined_pass_that_fits_best_and_logs_it(monkeypatch, skel):
    """``keep: fit``: of the passes after the first, the one with the fewest lost frames and then the lowest mean IK
    residual is the result, with its background; the passes stop ``patience`` passes after it, and with a logger
    it is tracked once more, on its own background, for the logs."""
    from types import SimpleNamespace

    from torchtrack.tracking import refine

    T = 8
    # each pass's mean IK residual (m); pass 0, on the plain background, is no candidate however low its residual;
    # pass 5 fits better than pass 3 but loses a frame
    residuals = [0.001, 0.030, 0.025, 0.020, 0.024, 0.010, 0.021, 0.019, 0.018]
    calls, backgrounds = [], []

    def fake_track(folder, observer, *args, **kwargs):
        p = backgrounds.index(observer.background)  # the pass whose background this is: its track
        calls.append((p, kwargs.get("logger")))
        valid = np.ones(T, bool)
        valid[0] = p != 5
        return _poses_at(np.full((T, 16, 3), place[p]), valid, skel, residuals[p]), 1.0

    def fake_background(*args, **kwargs):
        backgrounds.append(f"background {len(backgrounds)}")
        return backgrounds[-1]

    place = [0.001 * p for p in range(20)]  # every pass 1 mm from the one before: settled

    monkeypatch.setattr(refine, "track_sequence", fake_track)
    monkeypatch.setattr(refine, "refined_background", fake_background)
    monkeypatch.setattr(refine, "MovingSequence", lambda frames, *a, **k: frames)  # no frames here
    folder = SimpleNamespace(num_frames=T, root="seq", fps=10.0, camera_names=["a", "b"],
                             sample_frames=lambda *a, **k: (list(range(T)), None))
    tracker = SimpleNamespace(initialized=True, angles=torch.zeros(skel.num_dofs), floor_z=0.0, body_version=0,
                              subject=SimpleNamespace(skeleton=skel, blobs=None),
                              initialize_from_pose=lambda *a, **k: None)
    rig = _rig()
    logger = object()
    for log in (None, logger):
        calls.clear()
        backgrounds[:] = ["background 0"]
        poses, _, bg = refine.track_with_background_refinement(
            folder, "background 0", lambda b: SimpleNamespace(rig=rig, background=b), tracker,
            RefineConfig(passes=16, patience=3), BackgroundConfig(), logger=log)
        # pass 3 is the best; passes 4, 5 and 6 do not better it, so pass 6 is the last; pass 3 is tracked again
        # (the tracker ends in its state), with the logger when there is one
        assert [p for p, _ in calls] == list(range(7)) + [3]
        assert [c for _, c in calls] == [None] * 7 + [log]
        assert poses.joints3d[0, 0, 0] == pytest.approx(0.003) and bg == "background 3"
        assert int(poses.extra["refinement_pass"]) == 4
    # the best pass is the last (residuals falling to the end): no logger, so it is not tracked again
    residuals[:] = [0.05, 0.04, 0.03, 0.02]
    calls.clear()
    backgrounds[:] = ["background 0"]
    seen = []
    poses, _, bg = refine.track_with_background_refinement(
        folder, "background 0", lambda b: SimpleNamespace(rig=rig, background=b), tracker,
        RefineConfig(passes=3), BackgroundConfig(), on_pass=lambda p, tr: seen.append(p))
    assert [p for p, _ in calls] == [0, 1, 2, 3] and seen == [0, 1, 2, 3] and bg == "background 3"
    assert int(poses.extra["refinement_pass"]) == 4
    # with a logger it is tracked again, and on_pass hears of that track too
    calls.clear()
    backgrounds[:] = ["background 0"]
    seen.clear()
    refine.track_with_background_refinement(
        folder, "background 0", lambda b: SimpleNamespace(rig=rig, background=b), tracker,
        RefineConfig(passes=3), BackgroundConfig(), logger=logger, on_pass=lambda p, tr: seen.append(p))
    assert [p for p, _ in calls] == [0, 1, 2, 3, 3] and calls[-1][1] is logger and seen == [0, 1, 2, 3, 4]
    residuals[:] = [0.001, 0.030, 0.025, 0.020, 0.024, 0.010, 0.021, 0.019, 0.018]
    # keep: last is the last pass run, the passes stopping at min_change_m (off here: every pass)
    calls.clear()
    backgrounds[:] = ["background 0"]
    poses, _, bg = refine.track_with_background_refinement(
        folder, "background 0", lambda b: SimpleNamespace(rig=rig, background=b), tracker,
        RefineConfig(passes=8, min_change_m=0.0, keep="last"), BackgroundConfig(), logger=logger)
    assert [p for p, _ in calls] == list(range(9)) and calls[-1][1] is logger and bg == "background 8"
    assert poses.joints3d[0, 0, 0] == pytest.approx(0.008) and "refinement_pass" not in poses.extra
    # passes whose tracks still move (1 m, then 5 mm and less from pass 3 on) do not compete, however well they
    # fit: the best settled pass (4) is kept, and the patience counts from it
    residuals[:] = [0.001, 0.005, 0.006, 0.020, 0.015, 0.017, 0.016, 0.018, 0.019]
    for moves, passes, want in (([0.0, 1.0, 2.0, 2.005, 2.008, 2.009, 2.0095, 2.0097, 2.0098], 16,
                                 list(range(8)) + [4]),
                                ([float(p) for p in range(9)], 8, list(range(9)) + [1])):  # none settled: the best
        place[:] = moves + [moves[-1]] * 11  # of all refined passes, after all of them
        calls.clear()
        backgrounds[:] = ["background 0"]
        poses, _, bg = refine.track_with_background_refinement(
            folder, "background 0", lambda b: SimpleNamespace(rig=rig, background=b), tracker,
            RefineConfig(passes=passes, patience=3), BackgroundConfig())
        assert [p for p, _ in calls] == want and bg == f"background {want[-1]}"
        assert int(poses.extra["refinement_pass"]) == want[-1] + 1


def test_passes_after_the_first_start_in_the_body_it_moved(monkeypatch, skel):
    """A tracker started from a height learns its hips in the first pass (functional_hips); the later passes
    start from the same state re-stated in the moved body, not from the body before the move."""
    from types import SimpleNamespace

    from torchtrack.tracking import refine
    from torchtrack.tracking.markerless import MarkerlessTracker, TrackerConfig

    T = 8
    tracker = MarkerlessTracker(skel, TrackerConfig())
    start = skel.rest_angles(0.9)
    tracker.initialize_from_pose(start, height_m=skel.height())
    starts = []
    init = tracker.initialize_from_pose

    def recording_init(angles, height_m=None, *, skeleton=None, floor_z_m=None):
        starts.append((angles.clone(), skeleton))
        init(angles, height_m, skeleton=skeleton, floor_z_m=floor_z_m)

    def fake_track(*args, **kwargs):
        if not starts:  # the first pass moves the hips
            tracker.move_hips(0.03)
        return _poses_at(np.zeros((T, 16, 3)), np.ones(T, bool), skel), 1.0

    tracker.initialize_from_pose = recording_init
    monkeypatch.setattr(refine, "track_sequence", fake_track)
    monkeypatch.setattr(refine, "refined_background", lambda *a, **k: "refined")
    monkeypatch.setattr(refine, "MovingSequence", lambda frames, *a, **k: frames)  # no frames here
    folder = SimpleNamespace(num_frames=T, root="seq", fps=10.0, camera_names=["a", "b"],
                             sample_frames=lambda *a, **k: (list(range(T)), None))
    observer = SimpleNamespace(rig=_rig())
    refine.track_with_background_refinement(folder, "first", lambda b: observer, tracker,
                                            RefineConfig(passes=2, min_change_m=0.0), BackgroundConfig())
    assert len(starts) == 3  # the two refined passes, and the first of them again (kept: no better fit after it)
    moved_up = start.clone()
    moved_up[2] += 0.03  # upright: the pelvis' z axis is the world's
    for angles, body in starts:
        assert body is not skel and body.joint_origin("spine_flex")[2] == pytest.approx(
            skel.joint_origin("spine_flex")[2] - 0.03)
        np.testing.assert_allclose(angles.numpy(), moved_up.numpy(), atol=1e-5)


def test_an_automatic_start_is_searched_for_again_on_each_pass(monkeypatch, skel):
    """A tracker with no start given finds its start itself: every pass after the first resets it, so that the
    pass searches for its start on its own (refined) observation, and the kept pass tracked again does too; a
    given start is put back instead (the test above)."""
    from types import SimpleNamespace

    from torchtrack.tracking import refine

    T = 8
    events = []

    def fake_track(folder, observer, tracker, *args, **kwargs):
        events.append(("track", observer.background))
        return _poses_at(np.zeros((T, 16, 3)), np.ones(T, bool), skel, 0.01 * len(events)), 1.0

    monkeypatch.setattr(refine, "track_sequence", fake_track)
    monkeypatch.setattr(refine, "refined_background", lambda *a, **k: f"refined {len(events)}")
    monkeypatch.setattr(refine, "MovingSequence", lambda frames, *a, **k: frames)  # no frames here
    folder = SimpleNamespace(num_frames=T, root="seq", fps=10.0, camera_names=["a", "b"],
                             sample_frames=lambda *a, **k: (list(range(T)), None))
    tracker = SimpleNamespace(initialized=False, subject=SimpleNamespace(skeleton=skel, blobs=None),
                              reset=lambda: events.append(("reset",)),
                              initialize_from_pose=lambda *a, **k: events.append(("given",)))
    refine.track_with_background_refinement(folder, "first", lambda b: SimpleNamespace(rig=_rig(), background=b),
                                            tracker, RefineConfig(passes=2, patience=1), BackgroundConfig(),
                                            logger=object())
    # pass 1 on the first background, then each refined pass after a reset; pass 2 (the lowest residual) again
    assert events == [("track", "first"), ("reset",), ("track", "refined 1"), ("reset",), ("track", "refined 3"),
                      ("reset",), ("track", "refined 1")]
