"""Forward kinematics of several bodies at once (torchtrack/skeleton/stack.py) against pytorch-kinematics, body by
body."""

from __future__ import annotations

import pytest
import torch

from torchtrack.checks import InputError
from torchtrack.skeleton import Skeleton
from torchtrack.skeleton.stack import SkeletonStack


@pytest.fixture(scope="module")
def bodies():
    g = Skeleton.from_urdf()
    return [g.scaled_to_height(1.6), g.with_bone_lengths({"torso": 0.3, "l_thigh": 0.5, "r_forearm": 0.2}),
            g.with_joints_raised({"neck_flex": 0.05}), g]


def test_each_body_posed_as_pytorch_kinematics_poses_it(bodies):
    gen = torch.Generator().manual_seed(0)
    stack = SkeletonStack(bodies)
    a = (torch.rand(len(bodies), bodies[0].num_dofs, generator=gen, dtype=torch.float64) - 0.5) * 4
    T = stack.forward_frames(a)
    for b, body in enumerate(bodies):
        torch.testing.assert_close(T[b], body.forward_frames(a[b:b + 1])[0], rtol=0, atol=1e-12)
    fk = stack.forward(a.float())
    for b, body in enumerate(bodies):
        want = body.forward(a[b:b + 1].float())
        for name in ("landmarks", "joints", "output_points", "bone_frames"):
            torch.testing.assert_close(getattr(fk, name)[b], getattr(want, name)[0], rtol=0, atol=2e-5)
    # a sub-stack keeps its bodies; a stack of one poses that body at every row
    torch.testing.assert_close(stack.index([2, 0]).forward_frames(a[[2, 0]]), T[[2, 0]], rtol=0, atol=0)
    one = SkeletonStack([bodies[1]])
    many = one.forward_frames(a)
    for b in range(len(bodies)):
        torch.testing.assert_close(many[b], bodies[1].forward_frames(a[b:b + 1])[0], rtol=0, atol=1e-12)


def test_bodies_of_another_chain_are_refused(bodies, tmp_path):
    text = bodies[0].urdf_text.replace('name="neck_twist"', 'name="neck_turn"')
    with pytest.raises(InputError, match="not the chain"):
        SkeletonStack([bodies[0], Skeleton(text, source="other.urdf")])
    with pytest.raises(InputError, match="no bodies"):
        SkeletonStack([])
