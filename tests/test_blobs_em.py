"""EM of the blobs on voxels (torchtrack.blobs.em)."""

from __future__ import annotations

import math

import torch

from torchtrack.blobs import BlobModel
from torchtrack.blobs.em import EMConfig, fit_blobs, fit_blobs_many, prior_blobs
from torchtrack.skeleton import Skeleton


def test_many_bodies_fitted_at_once_as_each_alone():
    """fit_blobs_many against fit_blobs run on each body in turn: the voxels of a body in a walking pose, four
    hypotheses (headings a quarter turn apart, one shifted and with the arms raised, as a re-acquisition tries),
    float64."""
    skel = Skeleton.from_urdf()
    blobs = BlobModel.from_config(skel)
    names = skel.dof_names
    g = torch.Generator().manual_seed(0)
    true = skel.rest_angles().double()
    true[names.index("l_hip_flex")], true[names.index("r_knee_flex")] = 0.4, 0.6
    mean, cov = blobs.gaussians(skel.forward(true[None]).bone_frames)  # (1, K, 3), (1, K, 3, 3)
    K = mean.shape[1]
    k = torch.randint(K, (3000,), generator=g)
    L = torch.linalg.cholesky(cov[0].double())
    points = mean[0, k].double() + (L[k] @ torch.randn(3000, 3, 1, generator=g, dtype=torch.float64))[..., 0]
    weights, sizes = torch.rand(3000, generator=g, dtype=torch.float64) + 0.5, torch.full((3000,), 0.03).double()
    starts = skel.rest_angles().double().repeat(4, 1)
    for h in range(4):
        starts[h, names.index("root_rz")] = h * math.pi / 2
    starts[3, names.index("root_tx")] = 0.2
    starts[3, names.index("l_shoulder_abd")] = 1.5
    m, c = blobs.gaussians(skel.forward(starts).bone_frames)
    priors = [prior_blobs(m[h].double(), c[h].double()) for h in range(4)]
    stacked = type(priors[0])(*(torch.stack([getattr(p, f) for p in priors]) for f in (
        "mean", "cov", "colour_mean", "colour_cov", "colour_known", "fill", "active")))
    config = EMConfig(min_fill=0.3)
    got, assign = fit_blobs_many(points, weights, sizes, stacked, config)
    for h in range(4):
        want, want_assign = fit_blobs(points, weights, sizes, None, priors[h], config, learn_colour=False)
        assert torch.equal(assign[h], want_assign)
        torch.testing.assert_close(got.mean[h], want.mean, rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(got.cov[h], want.cov, rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(got.fill[h], want.fill, rtol=1e-9, atol=1e-12)
        assert torch.equal(got.active[h], want.active)
    assert not torch.equal(assign[0], assign[1])  # the bodies differ: each voxel's blob is each body's own
