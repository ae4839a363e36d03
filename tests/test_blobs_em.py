"""EM of the blobs on voxels (torchtrack.blobs.em): the E-step against a plain loop, displaced blobs recovered,
batched sets as each alone."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import fields, replace

import pytest
import torch

from torchtrack.blobs import BlobModel
from torchtrack.blobs.em import Blobs, EMConfig, e_step, fit_blobs, prior_blobs
from torchtrack.skeleton import Skeleton
from torchtrack.synth.motion import procedural_motion

from conftest import voxelised_observation as _observation


def _frame(skel, blobs, angles, n, cameras, g):
    """n voxels drawn from the blobs of the body at ``angles``, each seen in some of ``cameras`` views with its
    blob's colour plus noise (float64)."""
    mean, cov = blobs.gaussians(skel.forward(angles[None]).bone_frames)
    K = mean.shape[1]
    k = torch.randint(K, (n,), generator=g)
    L = torch.linalg.cholesky(cov[0].double())
    points = mean[0, k].double() + (L[k] @ torch.randn(n, 3, 1, generator=g, dtype=torch.float64))[..., 0]
    colours = blobs.colour.double()[k][:, None].expand(n, cameras, 3) + 0.05 * torch.randn(n, cameras, 3, generator=g,
                                                                                        dtype=torch.float64)
    colours = colours.masked_fill(torch.rand(n, cameras, 1, generator=g) < 0.3, math.nan)
    weights, sizes = torch.rand(n, generator=g, dtype=torch.float64) + 0.5, torch.full((n,), 0.03).double()
    return points, weights, sizes, colours


def test_frames_of_different_sizes_fitted_at_once_as_each_alone():
    """fit_blobs of three frames padded into one batch against fit_blobs of each frame alone (float64): different
    voxel counts and cameras, bodies at different headings, colour models learnt for some blobs of some frames,
    one frame that does not learn colour; a quarter of the hypotheses' blobs start far from their voxels."""
    skel = Skeleton.from_urdf()
    blobs = BlobModel.from_config(skel)
    names = skel.dof_names
    g = torch.Generator().manual_seed(0)
    poses, frames = [], []
    for h, (n, cams) in enumerate(((3000, 4), (1800, 3), (2500, 4))):
        a = skel.rest_angles().double()
        a[names.index("root_rz")], a[names.index("root_tx")] = h * math.pi / 2, 0.3 * h
        a[names.index("l_hip_flex")], a[names.index("r_knee_flex")] = 0.4, 0.2 * h
        frames.append(_frame(skel, blobs, a, n, cams, g))
        a = a.clone()
        a[names.index("l_shoulder_abd")] = 1.2 * (h == 2)  # the prediction off the voxels' arm in one frame
        poses.append(a)
    m, c = blobs.gaussians(skel.forward(torch.stack(poses)).bone_frames)
    K = m.shape[1]
    priors = []
    for h in range(3):
        p = prior_blobs(m[h].double(), c[h].double())
        known = torch.rand(K, generator=g) < 0.5 * h  # frame 0: no colour model yet
        priors.append(replace(p, colour_mean=blobs.colour.double() + 0.02, colour_cov=0.01 * p.colour_cov,
                              colour_known=known))
    N, C = max(f[0].shape[0] for f in frames), max(f[3].shape[1] for f in frames)
    points = torch.full((3, N, 3), math.nan, dtype=torch.float64)
    weights, sizes = torch.zeros(3, N, dtype=torch.float64), torch.zeros(3, N, dtype=torch.float64)
    colours = torch.full((3, N, C, 3), math.nan, dtype=torch.float64)
    for h, (p, w, s, col) in enumerate(frames):
        points[h, :len(p)], weights[h, :len(p)], sizes[h, :len(p)] = p, w, s
        colours[h, :len(p), :col.shape[1]] = col
    stacked = Blobs(*(torch.stack([getattr(p, f.name) for p in priors]) for f in fields(Blobs)))
    config = EMConfig(min_fill=0.3)
    learn = torch.tensor([True, False, True])
    got, assign = fit_blobs(points, weights, sizes, colours, stacked, config, learn_colour=learn)
    for h, (p, w, s, col) in enumerate(frames):
        want, want_assign = fit_blobs(p, w, s, col, priors[h], config, learn_colour=bool(learn[h]))
        assert torch.equal(assign[h, :len(p)], want_assign)
        assert bool((assign[h, len(p):] == -1).all())  # the padding is no blob's
        for f in fields(Blobs):
            torch.testing.assert_close(getattr(got, f.name)[h], getattr(want, f.name), rtol=1e-9, atol=1e-12,
                                       msg=f"frame {h}: {f.name}")
    assert bool(got.colour_known[0].any()) and torch.equal(got.colour_known[1], priors[1].colour_known)
    assert not bool(got.active[2].all()) and bool(got.active[0].all())  # the raised arm's blobs found no voxels


@pytest.fixture(scope="module")
def skel() -> Skeleton:
    return Skeleton.from_urdf()


def test_e_step_matches_a_plain_loop():
    gen = torch.Generator().manual_seed(0)
    K, N, C = 4, 60, 3
    mean = torch.randn(K, 3, generator=gen, dtype=torch.float64)
    A = torch.randn(K, 3, 3, generator=gen, dtype=torch.float64)
    cov = A @ A.transpose(-1, -2) + 0.1 * torch.eye(3, dtype=torch.float64)
    blobs = prior_blobs(mean, cov)
    cm = torch.rand(K, 3, generator=gen, dtype=torch.float64)
    B = torch.randn(K, 3, 3, generator=gen, dtype=torch.float64)
    ccov = B @ B.transpose(-1, -2) * 0.01 + 0.01 * torch.eye(3, dtype=torch.float64)
    known = torch.tensor([True, False, True, True])  # blob 1 has no colour model yet: position only
    blobs = dataclasses.replace(blobs, colour_mean=cm, colour_cov=ccov, colour_known=known)
    pts = torch.randn(N, 3, generator=gen, dtype=torch.float64)
    col = torch.rand(N, C, 3, generator=gen, dtype=torch.float64)
    col[::5, 1] = float("nan")
    col[3::7] = float("nan")  # voxels no view sees: no colour term, no view
    col[1::5, 0] = float("nan")  # the first view that sees them is not view 0
    cfg = EMConfig(gate_mahalanobis2=2.0)  # gates out some blobs for some points
    assign, view, _ = e_step(pts, col, blobs, cfg)
    for n in range(N):
        best, best_view = None, None
        for k in range(K):
            d = pts[n] - mean[k]
            cost = float(d @ torch.linalg.solve(cov[k], d))
            if cost > cfg.gate_mahalanobis2:  # outside this blob's gate: it does not compete
                continue
            seeing = [v for v in range(C) if not torch.isnan(col[n, v]).any()]
            dc_best, v_best = 0.0, (seeing[0] if seeing else -1)  # no colour model, or unseen: position only
            if known[k] and seeing:
                dc_best = math.inf
                for v in seeing:
                    e = col[n, v] - cm[k]
                    dc = float(e @ torch.linalg.solve(ccov[k], e))
                    if dc < dc_best:
                        dc_best, v_best = dc, v
            cost += dc_best
            if best is None or cost < best[0]:
                best, best_view = (cost, k), v_best
        if best is None:
            assert int(assign[n]) == -1 and int(view[n]) == -1
            continue
        assert int(assign[n]) == best[1]
        assert int(view[n]) == best_view


def test_em_recovers_displaced_blobs(skel):
    """Blobs predicted 3 cm and 0.06 rad per joint off converge onto the voxels of the true pose."""
    blobs = BlobModel.from_config(skel)
    T = procedural_motion(skel, "walk", 1.0, 30, starfish_s=0.0)
    truth = T[20]
    obs = _observation(skel, blobs, truth)
    pred = truth.clone()
    pred[0] += 0.03
    pred[6:] += 0.06
    mean_p, cov_p = blobs.gaussians(skel.forward(skel.clamp(pred)[None]).bone_frames)
    mean_t, _ = blobs.gaussians(skel.forward(truth[None]).bone_frames)
    fitted, _ = fit_blobs(obs.points, obs.weights, obs.sizes, None, prior_blobs(mean_p[0], cov_p[0]),
                          EMConfig(iterations=6))
    before = (mean_p[0] - mean_t[0]).norm(dim=-1)
    after = (fitted.mean - mean_t[0]).norm(dim=-1)
    assert float(after.median()) < 0.5 * float(before.median())
    near = before < 0.06  # blobs that overlap their voxels at the start (the far ones may lose them)
    assert int(near.sum()) >= 8
    assert float(after[near].max()) < 0.035
    assert float(after[near].median()) < 0.015
    assert bool(fitted.active[near].all())
