"""The subject's body and pose from 3D landmarks (torchtrack.tracking.landmark_fit), against the ground truth of
synthetic bodies whose proportions one height scale cannot represent."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchtrack.checks import InputError
from torchtrack.io.poses import load_poses, save_poses
from torchtrack.skeleton import Skeleton
from torchtrack.synth.motion import procedural_motion
from torchtrack.tracking.landmark_fit import fit_to_landmarks, initial_pose

#: The points a keypoint tool gives: the 16 landmarks and the head's top.
NAMES = ("pelvis", "spine", "neck", "head", "l_shoulder", "l_elbow", "l_wrist", "r_shoulder", "r_elbow", "r_wrist",
         "l_hip", "l_knee", "l_ankle", "r_hip", "r_knee", "r_ankle", "head_top")
#: One bone of each fitted group.
BONES = ("pelvis", "torso", "head", "l_upperarm", "r_forearm", "l_thigh", "r_shank")


@pytest.fixture(scope="module")
def skel() -> Skeleton:
    return Skeleton.from_urdf()


@pytest.fixture(scope="module")
def subject(skel) -> Skeleton:
    """A 1.80 m body: torso 0.88x, thighs 1.08x, shanks 1.12x, upper arms 0.95x the template's, the neck 5 cm
    lower and the shoulders 3 cm higher on the trunk."""
    subj = skel.scaled_to_height(1.80)
    length = dict(zip(subj.bone_names, subj.bone_lengths.tolist()))
    subj = subj.with_bone_lengths({"torso": 0.88 * length["torso"], "l_thigh": 1.08 * length["l_thigh"],
                                   "r_thigh": 1.08 * length["r_thigh"], "l_shank": 1.12 * length["l_shank"],
                                   "r_shank": 1.12 * length["r_shank"], "l_upperarm": 0.95 * length["l_upperarm"],
                                   "r_upperarm": 0.95 * length["r_upperarm"]})
    moved = {}
    for joint, dz in (("neck_flex", -0.05), ("l_shoulder_flex", 0.03), ("r_shoulder_flex", 0.03)):
        x, y, z = subj.joint_origin(joint)
        moved[joint] = (x, y, z + dz)
    return subj.with_joint_origins(moved)


def _points(body: Skeleton, angles: torch.Tensor) -> torch.Tensor:
    out = list(body.output_names)
    return body.forward(angles).output_points[:, [out.index(n) for n in NAMES]]


def _shoulder_height(body: Skeleton) -> float:
    """The shoulders' height above the hips in the rest pose (m)."""
    out = list(body.output_names)
    p = body.forward(body.rest_angles()[None]).output_points[0]
    return float(p[out.index("l_shoulder"), 2] - p[out.index("l_hip"), 2])


@pytest.mark.parametrize("frame", [0, 12])
def test_one_frames_landmarks_give_the_subjects_bones_and_pose(skel, subject, frame):
    T = procedural_motion(subject, "walk", 0.5, 30, starfish_s=0.0)
    truth = _points(subject, T[frame:frame + 1])[0]  # (L, 3)
    angles, body = fit_to_landmarks(skel, NAMES, truth)
    assert angles.shape == (skel.num_dofs,)
    fitted, true = dict(zip(body.bone_names, body.bone_lengths.tolist())), dict(
        zip(subject.bone_names, subject.bone_lengths.tolist()))
    for bone in BONES:
        assert fitted[bone] == pytest.approx(true[bone], abs=0.003), (bone, fitted[bone], true[bone])
    assert body.proportions()["neck_above_shoulders"] == pytest.approx(
        subject.proportions()["neck_above_shoulders"], abs=0.005)
    assert _shoulder_height(body) == pytest.approx(_shoulder_height(subject), abs=0.005)
    err = (_points(body, angles[None])[0] - truth).norm(dim=-1)
    assert float(err.mean()) < 0.002 and float(err.max()) < 0.005, err
    # the template scaled to the subject's height cannot: its torso and legs are off by centimetres
    angles_s, scaled = fit_to_landmarks(skel, NAMES, truth, fit_bones=False)
    assert float((_points(scaled, angles_s[None])[0] - truth).norm(dim=-1).mean()) > 5 * float(err.mean()) + 0.01


def test_frames_share_one_body_and_missing_points_are_left_out(skel, subject):
    T = procedural_motion(subject, "walk", 0.5, 30, starfish_s=0.0)[::5]  # (3, D)
    truth = _points(subject, T).clone()
    truth[0, NAMES.index("l_wrist")] = float("nan")  # a keypoint a tool missed in one frame
    truth[1, NAMES.index("r_knee")] = float("nan")
    angles, body = fit_to_landmarks(skel, NAMES, truth.numpy())
    assert angles.shape == (T.shape[0], skel.num_dofs)
    true = dict(zip(subject.bone_names, subject.bone_lengths.tolist()))
    for bone, length in zip(body.bone_names, body.bone_lengths.tolist()):
        if bone in BONES:
            assert length == pytest.approx(true[bone], abs=0.005), bone
    err = (_points(body, angles) - _points(subject, T)).norm(dim=-1)  # the missing points too
    assert float(err.mean()) < 0.004, err


def test_bad_landmarks_get_clear_errors(skel, subject):
    truth = _points(subject, subject.rest_angles()[None])[0]
    with pytest.raises(InputError, match="unknown landmarks.*'nose'"):
        fit_to_landmarks(skel, [*NAMES[:-1], "nose"], truth)
    with pytest.raises(InputError, match=r"\(L, 3\) or \(T, L, 3\)"):
        fit_to_landmarks(skel, NAMES, truth[:5])
    with pytest.raises(InputError, match="every landmark is NaN"):
        fit_to_landmarks(skel, NAMES, torch.full_like(truth, float("nan")))
    with pytest.raises(InputError, match="no segment to scale"):  # nothing to tell the subject's size
        keep = [NAMES.index(n) for n in ("pelvis", "l_shoulder", "r_shoulder", "l_hip", "r_hip")]
        fit_to_landmarks(skel, [NAMES[i] for i in keep], truth[keep])
    # a frame whose trunk is lost cannot place its root, and would spoil the body the frames share
    frames = torch.stack([truth, truth, truth]).clone()
    frames[1, [NAMES.index(n) for n in ("pelvis", "spine", "l_shoulder", "r_shoulder", "l_hip")]] = float("nan")
    with pytest.raises(InputError, match=r"frame \[1\] of 3 has fewer than 3 trunk points"):
        fit_to_landmarks(skel, NAMES, frames)


def test_points_on_any_device_and_with_grad_are_taken(skel, subject):
    truth = _points(subject, procedural_motion(subject, "walk", 0.2, 30, starfish_s=0.0)[2:3])[0]
    a, body = fit_to_landmarks(skel, NAMES, truth.clone().requires_grad_(True), rounds=2)
    assert not a.requires_grad and float((_points(body, a[None])[0] - truth).norm(dim=-1).mean()) < 0.01


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_fit_matches_cpu(skel, subject):
    truth = _points(subject, procedural_motion(subject, "walk", 0.2, 30, starfish_s=0.0)[2:3])[0]
    a_cpu, b_cpu = fit_to_landmarks(skel, NAMES, truth, rounds=2)
    a_gpu, b_gpu = fit_to_landmarks(skel.to(torch.device("cuda")), NAMES, truth.cuda(), rounds=2)
    assert a_gpu.is_cuda
    np.testing.assert_allclose(b_gpu.bone_lengths.cpu().numpy(), b_cpu.bone_lengths.numpy(), atol=1e-3)
    np.testing.assert_allclose(_points(b_gpu.cpu(), a_gpu.cpu()[None]).numpy(),
                               _points(b_cpu, a_cpu[None]).numpy(), atol=2e-3)


def test_initial_pose_file_carries_the_body_to_the_cli(tmp_path, skel, subject):
    """initial_pose -> save_poses -> the CLI's reader gives back the same state and body, and a tracker started
    from it uses that body."""
    from torchtrack.tracking.pipeline import read_start_pose as _initial_pose
    from torchtrack.tracking.markerless import MarkerlessTracker

    a = procedural_motion(subject, "walk", 0.2, 30, starfish_s=0.0)[3]
    save_poses(initial_pose(subject, a), tmp_path / "init.npz")
    poses = load_poses(tmp_path / "init.npz")
    np.testing.assert_allclose(poses.landmarks()[0], subject.landmarks(a[None])[0].numpy(), atol=1e-6)
    angles, height, body = _initial_pose(tmp_path / "init.npz")
    np.testing.assert_allclose(angles, a.numpy(), atol=1e-6)
    assert height == pytest.approx(subject.height(), abs=1e-6)
    np.testing.assert_allclose(body.bone_lengths.numpy(), subject.bone_lengths.numpy(), atol=1e-6)
    assert body.joint_origin("neck_flex") == pytest.approx(subject.joint_origin("neck_flex"), abs=1e-6)
    tracker = MarkerlessTracker(skel)
    tracker.initialize_from_pose(torch.as_tensor(angles), skeleton=body)
    np.testing.assert_allclose(tracker.subject.skeleton.forward(torch.as_tensor(angles)[None]).output_points[0].numpy(),
                               subject.forward(a[None]).output_points[0].numpy(), atol=1e-5)
    with pytest.raises(InputError, match="NaN"):
        initial_pose(subject, torch.full_like(a, float("nan")))


def test_a_body_of_other_dofs_in_an_initial_pose_file_is_refused(tmp_path, skel, subject):
    from torchtrack.tracking.pipeline import read_start_pose as _initial_pose

    rec = initial_pose(subject, subject.rest_angles())
    text = str(rec.extra["body_urdf"])
    start = text.index('<joint name="r_wrist_flex"')  # drop one hinge (its child link stays, fixed)
    joint = text[start:text.index("</joint>", start) + len("</joint>")]
    rec.extra["body_urdf"] = np.asarray(text.replace(joint, joint.replace('type="revolute"', 'type="fixed"')))
    save_poses(rec, tmp_path / "init.npz")
    with pytest.raises(InputError, match="body_urdf.*other DOFs"):
        _initial_pose(tmp_path / "init.npz")
