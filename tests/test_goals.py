"""The tracker's goals (torchtrack.tracking.goals): rotations against scipy, goals from exact blobs, the root fit,
the floor contact.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from torchtrack.blobs import BlobModel
from torchtrack.skeleton import root_rotation_angles, root_rotation_matrix
from torchtrack.skeleton import Skeleton
from torchtrack.skeleton.model import JOINT_FRAMES
from torchtrack.synth.motion import procedural_motion
from torchtrack.tracking.goals import (GoalModel, bound_rotation, feet_index, floor_contact, least_rotation,
                                       weighted_kabsch)

torch.set_grad_enabled(False)


@pytest.fixture(scope="module")
def skel() -> Skeleton:
    return Skeleton.from_urdf()


def test_root_rotation_matches_scipy_and_the_urdf_chain(skel):
    rng = np.random.default_rng(0)
    e = rng.uniform([-3, -1.4, -3], [3, 1.4, 3], size=(50, 3))
    R_ref = Rotation.from_euler("ZYX", e).as_matrix()  # intrinsic z, y, x: Rz Ry Rx
    R = root_rotation_matrix(torch.tensor(e))
    np.testing.assert_allclose(R.numpy(), R_ref, atol=1e-12)
    np.testing.assert_allclose(root_rotation_angles(torch.tensor(R_ref)).numpy(), e, atol=1e-9)
    # and it is the rotation the URDF's root joints give the pelvis
    angles = skel.rest_angles().double().repeat(5, 1)
    angles[:, 3:6] = torch.tensor(e[:5])
    pelvis = skel.forward_frames(angles)[:, skel.frame_index(["pelvis"])[0], :3, :3]
    np.testing.assert_allclose(pelvis.numpy(), R_ref[:5], atol=1e-9)


def test_least_rotation_takes_a_onto_b_with_the_least_angle():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(40, 3))
    b = rng.normal(size=(40, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    R = least_rotation(torch.tensor(a), torch.tensor(b)).numpy()
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R, a), b, atol=1e-12)
    angle = Rotation.from_matrix(R).magnitude()
    np.testing.assert_allclose(angle, np.arccos(np.clip((a * b).sum(1), -1, 1)), atol=1e-9)
    # about the axis a x b: the rotation vector along it
    axis = np.cross(a, b)
    np.testing.assert_allclose(Rotation.from_matrix(R).as_rotvec(), axis / np.linalg.norm(axis, axis=1,
                               keepdims=True) * angle[:, None], atol=1e-9)


def test_weighted_kabsch_recovers_a_rigid_motion_and_matches_scipy():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(3, 7, 3))
    R_true = Rotation.random(3, random_state=3).as_matrix()
    t_true = rng.normal(size=(3, 3))
    dst = np.einsum("bij,bnj->bni", R_true, src) + t_true[:, None]
    w = rng.uniform(0.1, 2.0, size=(3, 7))
    R, t = weighted_kabsch(torch.tensor(src), torch.tensor(dst), torch.tensor(w))
    np.testing.assert_allclose(R.numpy(), R_true, atol=1e-10)
    np.testing.assert_allclose(t.numpy(), t_true, atol=1e-10)
    # with noise: the same rotation as scipy's weighted align_vectors on centred points
    noisy = dst + rng.normal(scale=0.05, size=dst.shape)
    R, _ = weighted_kabsch(torch.tensor(src), torch.tensor(noisy), torch.tensor(w))
    for b in range(3):
        wn = w[b] / w[b].sum()
        cs, cd = (wn[:, None] * src[b]).sum(0), (wn[:, None] * noisy[b]).sum(0)
        ref, _ = Rotation.align_vectors(noisy[b] - cd, src[b] - cs, weights=w[b])
        np.testing.assert_allclose(R[b].numpy(), ref.as_matrix(), atol=1e-8)


def test_bound_rotation_clips_the_angle_about_the_same_axis():
    rv = np.array([[0.0, 0.0, 2.0], [0.3, -0.2, 0.1]])
    R = bound_rotation(torch.tensor(Rotation.from_rotvec(rv).as_matrix()), 0.5).numpy()
    out = Rotation.from_matrix(R).as_rotvec()
    np.testing.assert_allclose(out[0], [0, 0, 0.5], atol=1e-9)
    np.testing.assert_allclose(out[1], rv[1], atol=1e-9)  # under the bound: unchanged


@pytest.mark.parametrize("bound", [0.4, 0.01, 2.0])
@pytest.mark.parametrize("dtype, atol", [(torch.float64, 1e-9), (torch.float32, 2e-6)])
def test_bound_rotation_matches_scipy_at_every_angle(dtype, atol, bound):
    """Random axes at angles from 0 to a half turn (near it, where the skew part vanishes, and at it), bounds from
    small to over a quarter turn: scipy's rotation vector clipped to the bound, or the rotation unchanged under it."""
    rng = np.random.default_rng(4)
    axis = rng.normal(size=(60, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.concatenate([rng.uniform(0, np.pi, 50), np.pi - np.logspace(-8, -2, 5), [np.pi] * 5])
    rv = axis * angle[:, None]
    R = bound_rotation(torch.tensor(Rotation.from_rotvec(rv).as_matrix(), dtype=dtype), bound).double().numpy()
    expected = rv * np.minimum(1.0, bound / angle)[:, None]
    got = Rotation.from_matrix(R).as_rotvec()
    half = angle == np.pi  # a half turn about a is one about -a: either clipped rotation is right
    np.testing.assert_allclose(got[~half], expected[~half], atol=atol)
    np.testing.assert_allclose(np.abs((got[half] * expected[half]).sum(1)), bound ** 2, atol=atol)


def test_goals_from_exact_blobs_are_the_true_joints(skel):
    """Blobs placed by the true pose, bones predicted 0.1 rad off: every joint's goal is its true position."""
    blobs = BlobModel.from_config(skel).double()
    gm = GoalModel(skel, blobs).double()
    truth = procedural_motion(skel, "kick", 1.0, 30, starfish_s=0.0)[15].double()
    pred = truth.clone()
    pred[6:] += 0.1 * torch.cos(torch.arange(pred.shape[0] - 6, dtype=torch.float64))
    fk_t, fk_p = skel.forward(truth[None]), skel.forward(skel.clamp(pred)[None])
    mean, cov = blobs.gaussians(fk_t.bone_frames)
    goals, w = gm.joint_goals(fk_p.bone_frames, mean, cov, torch.ones(1, blobs.num_blobs, dtype=torch.float64))
    # joints whose bones have elongated blobs (limbs) get their true positions exactly; round blobs (pelvis,
    # hands, feet) keep the predicted orientation, so their far joints are only close
    err = (goals - fk_t.joints).norm(dim=-1)[0]
    assert bool((w > 0).all())
    from torchtrack.skeleton.model import JOINT_FRAMES

    for name in ("l_forearm", "r_forearm", "l_shank", "r_shank", "l_hand", "r_foot"):
        assert float(err[JOINT_FRAMES.index(name)]) < 1e-3, name
    for name in ("pelvis", "torso", "thorax", "head"):  # two-blob bones and the pelvis width: exact too
        assert float(err[JOINT_FRAMES.index(name)]) < 1e-6, name


def test_fit_root_recovers_a_moved_trunk(skel):
    blobs = BlobModel.from_config(skel)
    gm = GoalModel(skel, blobs)
    truth = skel.rest_angles().clone()
    truth[3] = 0.3  # yaw
    truth[0:2] = torch.tensor([0.2, -0.1])
    start = skel.rest_angles()
    fk_t, fk_s = skel.forward(truth[None]), skel.forward(start[None])
    w = torch.ones(1, fk_t.joints.shape[1])
    out = gm.fit_root(start[None], fk_s.joints, fk_t.joints, w, max_rotation=1.0)
    np.testing.assert_allclose(out[0, :6].numpy(), truth[:6].numpy(), atol=1e-5)
    bounded = gm.fit_root(start[None], fk_s.joints, fk_t.joints, w, max_rotation=0.1)
    assert abs(float(bounded[0, 3]) - 0.1) < 1e-5  # the heading change is clipped


def test_floor_contact_stands_the_lowest_foot_on_the_floor():
    """Worked by hand: two frames, 22 joints; the support foot's ankle and toe goals move down together."""
    G = len(JOINT_FRAMES)
    la, lt, ra, rt = (JOINT_FRAMES.index(n) for n in ("l_foot", "l_toe", "r_foot", "r_toe"))
    goals = torch.zeros(2, G, 3)
    weights = torch.full((2, G), 0.5)
    joints = torch.full((2, G, 3), 7.0)
    # frame 0: left sole at min(0.30, 0.38 - 0.08) = 0.30, right sole at min(0.25, 0.40 - 0.08) = 0.25: right
    goals[0, la], goals[0, lt] = torch.tensor([0.1, 0.2, 0.38]), torch.tensor([0.2, 0.2, 0.30])
    goals[0, ra], goals[0, rt] = torch.tensor([0.1, -0.2, 0.40]), torch.tensor([0.2, -0.2, 0.25])
    # frame 1: the left foot has no goals (from the joints: heel 0.12 - 0.08 = 0.04 under the toe's 0.10);
    # right sole 0.20: the left foot is the support; its ankle gets a goal from the joint, weighted 1, and its
    # toe none (a goal from the prediction would hold the foot's pitch)
    weights[1, [la, lt]] = 0.0
    joints[1, la], joints[1, lt] = torch.tensor([0.0, 0.1, 0.12]), torch.tensor([0.1, 0.1, 0.10])
    goals[1, ra], goals[1, rt] = torch.tensor([0.0, -0.1, 0.28]), torch.tensor([0.1, -0.1, 0.20])
    inputs = [x.clone() for x in (goals, weights, joints)]
    out, w = floor_contact(goals, weights, joints, 0.05, feet_index(), torch.tensor([0.08, 0.08]))
    assert all(torch.equal(a, b) for a, b in zip(inputs, (goals, weights, joints)))  # the inputs are not modified
    np.testing.assert_allclose(out[0, ra].numpy(), [0.1, -0.2, 0.20], atol=1e-6)  # moved by 0.05 - 0.25
    np.testing.assert_allclose(out[0, rt].numpy(), [0.2, -0.2, 0.05], atol=1e-6)
    np.testing.assert_allclose(out[1, la].numpy(), [0.0, 0.1, 0.13], atol=1e-6)  # moved by 0.05 - 0.04
    changed = torch.zeros(2, G, dtype=torch.bool)
    changed[0, [ra, rt]] = changed[1, la] = True
    assert torch.equal(out[~changed], goals[~changed])  # everything else untouched, the left toe's too
    assert torch.equal(w[~changed], weights[~changed])
    np.testing.assert_allclose(w[changed].numpy(), 1.0)  # 0.5 and 0 raised to the minimum weight
