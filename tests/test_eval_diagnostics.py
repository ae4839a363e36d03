"""The evaluation scripts' diagnostics that the README quotes (scripts/eval_tracking.py --trunk,
scripts/eval_pose2sim_tracking.py --bias).

References: headings of a root turned about the vertical and a spine twisted about it (closed form), scipy's
``Rotation.align_vectors`` for the rigid alignment, and a knee bent by a known angle.
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path
from types import ModuleType, SimpleNamespace

import numpy as np
import torch
import pytest
from scipy.spatial.transform import Rotation

from torchtrack.skeleton import Skeleton

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def _script(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def eval_tracking() -> ModuleType:
    return _script("eval_tracking")


@pytest.fixture(scope="module")
def skeleton() -> Skeleton:
    return Skeleton.from_urdf()


def _poses(skeleton: Skeleton, yaw: np.ndarray, twist: np.ndarray) -> SimpleNamespace:
    """Poses whose root turns ``yaw`` (rad) about the vertical and whose spine twists ``twist`` above it."""
    names = list(skeleton.dof_names)
    angles = np.tile(skeleton.rest_angles().numpy(), (len(yaw), 1))
    angles[:, names.index("root_rz")] = yaw
    angles[:, names.index("spine_twist")] = twist
    return SimpleNamespace(dof_names=names, angles=angles, valid=np.ones(len(yaw), bool))


def test_trunk_headings_of_a_trunk_that_does_not_twist(eval_tracking, skeleton):
    # the truth twists the torso by tau over the pelvis; the track turns both by half of it and does not twist:
    # each heading is tau / 2 off its true one and on the mean of the true two
    yaw = np.radians([10.0, 100.0, 175.0, -170.0])  # across the +-180 deg seam too
    tau = np.radians([20.0, -30.0, 16.0, 40.0])
    h = eval_tracking.trunk_headings(_poses(skeleton, yaw + tau / 2, 0 * tau), _poses(skeleton, yaw, tau), skeleton)
    half = np.degrees(np.abs(tau)) / 2
    np.testing.assert_allclose(h["pelvis"], half, atol=1e-4)
    np.testing.assert_allclose(h["torso"], half, atol=1e-4)
    np.testing.assert_allclose(h["pelvis_from_mean"], 0.0, atol=1e-4)
    np.testing.assert_allclose(h["torso_from_mean"], 0.0, atol=1e-4)
    np.testing.assert_allclose(h["true_twist"], 2 * half, atol=1e-4)
    np.testing.assert_allclose(h["tracked_twist"], 0.0, atol=1e-4)
    line = eval_tracking.headings_line(h)
    assert f"pelvis {half.mean():.1f} / {half.max():.1f}" in line and "tracked 0.0 / 0.0" in line


def test_trunk_headings_skip_invalid_frames(eval_tracking, skeleton):
    truth = _poses(skeleton, np.zeros(3), np.zeros(3))
    track = _poses(skeleton, np.radians([5.0, 90.0, 5.0]), np.zeros(3))
    track.valid = np.array([True, False, True])
    h = eval_tracking.trunk_headings(track, truth, skeleton)
    np.testing.assert_allclose(h["pelvis"], [5.0, 5.0], atol=1e-4)


def test_rigid_residuals_against_scipy_alignment():
    mod = _script("eval_pose2sim_tracking")
    rng = np.random.default_rng(3)
    x = rng.normal(size=(4, 15, 3))  # four frames, aligned each on its own
    R = Rotation.random(4, random_state=5)
    y = np.stack([R[i].apply(x[i]) for i in range(4)]) + rng.normal(size=(4, 1, 3))
    np.testing.assert_allclose(mod.rigid_residuals(x, y), 0.0, atol=1e-9)
    y_noisy = y + rng.normal(scale=0.05, size=y.shape)
    for i, got in enumerate(mod.rigid_residuals(x, y_noisy)):
        best, _ = Rotation.align_vectors(y_noisy[i] - y_noisy[i].mean(0), x[i] - x[i].mean(0))
        expect = np.linalg.norm(best.apply(x[i] - x[i].mean(0)) + y_noisy[i].mean(0) - y_noisy[i], axis=-1)
        np.testing.assert_allclose(got, expect, atol=1e-9)


def test_knee_bend_closed_form():
    mod = _script("eval_pose2sim_tracking")
    names = ["l_hip", "l_knee", "l_ankle"]
    bend = np.radians([0.0, 30.0, 90.0])
    # thigh straight down 0.4 m, shank 0.38 m bent back by the angle
    pts = np.stack([np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.6],
                              [-0.38 * math.sin(b), 0.0, 0.6 - 0.38 * math.cos(b)]]) for b in bend])
    np.testing.assert_allclose(mod.knee_bend(pts, names, "l"), np.degrees(bend), atol=1e-6)
    # nearly straight, in float32 (the tracks' dtype): 0.05 deg is still read as such
    b = math.radians(0.05)
    nearly = np.array([[[0.0, 0.0, 1.0], [0.0, 0.0, 0.6], [-0.38 * math.sin(b), 0.0, 0.6 - 0.38 * math.cos(b)]]],
                      np.float32)
    np.testing.assert_allclose(mod.knee_bend(nearly, names, "l"), [0.05], atol=5e-4)  # arccos: 0.0523


def test_jitter_of_constant_velocity_and_of_alternating_noise():
    """The RMS second difference: 0 for a trajectory at constant velocity; 4 a for one that alternates by +-a
    (second difference a (1 + 2 + 1) in every frame)."""
    mod = _script("eval_pose2sim_occupancy")
    t = np.arange(30, dtype=float)[:, None, None]
    moving = np.array([0.01, -0.02, 0.005]) * t + np.zeros((1, 5, 3))  # (30, 5, 3) m
    assert mod.jitter_mm(moving) == pytest.approx(0.0, abs=1e-9)
    a = 0.003
    alternating = moving + a * (-1.0) ** t * np.array([1.0, 0.0, 0.0])
    assert mod.jitter_mm(alternating) == pytest.approx(4e3 * a)


def test_centroid_along_segments_against_closed_forms():
    """Points filling a cylinder around a segment centre at 0.5 of it; a cone with its base at the proximal end at
    0.25 (a solid cone's centroid is a quarter of its height from the base); points nearer another segment or
    beyond the radius are not counted; a segment without points is NaN."""
    mod = _script("eval_pose2sim_occupancy")
    rng = np.random.default_rng(0)
    n = 200_000
    z = rng.uniform(0, 1, n)  # along, from the proximal end at z = 1 down to 0 (a hanging limb, 1 m)
    r, phi = 0.05 * np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n)
    cylinder = np.stack([r * np.cos(phi), r * np.sin(phi), 1 - z], 1)
    # a cone of base radius 0.06 at the top: accept points under its surface (rejection sampling in its cylinder)
    rc = 0.06 * np.sqrt(rng.uniform(0, 1, n))
    keep = rc <= 0.06 * (1 - z)
    cone = np.stack([rc * np.cos(phi) + 1.0, rc * np.sin(phi), 1 - z], 1)[keep]
    far = np.array([[0.0, 0.5, 0.5]])  # 0.5 m from the first segment, beyond the radius of every segment
    a = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [3.0, 0.0, 1.0]])  # (S, 3) proximal ends
    b = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    got = mod.centroid_along_segments(np.concatenate([cylinder, cone, far]), a, b, radius=0.12)
    np.testing.assert_allclose(got[:2], [0.5, 0.25], atol=3e-3)
    assert np.isnan(got[2])
    # a point 0.5 m off the first segment's axis is not counted for it, however near its end
    assert np.isnan(mod.centroid_along_segments(np.array([[0.0, 0.5, 0.9]]), a[:1], b[:1], radius=0.12)[0])
    assert mod.centroid_along_segments(np.array([[0.0, 0.1, 0.9]]), a[:1], b[:1], radius=0.12)[0] == \
        pytest.approx(0.1)
    assert np.isnan(mod.centroid_along_segments(np.zeros((0, 3)), a, b, radius=0.12)).all()  # no points
    # a point nearer the second segment goes to it, not to the first even within the radius
    between = np.array([[0.6, 0.0, 0.5]])
    got = mod.centroid_along_segments(between, a[:2], b[:2], radius=0.5)
    assert np.isnan(got[0]) and got[1] == pytest.approx(0.5)


def test_velocity_table_medians():
    """--velocities' summary: a line per run and the medians over the runs (worked by hand: the middle of the five
    sorted values), '-' for the filtered column when a run has no filtered figure."""
    mod = _script("eval_pose2sim_tracking")
    rows = [(0.5, 60.7, 58.5, 0, 7), (0.47, 60.4, 58.2, 0, 8), (0.53, 65.4, 63.3, 0, 8), (0.45, 60.4, 58.2, 0, 8),
            (0.55, 64.7, 62.7, 1, 7)]
    lines = mod.velocity_table(rows).splitlines()
    assert len(lines) == 7
    assert lines[3].split() == ["0.53", "65.4", "/", "63.3", "0", "8"]
    assert lines[-1].split()[:4] == ["median", "60.7", "/", "58.5"]
    two = mod.velocity_table([(0.5, 60.0, None, 0, 7), (0.4, 62.0, 59.0, 0, 7)]).splitlines()
    assert two[1].split() == ["0.5", "60.0", "/", "-", "0", "7"]
    assert two[-1].split()[:4] == ["median", "61.0", "/", "-"]


def test_frame_ranges(eval_tracking):
    assert eval_tracking.frame_ranges([3, 4, 5, 9]) == "3-5, 9"
    assert eval_tracking.frame_ranges([0, 2, 3, 7, 8, 9, 11]) == "0, 2-3, 7-9, 11"
    assert eval_tracking.frame_ranges([]) == ""


def test_blob_activity_records_a_hand_without_voxels(eval_tracking, skeleton):
    """--blob-activity: a starfish whose left hand's voxels are taken away (the ground truth of the scene) gives a
    de-activated left hand in the frame tracked and nothing for a skipped frame; the whole body: every blob on."""
    import dataclasses

    from conftest import voxelised_observation as _observation

    from torchtrack.blobs.model import BlobModel
    from torchtrack.occupancy.metrics import inside_ellipsoids
    from torchtrack.tracking.markerless import TrackerConfig

    subj = skeleton.scaled_to_height(1.75)
    blobs = BlobModel.from_config(subj)
    angles = subj.starfish_angles()
    obs = _observation(subj, blobs, angles)
    centres, R = blobs.ellipsoids(subj.forward(angles[None].double()).bone_frames)
    k = blobs.names.index("l_hand")
    hand = inside_ellipsoids(obs.points.double(), centres[0, k:k + 1], R[0, k:k + 1],
                             blobs.semi_axes[k:k + 1].double() + 0.02)
    keep = ~hand
    handless = dataclasses.replace(obs, points=obs.points[keep], sizes=obs.sizes[keep], weights=obs.weights[keep],
                                   colours=obs.colours[keep])
    tracker = eval_tracking.RecordingTracker(skeleton, TrackerConfig(fit_bone_lengths=False))
    tracker.initialize_from_pose(angles, 1.75)
    tracker.step(obs)
    tracker.skip()
    tracker.step(handless)
    assert len(tracker.active) == 3 and tracker.active[1] is None
    assert tracker.active[0].all()
    assert not tracker.active[2][k] and tracker.active[2].sum() == len(blobs.names) - 1
    assert eval_tracking.blob_activity(tracker) == ["l_hand off in 1 frame: 2"]


def test_start_heights_are_the_first_frames_height_differences(eval_tracking):
    from torchtrack.conventions import LANDMARKS

    true = np.zeros((2, len(LANDMARKS), 3))
    tracked = true.copy()
    tracked[0, LANDMARKS.index("pelvis"), 2] = -0.058
    tracked[0, LANDMARKS.index("l_ankle")] = [0.3, 0.1, 0.028]  # only the height counts
    tracked[1] = 1.0  # a later frame: not read
    line = eval_tracking.start_heights(SimpleNamespace(landmarks=lambda: tracked),
                                       SimpleNamespace(landmarks=lambda: true))
    assert "pelvis -5.8," in line and "l_ankle +2.8," in line and "head +0.0," in line


def test_coverage_of_a_ball_with_its_top_cut_off(eval_tracking):
    """--coverage against closed forms: a 'head' ball of radius 0.1 m whose voxels (1 cm cubes, centres inside
    it) stop at centres 5 cm above its middle (the highest at 4.5 cm) misses the cap beyond the cubes' tops and the
    1 cm tolerance, 6 cm above the middle: (1 - 0.6)^2 (2 + 0.6) / 4 = 10.4 % of the ball; its highest voxel
    centre lies 5.5 cm under the top. A second ball, wholly voxelised, misses nothing; a box that cuts the first
    one's cap off counts the cap as unobserved, not missed."""
    from torchtrack.tracking.observation import VoxelObservation

    g = (torch.arange(-12, 12, dtype=torch.float64) + 0.5) * 0.01  # 1 cm cube centres
    grid = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    ball = grid[grid.norm(dim=1) <= 0.1]
    head = ball[ball[:, 2] <= 0.05] + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    other = ball + torch.tensor([0.5, 0.0, 1.0], dtype=torch.float64)
    pts = torch.cat([head, other])
    truth = {"blob_names": np.array(["head", "other"]),
             "blob_centres": np.array([[[0.0, 0.0, 1.0], [0.5, 0.0, 1.0]]]),
             "blob_R_world": np.tile(np.eye(3), (1, 2, 1, 1)), "blob_semi_axes": np.full((2, 3), 0.1)}

    def obs(volume):
        n = pts.shape[0]
        return VoxelObservation(pts, torch.full((n,), 0.01, dtype=torch.float64), torch.ones(n, dtype=torch.float64),
                                torch.zeros(n, 1, 3), torch.ones(1, dtype=torch.bool), volume_m=volume)

    missed, under = eval_tracking.coverage(obs(None), truth, samples=4000)
    cap = (1 - 0.6) ** 2 * (2 + 0.6) / 4
    assert missed["head"] == pytest.approx(cap, abs=0.015), missed  # 4000 samples: sd 0.4 %
    assert missed["other"] < 0.005, missed
    assert under == pytest.approx(0.055, abs=1e-9)
    line = eval_tracking.coverage_line({"head": 0.104, "other": 0.0, "hand": 0.06}, 0.055)
    assert line.endswith("(%, over 5): head 10.4, hand 6.0; the head's highest voxel centre 5.5 cm under its top")
    # a volume whose top is at 1.04 m: the cap is out of view, so not counted as missed
    boxed, _ = eval_tracking.coverage(obs(((-1.0, -1.0, 0.0), (1.0, 1.0, 1.04))), truth, samples=4000)
    assert boxed["head"] < 0.01, boxed


def test_score_per_landmark_against_a_known_shift(tmp_path, capsys):
    """--score --per-landmark of the raw reference itself with the left ankle moved 0.1 m up and the right wrist
    0.03 m sideways: 100 and 30 mm there, 0 elsewhere (closed form)."""
    mod = _script("eval_pose2sim_tracking")
    if not (mod.DEMO / "videos").is_dir():
        pytest.skip(f"{mod.DEMO}: the Pose2Sim demo is not there")
    from torchtrack.io.poses import save_poses

    names, ref = mod.reference_landmarks(mod.DEMO)
    moved = ref.copy()
    moved[:, names.index("l_ankle"), 2] += 0.1
    moved[:, names.index("r_wrist"), 0] += 0.03
    path = tmp_path / "poses.npz"
    poses = mod.reference_poses(names, moved, 60.0, list(Skeleton.from_urdf().output_names))
    poses.joints3d = np.nan_to_num(poses.joints3d)  # joints that are not landmarks: any finite value
    save_poses(poses, path)
    mod.score(path, mod.DEMO, per_landmark=True)
    line = capsys.readouterr().out.splitlines()[1].split()
    got = dict(zip(line[::2], map(float, line[1::2])))
    assert set(got) == set(names)
    expect = {n: 100.0 if n == "l_ankle" else 30.0 if n == "r_wrist" else 0.0 for n in names}
    for n in names:
        assert got[n] == pytest.approx(expect[n], abs=0.06), n
