"""Functional hip centres (torchtrack.tracking.functional, TrackerConfig.functional_hips).

References: a pivot that every line is built through (a closed form), the information of two lines at +-alpha
(2 sin^2 alpha), the body's own forward kinematics before the move, and a true body with higher hips whose blobs
the tracker is shown.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from torchtrack.blobs.em import prior_blobs
from torchtrack.blobs.model import BlobModel, load_blob_specs
from torchtrack.skeleton import Skeleton
from torchtrack.tracking.functional import AxisPivot
from torchtrack.tracking.markerless import FrameResult, MarkerlessTracker, TrackerConfig, with_hips_raised

torch.set_grad_enabled(False)


@pytest.fixture(scope="module")
def skel() -> Skeleton:
    return Skeleton.from_urdf().scaled_to_height(1.7)


def _line_cov(d: np.ndarray) -> torch.Tensor:
    """A blob elongated along ``d`` (its main eigenvector)."""
    return torch.from_numpy(0.01 * np.outer(d, d) + 1e-4 * np.eye(3))


def test_axis_pivot_finds_the_point_every_line_passes_through():
    rng = np.random.default_rng(0)
    pivots = np.array([[0.01, 0.09, 0.03], [-0.02, -0.08, 0.05]])  # in the parent's frame
    acc = AxisPivot(2)
    for _ in range(12):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        T[:3, 3] = rng.normal(size=3)
        means, covs = [], []
        for p in pivots:
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            on_line = p + rng.uniform(-0.3, 0.3) * d  # a point of the line, parent frame
            means.append(T[:3, :3] @ on_line + T[:3, 3])
            covs.append(_line_cov(T[:3, :3] @ d))
        acc.add(torch.from_numpy(T), torch.from_numpy(np.stack(means)), torch.stack(covs), torch.ones(2))
        # a line not seen this frame (weight 0) changes nothing, wherever it lies
        acc.add(torch.from_numpy(T), torch.from_numpy(rng.normal(size=(2, 3))), torch.stack(covs), torch.zeros(2))
    np.testing.assert_allclose(acc.centres().numpy(), pivots, atol=1e-9)
    assert acc.lines.tolist() == [12, 12]


@pytest.mark.parametrize("alpha_deg", [5.0, 20.0, 40.0])
def test_axis_pivot_information_of_a_swing_is_the_sum_of_sin2(alpha_deg):
    a = math.radians(alpha_deg)
    acc = AxisPivot(1)
    for s in (-1.0, 1.0):  # two lines in the x-z plane at +-alpha off the vertical
        d = np.array([s * math.sin(a), 0.0, -math.cos(a)])
        acc.add(torch.eye(4, dtype=torch.float64), torch.zeros(1, 3, dtype=torch.float64), _line_cov(d)[None],
                torch.ones(1))
    assert float(acc.information()[0]) == pytest.approx(2 * math.sin(a) ** 2, rel=1e-9)


def test_raised_hips_keep_the_rest_of_the_body_where_it_was(skel):
    dz = 0.035
    rng = np.random.default_rng(1)
    angles = skel.rest_angles(0.9).repeat(6, 1)
    angles[:, 3:] += torch.from_numpy(rng.uniform(-0.4, 0.4, size=(6, angles.shape[1] - 3))).float()
    angles = skel.clamp(angles)
    tracker = MarkerlessTracker(Skeleton.from_urdf(), TrackerConfig())
    tracker.initialize_from_pose(angles[0], skeleton=skel)
    tracker.move_hips(dz)
    moved = tracker.subject.skeleton
    assert tracker.body_version == 1
    before = skel.forward(angles)
    after = moved.forward(tracker.restate(angles, 0))
    names = list(skel.output_names)
    hips = [names.index(n) for n in ("pelvis", "l_hip", "r_hip")]
    up = before.bone_frames[:, skel.bone_names.index("pelvis"), :3, 2]  # (B, 3) the pelvis' z axis, world
    np.testing.assert_allclose(after.output_points[:, hips].numpy(),
                               (before.output_points[:, hips] + dz * up[:, None]).numpy(), atol=1e-5)
    # the rest where it was: exactly for the trunk, arms and head; the longer thighs bent back onto the knees
    err = (after.output_points - before.output_points).norm(dim=-1)  # (B, J)
    legs = [names.index(n) for n in ("l_knee", "l_ankle", "l_toe", "r_knee", "r_ankle", "r_toe")]
    rest = [i for i in range(len(names)) if i not in hips + legs]
    assert float(err[:, rest].max()) < 1e-5
    assert float(err[:, legs].max()) < 8e-3  # the thighs are dz longer: off by dz (1 - cos flexion)
    thigh = skel.bone_names.index("l_thigh")
    assert float(moved.bone_lengths[thigh]) == pytest.approx(float(skel.bone_lengths[thigh]) + dz, abs=1e-6)
    # the tracked state and the one before it moved with the body; a state already in it is left as it is, and
    # NaN stays NaN
    np.testing.assert_allclose(tracker.angles.numpy(), tracker.restate(angles[:1], 0)[0].numpy(), atol=1e-6)
    np.testing.assert_allclose(tracker.previous.numpy(), tracker.restate(angles[:1], 0)[0].numpy(), atol=1e-6)
    np.testing.assert_array_equal(tracker.restate(angles, 1).numpy(), angles.numpy())
    assert torch.isnan(tracker.restate(torch.full_like(angles[:1], math.nan), 0)).all()
    # a second move: a state of version 0 takes both, one of version 1 the second only
    tracker.move_hips(0.01)
    for version, total in ((0, dz + 0.01), (1, 0.01)):
        base = skel.forward(angles) if version == 0 else moved.forward(angles)
        again = tracker.subject.skeleton.forward(tracker.restate(angles, torch.full((6,), version)))
        np.testing.assert_allclose(again.output_points[:, hips].numpy(),
                                   (base.output_points[:, hips] + total * up[:, None]).numpy(), atol=1e-5)
        assert float((again.output_points - base.output_points).norm(dim=-1)[:, rest].max()) < 1e-5


def _thigh_swing(skel: Skeleton, frames: int) -> torch.Tensor:
    """(frames, D) a subject standing at the origin swinging both thighs back and forth out of phase."""
    a = skel.rest_angles(0.9).repeat(frames, 1)
    phase = torch.linspace(0, 2 * math.pi, frames, dtype=a.dtype)
    a[:, skel.dof_names.index("l_hip_flex")] = 0.5 * torch.sin(phase)
    a[:, skel.dof_names.index("r_hip_flex")] = -0.4 * torch.sin(phase)
    a[:, skel.dof_names.index("l_knee_flex")] = 0.6 * (1 + torch.sin(phase)) / 2
    return skel.clamp(a)


def _shown_moved_hips(body: Skeleton, dz: float) -> tuple[MarkerlessTracker, torch.Tensor, Skeleton, int]:
    """A tracker learning the hips of ``body`` (as for a body it fitted) shown, frame after frame of a thigh
    swing, the blobs of the subject's true body, whose hips are ``dz`` higher, until it stops learning.

    Returns:
        the tracker, the true body's state vectors (T, D), the true body and the last frame shown.
    """
    config = TrackerConfig(functional_hips=2.0)
    tracker = MarkerlessTracker(Skeleton.from_urdf(), config)
    angles = _thigh_swing(body, 40)
    tracker.initialize_from_pose(angles[0], skeleton=body)
    tracker._start_hips(learn=True)  # as for a body the tracker fitted (a given skeleton is not learnt)
    true = with_hips_raised(body, dz)
    frames = body.forward(angles).bone_frames  # the fitted body, tracked at the same states
    true_angles = angles.clone()  # the true body's states: the same trunk, the pelvis dz higher
    true_angles[:, :3] += dz * frames[:, body.bone_names.index("pelvis"), :3, 2]
    means, covs = BlobModel(true, *load_blob_specs(config.blobs)).gaussians(true.forward(true_angles).bone_frames)
    for t in range(angles.shape[0]):
        tracker.angles = tracker.previous = angles[t]
        tracker._learn_hips(FrameResult(angles[t], torch.zeros(1, 3), torch.ones(1), True, 0.0, 1.0, False,
                                        prior_blobs(means[t], covs[t]), frames[t]))
        if tracker.hips is None:
            break
    return tracker, true_angles, true, t


@pytest.mark.parametrize("dz", [0.03, 0.012])
def test_the_tracker_moves_its_hips_to_where_the_thighs_pivot(skel, dz):
    tracker, true_angles, true, t = _shown_moved_hips(skel, dz)
    assert tracker.body_version == 1  # moved once, then no longer learning
    assert tracker.hip_shifts[0] == pytest.approx(dz, abs=2e-3)
    above, information = tracker.hip_estimate
    np.testing.assert_allclose(above.numpy(), [dz, dz], atol=3e-3)
    assert bool((information >= 2.0).all())
    # the tracked state's hips now sit on the true ones
    hips = [list(skel.output_names).index(n) for n in ("pelvis", "l_hip", "r_hip")]
    np.testing.assert_allclose(tracker.subject.skeleton.forward(tracker.angles[None]).output_points[0, hips].numpy(),
                               true.forward(true_angles[t:t + 1]).output_points[0, hips].numpy(), atol=3e-3)


def test_a_pivot_below_the_fitted_hips_leaves_the_body(skel, caplog):
    """The bone fit's bias runs up: thighs that seem to pivot under the fitted hips are the axes' error."""
    with caplog.at_level("WARNING", logger="torchtrack.tracking.markerless"):
        tracker, _, _, _ = _shown_moved_hips(skel, -0.03)
    assert tracker.body_version == 0 and tracker.subject.skeleton is skel
    np.testing.assert_allclose(tracker.hip_estimate[0].numpy(), [-0.03, -0.03], atol=3e-3)
    assert "-30 mm above the fitted hips" in caplog.text


def test_a_given_skeleton_keeps_its_hips(skel):
    tracker = MarkerlessTracker(Skeleton.from_urdf(), TrackerConfig())
    tracker.initialize_from_pose(skel.rest_angles(0.9), skeleton=skel)
    assert tracker.hips is None
    tracker.initialize_from_pose(skel.rest_angles(0.9), height_m=1.7)
    assert tracker.hips is not None
    off = MarkerlessTracker(Skeleton.from_urdf(), TrackerConfig(functional_hips=0))
    off.initialize_from_pose(skel.rest_angles(0.9), height_m=1.7)
    assert off.hips is None


def test_functional_hips_setting_is_checked():
    from torchtrack.checks import InputError

    with pytest.raises(InputError, match="functional_hips"):
        TrackerConfig(functional_hips=-1)
    with pytest.raises(InputError, match="functional_hips_min_cameras"):
        TrackerConfig(functional_hips_min_cameras=-1)


def test_a_tracked_sequence_is_restated_in_the_moved_body(tmp_path):
    """Frames tracked before the hips moved come out in the final body: their trunk, arms and head where they were
    tracked, the pelvis and hips raised by the move, the legs within a few cm of the tracked ones (the thighs are
    longer); their state vectors, put through the output's body (``body_urdf``), give the output points."""
    import dataclasses

    from torchtrack.background import BackgroundModel
    from torchtrack.io.sequence import SequenceFolder
    from torchtrack.tracking.pipeline import load_config
    from torchtrack.tracking.observation import Observer
    from torchtrack.tracking.run import track_sequence

    from conftest import small_walk

    seq = small_walk(tmp_path / "seq", duration_s=0.8, video_format="png", size_wh=(160, 120))
    folder = SequenceFolder(seq)
    rig = folder.rig.float()
    observer = Observer(rig, BackgroundModel.from_folder(folder), "bayes", voxel_size_m=0.04)
    config = dataclasses.replace(TrackerConfig.from_dict(load_config("markerless.yaml")["tracker"]),
                                 functional_hips=0.2, functional_hips_min_cameras=4)  # a short 4-camera walk
    tracker = MarkerlessTracker(Skeleton.from_urdf(), config)
    tracked, versions = [], []  # each frame's output points and pelvis as the tracker gave them
    step = tracker.step

    def recording_step(obs):
        versions.append(tracker.body_version)
        res = step(obs)
        tracked.append((res.output_points.numpy().copy(), res.bone_frames[0, :3, 2].numpy().copy()))
        return res

    take = tracker.take_revised

    def recording_take():  # frames revised by a start race or the track back, as the tracker gave them
        late = take()
        for j, (res, version) in enumerate(late):
            i = len(tracked) - len(late) + j
            tracked[i] = (res.output_points.numpy().copy(), res.bone_frames[0, :3, 2].numpy().copy())
            versions[i] = version
        return late

    tracker.step, tracker.take_revised = recording_step, recording_take
    poses, _ = track_sequence(folder, observer, tracker, progress=False)
    assert tracker.body_version == 1 and poses.valid.all()
    before = np.array(versions) == 0
    assert 0 < before.sum() < len(versions)  # the move came mid-sequence
    names = list(tracker.generic.output_names)
    hips = [names.index(n) for n in ("pelvis", "l_hip", "r_hip")]
    legs = [names.index(n) for n in ("l_knee", "l_ankle", "l_toe", "r_knee", "r_ankle", "r_toe")]
    rest = [i for i in range(len(names)) if i not in hips + legs]
    points = np.stack([p for p, _ in tracked])
    up = np.stack([z for _, z in tracked])  # (T, 3) the pelvis' z axis (bone frame 0: the pelvis)
    dz = tracker.hip_shifts[0]
    np.testing.assert_allclose(poses.joints3d[:, rest], points[:, rest], atol=1e-4)
    assert float(np.linalg.norm(poses.joints3d[:, legs] - points[:, legs], axis=-1).max()) < 0.5 * abs(dz) + 0.005
    np.testing.assert_allclose(poses.joints3d[before][:, hips], points[before][:, hips] + dz * up[before][:, None],
                               atol=1e-4)
    np.testing.assert_allclose(poses.joints3d[~before], points[~before], atol=1e-6)
    body = Skeleton(str(poses.extra["body_urdf"]))
    fk = body.forward(torch.from_numpy(poses.angles)).output_points.numpy()
    np.testing.assert_allclose(fk, poses.joints3d, atol=1e-4)
