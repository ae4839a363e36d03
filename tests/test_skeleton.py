"""Skeleton FK against a plain per-joint implementation written from the URDF text by hand."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import torch

from torchtrack.checks import InputError, ShapeError
from torchtrack.conventions import LANDMARKS
from torchtrack.resources import config_path
from torchtrack.skeleton import Skeleton
from torchtrack.skeleton.model import LANDMARK_FRAMES


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' formula, written out (independent of any library)."""
    a = axis / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def plain_fk(urdf_text: str, angles: dict[str, float]) -> dict[str, np.ndarray]:
    """World 4x4 of every link by walking the URDF joints from the root, one joint at a time."""
    root = ET.fromstring(urdf_text)
    joints = {}
    for j in root.iter("joint"):
        origin = j.find("origin")
        axis = j.find("axis")
        joints[j.find("child").get("link")] = (
            j.get("name"), j.get("type"), j.find("parent").get("link"),
            np.array([float(v) for v in origin.get("xyz").split()]),
            np.array([float(v) for v in axis.get("xyz").split()]) if axis is not None else None)
    out = {"world": np.eye(4)}

    def world(link: str) -> np.ndarray:
        if link not in out:
            name, kind, parent, xyz, axis = joints[link]
            local = np.eye(4)
            local[:3, 3] = xyz
            motion = np.eye(4)
            if kind == "revolute":
                motion[:3, :3] = _axis_angle(axis, angles[name])
            elif kind == "prismatic":
                motion[:3, 3] = axis / np.linalg.norm(axis) * angles[name]
            out[link] = world(parent) @ local @ motion
        return out[link]

    for link in joints:
        world(link)
    return out


@pytest.fixture(scope="module")
def skel() -> Skeleton:
    return Skeleton.from_urdf()


def _random_angles(skel: Skeleton, n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    lo, hi = skel.lower.clone(), skel.upper.clone()
    lo[:3], hi[:3] = -2.0, 2.0  # root translation
    lo[3:6], hi[3:6] = -3.0, 3.0  # root rotation
    return lo + (hi - lo) * torch.rand(n, skel.num_dofs, generator=g, dtype=torch.float64)


def test_dofs_and_limits_match_urdf(skel):
    root = ET.fromstring(config_path("body.urdf").read_text())
    movable = [j for j in root.iter("joint") if j.get("type") != "fixed"]
    assert sorted(skel.dof_names) == sorted(j.get("name") for j in movable)
    assert skel.dof_names[:6] == ("root_tx", "root_ty", "root_tz", "root_rz", "root_ry", "root_rx")
    assert skel.num_dofs == 32
    for j in movable:
        i = skel.dof_names.index(j.get("name"))
        lim = j.find("limit")
        assert skel.lower[i].item() == pytest.approx(float(lim.get("lower")))
        assert skel.upper[i].item() == pytest.approx(float(lim.get("upper")))
    # at least de Bem's 21 joints besides the root
    assert len(skel.joint_names) - 1 >= 21


def test_fk_matches_plain_implementation(skel):
    angles = _random_angles(skel, 5)
    res = skel(angles)
    for b in range(angles.shape[0]):
        ref = plain_fk(skel.urdf_text, dict(zip(skel.dof_names, angles[b].tolist())))
        lm_ref = np.stack([ref[LANDMARK_FRAMES[n]][:3, 3] for n in LANDMARKS])
        np.testing.assert_allclose(res.landmarks[b].numpy(), lm_ref, atol=1e-7)  # 0.1 um; pytorch-kinematics keeps some constants in float32
        bf_ref = np.stack([ref[n] for n in skel.bone_names])
        np.testing.assert_allclose(res.bone_frames[b].numpy(), bf_ref, atol=1e-7)  # 0.1 um; pytorch-kinematics keeps some constants in float32
        jt_ref = np.stack([ref[n][:3, 3] for n in skel.joint_names])
        np.testing.assert_allclose(res.joints[b].numpy(), jt_ref, atol=1e-7)  # 0.1 um; pytorch-kinematics keeps some constants in float32


def test_lean_bone_poses_match_the_plain_implementation_and_pytorch_kinematics(skel, device):
    """The particle filter's lean FK against the plain URDF walk (and pytorch-kinematics' FK, also its gradient)."""
    angles = _random_angles(skel, 6, seed=3)
    R, t = skel.bone_poses(angles)
    for b in range(angles.shape[0]):
        ref = plain_fk(skel.urdf_text, dict(zip(skel.dof_names, angles[b].tolist())))
        bf = np.stack([ref[n] for n in skel.bone_names])
        np.testing.assert_allclose(R[b].numpy(), bf[:, :3, :3], atol=1e-7)  # pytorch-kinematics' float32 constants
        np.testing.assert_allclose(t[b].numpy(), bf[:, :3, 3], atol=1e-7)
    # both ways of composing the levels: a product and a sum below LEAN_MANY_STATES states, multiply-adds from it
    for n in (300, 600):
        x = _random_angles(skel, n, seed=4).to(device)
        for dtype, tol in ((torch.float64, 1e-12), (torch.float32, 2e-5)):
            R, t = skel.bone_poses(x.to(dtype))
            T = skel(x.to(dtype)).bone_frames
            assert R.dtype == dtype and R.device.type == device.type
            torch.testing.assert_close(R, T[..., :3, :3], atol=tol, rtol=0)
            torch.testing.assert_close(t, T[..., :3, 3], atol=tol, rtol=0)
    xg = x[:4].clone().requires_grad_(True)
    with torch.enable_grad():  # other test modules turn gradients off for the whole session
        R, t = skel.bone_poses(xg)
        (R.sin().sum() + t.square().sum()).backward()
        lean = xg.grad.clone()
        xg.grad = None
        T = skel(xg).bone_frames
        (T[..., :3, :3].sin().sum() + T[..., :3, 3].square().sum()).backward()
    torch.testing.assert_close(lean, xg.grad, atol=1e-10, rtol=0)


def test_lockstep_bodies_are_each_bodys_plain_walk(skel):
    """Q bodies of other bone lengths in one batch (the marker filter's lockstep): each body's bones as the plain
    URDF walk of its own skeleton places them; a skeleton of another chain is refused."""
    from torchtrack.skeleton.model import LockstepBodies

    bodies = [skel, skel.scaled_to_height(1.55), skel.with_bone_lengths({"l_thigh": 0.5, "r_forearm": 0.2})]
    angles = torch.stack([_random_angles(skel, 3, seed=10 + q) for q in range(3)])  # (Q, N, D)
    R, t = LockstepBodies(bodies, torch.float64, "cpu")(angles)  # (nb, 3, 3, Q, N), (nb, 3, Q, N)
    for q, body in enumerate(bodies):
        for n in range(3):
            ref = plain_fk(body.urdf_text, dict(zip(body.dof_names, angles[q, n].tolist())))
            bf = np.stack([ref[b] for b in body.bone_names])
            np.testing.assert_allclose(R[..., q, n].numpy(), bf[:, :3, :3], atol=1e-7)
            np.testing.assert_allclose(t[..., q, n].numpy(), bf[:, :3, 3], atol=1e-7)
    other = ET.fromstring(skel.urdf_text)
    joint = next(j for j in other.iter("joint") if j.get("type") == "revolute")
    joint.find("axis").set("xyz", "0 0 1" if joint.find("axis").get("xyz") != "0 0 1" else "1 0 0")
    with pytest.raises(InputError, match="is not the chain of"):
        LockstepBodies([skel, Skeleton(ET.tostring(other, encoding="unicode"), "other.urdf")], torch.float64, "cpu")


def test_batched_equals_looped(skel, device):
    angles = _random_angles(skel, 64, seed=1).float().to(device)
    batched = skel.landmarks(angles)
    looped = torch.cat([skel.landmarks(angles[i:i + 1]) for i in range(angles.shape[0])])
    assert batched.device.type == device.type and batched.dtype == torch.float32
    torch.testing.assert_close(batched, looped, atol=1e-5, rtol=0)


def test_cuda_matches_cpu(skel):
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    angles = _random_angles(skel, 256, seed=2)
    torch.testing.assert_close(skel.landmarks(angles.cuda()).cpu(), skel.landmarks(angles), atol=1e-9, rtol=0)


def test_rest_pose_geometry(skel):
    lm = dict(zip(LANDMARKS, skel.landmarks(skel.rest_angles()[None].double())[0]))
    assert skel.height() == pytest.approx(1.75, abs=1e-6)
    assert lm["head"][2] > lm["neck"][2] > lm["spine"][2] > lm["pelvis"][2] > lm["l_knee"][2] > lm["l_ankle"][2]
    assert lm["l_shoulder"][1] > 0 > lm["r_shoulder"][1]  # left is +Y
    # positive flexion: elbow brings the wrist forward (+X), knee the ankle backward (-X), hip the knee forward
    for dof, lmk, sign in (("l_elbow_flex", "l_wrist", 1), ("r_knee_flex", "r_ankle", -1),
                           ("l_hip_flex", "l_knee", 1), ("r_shoulder_abd", "r_elbow", 0)):
        a = skel.rest_angles()
        a[skel.dof_names.index(dof)] = 0.5
        moved = dict(zip(LANDMARKS, skel.landmarks(a[None])[0]))
        if sign:
            assert torch.sign(moved[lmk][0]) == sign
        else:  # abduction moves the right arm outwards (-Y)
            assert moved[lmk][1] < lm[lmk][1] - 0.05


def test_proportions(skel):
    """Against the template's URDF numbers (scripts/make_body_urdf.py: the neck 0.45 m and the shoulders
    0.38 m up the torso, upright at rest) and an edit that lowers the neck 6 cm."""
    p = skel.proportions()
    assert p["height"] == pytest.approx(1.75, abs=1e-6)
    assert p["torso"] == pytest.approx(0.45, abs=1e-6) and p["l_thigh"] == pytest.approx(0.42, abs=1e-6)
    assert p["neck_above_shoulders"] == pytest.approx(0.07, abs=1e-6)
    x, y, z = skel.joint_origin("neck_flex")
    low = skel.with_joint_origins({"neck_flex": (x, y, z - 0.06)}).proportions()
    assert low["neck_above_shoulders"] == pytest.approx(0.01, abs=1e-6)
    assert low["torso"] == pytest.approx(0.39, abs=1e-6) and low["l_thigh"] == pytest.approx(0.42, abs=1e-6)


def test_joints_raised_move_what_they_carry_along_the_parents_axis(skel):
    """Raising the neck 4 cm on the torso, in a bent pose: the head's landmarks move 4 cm along the torso's own
    z axis (its frame from forward kinematics), the shoulders and everything off the neck do not move."""
    angles = _random_angles(skel, 3).float()
    fk = skel.forward(angles)
    moved = skel.with_joints_raised({"neck_flex": 0.04}).forward(angles)
    torso_z = fk.bone_frames[:, list(skel.bone_names).index("torso"), :3, 2]  # (B, 3)
    out = list(skel.output_names)
    for name in ("neck", "head", "head_top"):
        i = out.index(name)
        torch.testing.assert_close(moved.output_points[:, i] - fk.output_points[:, i], 0.04 * torso_z,
                                   atol=1e-5, rtol=0)
    for name in ("l_shoulder", "r_wrist", "spine", "l_ankle"):
        i = out.index(name)
        torch.testing.assert_close(moved.output_points[:, i], fk.output_points[:, i], atol=1e-6, rtol=0)


def test_limits_clamp(skel):
    angles = _random_angles(skel, 10) * 3.0
    clamped = skel.clamp(angles)
    assert torch.all(clamped >= skel.lower.double()) and torch.all(clamped <= skel.upper.double())
    inside = (angles >= skel.lower.double()) & (angles <= skel.upper.double())
    assert torch.equal(clamped[inside], angles[inside])


def test_scaling(skel):
    tall = skel.scaled_to_height(1.90)
    assert tall.height() == pytest.approx(1.90, abs=1e-5)
    np.testing.assert_allclose(tall.bone_lengths.numpy(), skel.bone_lengths.numpy() * 1.90 / 1.75, rtol=1e-5)
    long_leg = skel.with_bone_lengths({"l_shank": 0.5})
    i = skel.bone_names.index("l_shank")
    assert long_leg.bone_lengths[i].item() == pytest.approx(0.5, abs=1e-6)
    lm = long_leg.landmarks(long_leg.rest_angles()[None].double())[0]
    knee, ankle = lm[LANDMARKS.index("l_knee")], lm[LANDMARKS.index("l_ankle")]
    assert (knee - ankle).norm().item() == pytest.approx(0.5, abs=1e-6)
    with pytest.raises(InputError, match="metres"):
        skel.scaled_to_height(175)
    with pytest.raises(InputError, match="unknown bone"):
        skel.with_bone_lengths({"tail": 0.3})


def test_bad_input(skel):
    with pytest.raises(ShapeError, match="angles"):
        skel.landmarks(torch.zeros(2, 31))
    bad = torch.zeros(1, skel.num_dofs)
    bad[0, 7] = float("nan")
    with pytest.raises(InputError, match="NaN"):
        skel.landmarks(bad)
    with pytest.raises(InputError, match="not found"):
        Skeleton.from_urdf("/nonexistent/body.urdf")


@pytest.mark.parametrize("markers, name", [(False, "body.urdf"), (True, "body_markers.urdf")])
def test_shipped_body_urdfs_are_what_their_generator_writes(markers, name):
    """configs/body.urdf and configs/body_markers.urdf are regenerated from scripts/make_body_urdf.py's tables, not
    edited by hand: each equals the generator's text."""
    import importlib.util

    from torchtrack.resources import builtin_config

    path = Path(__file__).resolve().parents[1] / "scripts" / "make_body_urdf.py"
    spec = importlib.util.spec_from_file_location("make_body_urdf", path)
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    assert builtin_config(name).read_text() == gen.build(markers)
