"""Poses apart from any frame (torchtrack.tracking.poses): the body's symmetries against their closed forms, the
real captures' prior."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchtrack.resources import builtin_config
from torchtrack.skeleton import Skeleton
from torchtrack.tracking.poses import POSE_PRIOR, mirrored, real_pose_prior, turned_round


@pytest.fixture(scope="module")
def skel() -> Skeleton:
    return Skeleton.from_urdf()


def _random_states(skel, height_m, seed, n=16):
    """The skeleton scaled to ``height_m``; ``n`` random states of it (limbs within the limits, the root anywhere
    near the origin, any heading, small tilts); and the output points' order with left and right swapped."""
    subj = skel.scaled_to_height(height_m)
    gen = torch.Generator().manual_seed(seed)
    a = subj.lower + (subj.upper - subj.lower) * torch.rand(n, subj.num_dofs, generator=gen, dtype=subj.lower.dtype)
    a[:, :3] = torch.randn(n, 3, generator=gen, dtype=a.dtype)
    a[:, 3:6] = torch.randn(n, 3, generator=gen, dtype=a.dtype) * torch.tensor([2.0, 0.3, 0.3], dtype=a.dtype)
    names = list(subj.output_names)
    other = {"l_": "r_", "r_": "l_"}
    swap = [names.index(other[n[:2]] + n[2:]) if n[:2] in other else i for i, n in enumerate(names)]
    return subj, a, swap


def test_turned_round_is_the_reflection_through_the_frontal_plane(skel):
    """The start turned round, against the closed form: for any state (random tilts and limbs within the limits),
    its output points, left and right swapped, are the original's reflected through the vertical plane through the
    root across its heading."""
    subj, a, swap = _random_states(skel, 1.8, seed=3)
    p = subj.forward(a).output_points.double()
    q = subj.forward(turned_round(subj, a)).output_points.double()[:, swap]
    normal = torch.stack([torch.cos(a[:, 3]), torch.sin(a[:, 3]), torch.zeros_like(a[:, 3])], -1).double()
    along = ((p - a[:, None, :3].double()) * normal[:, None]).sum(-1, keepdim=True)
    assert torch.allclose(q, p - 2 * along * normal[:, None], atol=1e-5)
    assert torch.allclose(turned_round(subj, turned_round(subj, a))[:, 4:], a[:, 4:])  # twice: back (heading +2 pi)


def test_mirrored_is_the_reflection_through_the_xz_plane(skel):
    """The left-right mirror against the closed form: for any state, its output points, left and right swapped,
    are the original's with y negated."""
    subj, a, swap = _random_states(skel, 1.7, seed=4)
    p = subj.forward(a).output_points.double()
    q = subj.forward(mirrored(subj, a)).output_points.double()[:, swap]
    assert torch.allclose(q, p * torch.tensor([1.0, -1.0, 1.0], dtype=p.dtype), atol=1e-5)


def test_the_real_pose_prior_leaves_a_subject_out(skel):
    """The built-in prior of real poses: every pose within the joint limits, root translation and heading zero;
    leaving a subject out drops exactly the poses of the captures named after it (the file's own sources)."""

    sources = np.load(builtin_config(POSE_PRIOR))["source"]
    every = real_pose_prior(skel)
    assert every.shape == (len(sources), skel.num_dofs) and len(set(sources.tolist())) >= 3
    assert torch.equal(every, skel.clamp(every)) and not every[:, [0, 1, 2, 3]].any()
    for subject in ("131_", "85_"):
        left = real_pose_prior(skel, exclude=(subject,))
        assert left.shape[0] == sum(subject not in s for s in sources.tolist()) < every.shape[0]
