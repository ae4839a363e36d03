"""Retargeting motion-capture joint positions onto the skeleton."""

from __future__ import annotations

import math

import pytest
import torch

from conftest import shared_data
from torchtrack.checks import InputError
from torchtrack.skeleton import Skeleton
from torchtrack.synth.retarget import retarget_positions


#: Our joints the known-pose tests map onto the source's joints of the same name.
OWN_JOINTS = ("pelvis", "l_thigh", "l_shank", "l_foot", "l_toe", "r_thigh", "r_shank", "r_foot", "r_toe", "head",
              "head_top", "l_upperarm", "l_forearm", "l_hand", "l_hand_tip", "r_upperarm", "r_forearm", "r_hand",
              "r_hand_tip")


def _known_poses(subject: Skeleton, seed: int, T: int = 12) -> torch.Tensor:
    """(T, D) poses of ``subject``: placed and turned at random, every joint in the middle fifth of its range."""
    g = torch.Generator().manual_seed(seed)
    angles = subject.rest_angles().expand(T, -1).clone()
    angles[:, 0:2] = torch.rand(T, 2, generator=g) - 0.5
    angles[:, 3] = 2 * torch.rand(T, generator=g) - 1  # yaw
    inner = torch.rand(T, subject.num_dofs - 6, generator=g)
    span = (subject.upper - subject.lower)[6:]
    angles[:, 6:] = subject.lower[6:] + span * (0.4 + 0.2 * inner)  # mid-range poses
    return angles


def _reproduces(skel: Skeleton, subject: Skeleton, angles: torch.Tensor) -> None:
    """``skel`` retargeted onto ``subject``'s joints in ``angles`` reproduces its height and the points."""
    joints = subject(angles.double()).joints  # (T, 22, 3)
    res = retarget_positions(skel, joints, list(subject.joint_names), mapping={n: (n,) for n in OWN_JOINTS},
                             iterations=600)
    assert res.skeleton.height() == pytest.approx(subject.height(), abs=0.02)
    assert float(res.residual_m.mean()) < 0.01
    assert float(res.residual_m.max()) < 0.05


def test_recovers_known_poses_of_a_differently_sized_subject():
    """Source = our own chain with other proportions in known poses: the fit must reproduce the points."""
    skel = Skeleton.from_urdf()
    subject = skel.scaled_to_height(1.62).with_bone_lengths({"l_thigh": 0.40, "r_thigh": 0.40})
    _reproduces(skel, subject, _known_poses(subject, 3))


def test_the_marker_skeletons_shoulder_girdle():
    """The marker skeleton (``configs/body_markers.urdf``) is the body with a clavicle per side (and the ankle's
    inversion, the test below): raising the clavicle by e lifts the shoulder by L sin e about the pivot, bringing it
    forward by p moves it forward by L sin p (L the clavicle, pivot to shoulder: closed forms); and a subject of that
    chain at another size, its girdle and ankles at rest and the other joints in known poses, is reproduced by the
    retarget, which places the pivot and the shoulder from the source's medians."""
    from torchtrack.markers.model import MARKER_URDF
    from torchtrack.resources import builtin_config

    girdle = Skeleton.from_urdf(builtin_config(MARKER_URDF))
    assert girdle.num_dofs == Skeleton.from_urdf().num_dofs + 6
    L = girdle.joint_origin("l_shoulder_flex")[1]
    shoulder = list(girdle.joint_names).index("l_upperarm")
    rest = girdle.rest_angles().double()
    at_rest = girdle(rest[None]).joints[0, shoulder]
    for dof, axis in (("l_shoulder_elev", 2), ("l_shoulder_prot", 0)):
        moved = rest.clone()
        moved[girdle.dof_names.index(dof)] = 0.3
        delta = girdle(moved[None]).joints[0, shoulder] - at_rest
        assert float(delta[axis]) == pytest.approx(L * math.sin(0.3), abs=1e-6)
        assert float(delta[1]) == pytest.approx(-L * (1 - math.cos(0.3)), abs=1e-6)  # towards the pivot
    subject = girdle.scaled_to_height(1.62)
    angles = _known_poses(subject, 5)
    angles[:, [subject.dof_names.index(f"{s}_shoulder_{k}") for s in "lr" for k in ("elev", "prot")]] = 0.0
    angles[:, [subject.dof_names.index(f"{s}_ankle_inv") for s in "lr"]] = 0.0
    _reproduces(girdle, subject, angles)


def test_the_marker_skeletons_ankle_inverts():
    """The marker skeleton's ankle inverts: turning ``ankle_inv`` by a turns the toe (x forward, z down from the
    ankle) about the forward axis towards the midline, to (x, z sin a, z cos a) on the left and (x, -z sin a,
    z cos a) on the right (a closed form)."""
    from torchtrack.markers.model import MARKER_URDF
    from torchtrack.resources import builtin_config

    girdle = Skeleton.from_urdf(builtin_config(MARKER_URDF))
    rest = girdle.rest_angles().double()
    toe, ankle = (list(girdle.output_names).index(n) for n in ("l_toe", "l_ankle"))
    rest_fk = girdle(rest[None])
    x, _, z = (rest_fk.output_points[0, toe] - rest_fk.output_points[0, ankle]).tolist()
    for side, sign in (("l", 1.0), ("r", -1.0)):
        toe, ankle = (list(girdle.output_names).index(n) for n in (f"{side}_toe", f"{side}_ankle"))
        moved = rest.clone()
        moved[girdle.dof_names.index(f"{side}_ankle_inv")] = 0.2
        fk = girdle(moved[None])
        got = fk.output_points[0, toe] - fk.output_points[0, ankle]
        want = torch.tensor((x, sign * z * math.sin(0.2), z * math.cos(0.2)), dtype=got.dtype)
        torch.testing.assert_close(got, want, rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", ["131_01", "131_02"])
def test_cmu_bvh_retarget_follows_the_capture(name):
    from torchtrack.synth.bvh_motion import retarget_bvh

    path = shared_data("mocap", "cmu", f"{name}.bvh")
    res = retarget_bvh(path, Skeleton.from_urdf(), fps=15)  # the whole file, every 8th frame
    # measured at 30 fps: mean 13-16 mm, worst point 7-8 cm (toes and hand tips, placed differently by CMU)
    assert float(res.residual_m.mean()) < 0.02
    assert float(res.residual_m.max()) < 0.09
    assert 1.3 < res.skeleton.height() < 1.9
    # A human body, against Winter's segment proportions (Biomechanics and Motor Control of Human Movement, 4th
    # ed., Fig. 4.1, as fractions of the height H): shoulder joints 0.818 H above the floor, hips 0.530 H,
    # thigh + shank 0.491 H; the neck above the shoulder joints. CMU's `lowerneck` (at the collar bones) taken
    # for our neck gave shoulders at 0.87 H, hips at 0.59 H and legs of 0.55 H.
    body = res.skeleton
    H = body.height()
    z = body.rest_frames[body.frame_index(["l_upperarm", "l_thigh", "l_toe"])][:, 2, 3]
    p = body.proportions()
    assert float(z[0] - z[2]) / H == pytest.approx(0.818, abs=0.03)
    assert float(z[1] - z[2]) / H == pytest.approx(0.530, abs=0.035)
    assert (p["l_thigh"] + p["l_shank"]) / H == pytest.approx(0.491, abs=0.035)
    assert p["neck_above_shoulders"] > 0.01


def test_bad_source():
    skel = Skeleton.from_urdf()
    with pytest.raises(InputError, match="LeftHip"):
        retarget_positions(skel, torch.zeros(2, 1, 3), ["Hips"])
    with pytest.raises(InputError, match="NaN"):
        retarget_positions(skel, torch.full((2, 1, 3), float("nan")), ["Hips"])
