"""The fast Bayesian grid against a straightforward Algorithm 1 (per voxel, per camera, per window pixel)."""

from __future__ import annotations

import dataclasses
import math
import warnings

import cv2
import numpy as np
import pytest
import torch

from torchtrack.background import BackgroundConfig, BackgroundModel
from torchtrack.checks import InputError, ShapeError
from torchtrack.occupancy.bayes import BayesConfig, BayesianGrid, window_sum
from torchtrack.occupancy.grid import GridSpec, VoxelLookup
from torchtrack.synth.sequence import RigConfig, make_ring_rig

# BT.601 as kornia defines YUV, written out for the reference
RGB2YUV = np.array([[0.299, 0.587, 0.114], [-0.147, -0.289, 0.436], [0.615, -0.515, -0.100]])


def detection(cfg: BayesConfig) -> tuple[float, float]:
    """p(F=1 | G=1) and p(F=1 | G=0) written out from ALGORITHMS.md §1 (S: the pixel samples the voxel, R:
    another object on its viewing line)."""
    s1, r1 = cfg.p_sample, cfg.p_other
    return (1 - s1) * 0.5 + s1 * cfg.pd, (1 - s1) * 0.5 + s1 * (r1 * cfg.pd + (1 - r1) * cfg.pfa)


def algorithm1(rig, bg_mean, bg_std, images, spec: GridSpec, cfg: BayesConfig, shadow_min_ratio: float = 0.0,
               luminance_relax: float = 1.0, shadow_min_gain: float = 1.0) -> np.ndarray:
    """Posterior P(G=1) per voxel, computed the slow way.

    Voxel centres are projected with cv2.projectPoints (an independent projection); each camera's pixels in
    the k x k window around the nearest pixel multiply p(I|G) into both hypotheses (in log space). ``bg_std``
    is the relaxed std; a pixel whose Y lies outside ``[r, 1 / r]`` times the background's Y is judged with the
    unrelaxed Y std ``bg_std / luminance_relax`` (the background model's shadow band). For a voxel of the floor
    layer (``cfg.shadow_layer_m``) the background density is the larger of that and the shadow's: the
    background times the alpha in ``[shadow_min_gain, 1]`` that fits best by weighted least squares, with the
    unrelaxed std, where at least ``cfg.shadow_min_share`` of the cameras whose window evidence is positive
    without it have a negative one with it.
    """
    C, _, H, W = images.shape
    pf1, pf0 = detection(cfg)
    uniform = 1.0 / abs(np.linalg.det(RGB2YUV))
    centres = spec.centres(torch.float64).numpy()
    yuv = np.einsum("ij,cjhw->cihw", RGB2YUV, images)
    out = np.empty(len(centres))
    half = cfg.window // 2
    for v, X in enumerate(centres):
        in_layer = shadow_min_gain < 1 and X[2] < spec.lower_m[2] + cfg.shadow_layer_m
        lit_ev, shadow_ev = [], []  # per camera seeing the voxel: the window's log ratio without / with shadows
        for c in range(C):
            rvec, _ = cv2.Rodrigues(rig.R_cam_world[c].numpy())
            uv, _ = cv2.projectPoints(X[None], rvec, rig.t_cam_world[c].numpy(), rig.K[c].numpy(),
                                      rig.dist[c].numpy())
            u, w = uv[0, 0]
            z = (rig.R_cam_world[c].numpy() @ X + rig.t_cam_world[c].numpy())[2]
            pu, pv = int(round(u)), int(round(w))
            if z <= 0 or not (0 <= pu < W and 0 <= pv < H):
                continue
            ev = [0.0, 0.0]
            for dv in range(-half, half + 1):
                for du in range(-half, half + 1):
                    qu, qv = pu + du, pv + dv
                    if not (0 <= qu < W and 0 <= qv < H):
                        continue
                    normal = 1.0
                    y, y_bg = yuv[c, 0, qv, qu], bg_mean[c, 0, qv, qu]
                    in_band = shadow_min_ratio * y_bg <= y <= y_bg / shadow_min_ratio if shadow_min_ratio else True
                    for ch in range(3):
                        m, s = bg_mean[c, ch, qv, qu], bg_std[c, ch, qv, qu]
                        if ch == 0 and not in_band:
                            s = s / luminance_relax
                        normal *= math.exp(-0.5 * ((yuv[c, ch, qv, qu] - m) / s) ** 2) / (s * math.sqrt(2 * math.pi))
                    shadowed = normal
                    if in_layer:
                        m = bg_mean[c, :, qv, qu]
                        s = bg_std[c, :, qv, qu] / np.array([luminance_relax, 1.0, 1.0])
                        alpha = float(np.clip((yuv[c, :, qv, qu] * m / s ** 2).sum() / (m * m / s ** 2).sum(),
                                              shadow_min_gain, 1.0))
                        shadowed = max(normal, float(np.prod(np.exp(-0.5 * ((yuv[c, :, qv, qu] - alpha * m) / s) ** 2)
                                                             / (s * math.sqrt(2 * math.pi)))))
                    for i, n in enumerate((normal, shadowed)):
                        ev[i] += (math.log(pf1 * uniform + (1 - pf1) * n) - math.log(pf0 * uniform + (1 - pf0) * n))
            lit_ev.append(ev[0])
            shadow_ev.append(ev[1])
        foreground = [e > 0 for e in lit_ev]
        votes = sum(f and e < 0 for f, e in zip(foreground, shadow_ev))
        use_shadow = in_layer and votes >= cfg.shadow_min_share * sum(foreground)
        log_odds = math.log(cfg.prior / (1 - cfg.prior)) + sum(shadow_ev if use_shadow else lit_ev)
        log1, log0 = log_odds, 0.0
        out[v] = 1.0 / (1.0 + math.exp(log0 - log1))
    return out


@pytest.fixture(scope="module")
def scene():
    g = torch.Generator().manual_seed(0)
    rig = make_ring_rig(RigConfig(num_cameras=3, width=40, height=30, radius_m=3.0, k1=-0.05))
    empty = 0.2 + 0.6 * torch.rand(1, 3, 3, 30, 40, generator=g, dtype=torch.float64)
    empty = empty + 0.01 * torch.randn(8, 3, 3, 30, 40, generator=g, dtype=torch.float64)
    bg = BackgroundModel.from_frames(empty.clamp(0, 1), BackgroundConfig(compensate_gain=False, shadow_min_gain=0.4,
                                                                          shadow_min_ncc=0.0))  # the colour test
    images = empty[:2].clone()
    images[:, :, :, 10:22, 15:26] = torch.rand(2, 3, 3, 12, 11, generator=g, dtype=torch.float64)  # "body"
    images[:, :, :, 20:30, 5:20] *= 0.6  # a "shadow": the background darkened
    spec = GridSpec((-0.487, -0.493, 0.31), (0.5, 0.5, 1.5), 0.2)  # off-centre: no voxel projects on a half pixel
    return rig, bg, images, spec


@pytest.mark.parametrize("cfg", [BayesConfig(), BayesConfig(pd=0.8, pfa=0.2, window=1, prior=0.3),
                                 BayesConfig(window=5, p_sample=0.7, p_other=0.3, shadow_layer_m=0.5),
                                 BayesConfig(shadow_layer_m=0.5, shadow_min_share=0.0),
                                 BayesConfig(shadow_layer_m=0.5, shadow_min_share=1.0),
                                 BayesConfig(shadow_layer_m=0.0), BayesConfig(pd=None),
                                 BayesConfig(pd=0.95)])
def test_fast_grid_equals_algorithm1(scene, cfg):
    rig, bg, images, spec = scene
    grid = BayesianGrid(rig, spec, bg, cfg)
    fast = grid(images).probability()  # (B, V)
    assert bg.config.shadow_min_ratio > 0 and bg.config.luminance_relax > 1  # the shadow band is exercised
    assert grid.config.pd == (cfg.pd or 0.99)  # not given: a 3-camera rig's
    cfg = grid.config
    for b in range(images.shape[0]):
        ref = algorithm1(rig, bg.mean_yuv.numpy(), bg.std_yuv.numpy(), images[b].numpy(), spec, cfg,
                         bg.config.shadow_min_ratio, bg.config.luminance_relax, bg.config.shadow_min_gain)
        # tolerance: float64 throughout; differences only from summation order
        np.testing.assert_allclose(fast[b].numpy(), ref, atol=1e-9, rtol=0)
    assert 0.0 < float(fast.mean()) < 1.0  # not a degenerate case: some voxels are occupied, some are not
    if cfg.shadow_layer_m > 0 and cfg.shadow_min_share < 1:  # the shadow test changes the floor layer's voxels
        plain = BayesianGrid(rig, spec, bg, dataclasses.replace(cfg, shadow_layer_m=0.0))(images).probability()
        assert float((plain - fast).abs().max()) > 0.01
    if cfg.shadow_layer_m > 0 and cfg.shadow_min_share == 0:  # the cameras' vote is exercised: a half share differs
        half = BayesianGrid(rig, spec, bg, dataclasses.replace(cfg, shadow_min_share=0.5))(images).probability()
        assert float((half - fast).abs().max()) > 0.01


@pytest.mark.parametrize("cameras, misses, occupied", [(8, 0, True), (8, 1, True), (8, 2, False), (12, 1, True),
                                                       (7, 1, True), (6, 1, False), (4, 1, False), (4, 0, True)])
def test_many_cameras_outvote_one_view_that_misses(cameras, misses, occupied):
    """The rig's sensor model (``pd`` None): a voxel that every camera sees, clearly foreground in all but
    ``misses`` of them and clearly background there, is occupied on a rig of seven cameras or more with one view
    missing it, never with two (up to 12 cameras) or on a smaller rig. The grid's fusion against the closed form of
    p(F | G) summed over the cameras."""
    rig = make_ring_rig(RigConfig(num_cameras=cameras, width=16, height=16, radius_m=3.0))
    bg = BackgroundModel.from_frames(torch.rand(5, cameras, 3, 16, 16, generator=torch.Generator().manual_seed(1)))
    spec = GridSpec((-0.1, -0.1, 0.85), (0.1, 0.1, 1.05), 0.2)  # one voxel at the cameras' target
    grid = BayesianGrid(rig, spec, bg, BayesConfig(pd=None))
    assert grid.config.pd == (0.95 if cameras >= 7 else 0.99)
    assert BayesianGrid(rig, spec, bg).config.pd == 0.99  # the plain default: the intersection
    pf1, pf0 = detection(grid.config)
    closed = (cameras - misses) * math.log(pf1 / pf0) + misses * math.log((1 - pf1) / (1 - pf0))  # prior 0.5
    log_bg = torch.full((1, cameras, 16, 16), bg.log_uniform - 60.0)  # N << U: clearly foreground
    log_bg[:, :misses] = bg.log_uniform + 60.0  # N >> U: clearly background
    occ = grid.from_log_likelihood(log_bg)
    assert int(grid.lookup.num_views[0]) == cameras and bool(occ.observed[0])
    np.testing.assert_allclose(float(occ.log_odds[0, 0]), closed, atol=1e-5)
    assert bool(occ.occupied()[0, 0]) == occupied and (closed > 0) == occupied


def test_window_sum_by_hand():
    x = torch.arange(20, dtype=torch.float64).reshape(1, 1, 4, 5)
    s = window_sum(x, 3)
    ref = np.zeros((4, 5))
    for i in range(4):
        for j in range(5):
            ref[i, j] = x[0, 0, max(0, i - 1):i + 2, max(0, j - 1):j + 2].sum()
    np.testing.assert_allclose(s[0, 0].numpy(), ref)


def test_lookup_matches_opencv(scene):
    rig, _, _, spec = scene
    lk = VoxelLookup(rig, spec)
    X = spec.centres(torch.float64).numpy()
    for c in range(rig.num_cameras):
        rvec, _ = cv2.Rodrigues(rig.R_cam_world[c].numpy())
        uv, _ = cv2.projectPoints(X, rvec, rig.t_cam_world[c].numpy(), rig.K[c].numpy(), rig.dist[c].numpy())
        px = np.round(uv[:, 0]).astype(int)
        inside = (px[:, 0] >= 0) & (px[:, 0] < 40) & (px[:, 1] >= 0) & (px[:, 1] < 30)
        expect = np.where(inside, px[:, 1] * 40 + px[:, 0], -1)
        np.testing.assert_array_equal(lk.pixel_index[c].numpy(), expect)


def test_unreadable_camera_gives_no_evidence(scene):
    rig, bg, images, spec = scene
    grid = BayesianGrid(rig, spec, bg, BayesConfig(shadow_layer_m=0.0))  # evidence() has no shadow test
    bad = images.clone()
    bad[:, 1] = float("nan")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # unreadable (NaN) is not warned about here: the reader reports it
        lo_bad = grid(bad).log_odds
    ev = grid.evidence(images)
    manual = grid.lookup.gather(ev)[:, [0, 2]].sum(1)  # cameras 0 and 2 only (prior 0.5: logit 0)
    torch.testing.assert_close(lo_bad, manual)


def test_bad_input(scene):
    rig, bg, images, spec = scene
    grid = BayesianGrid(rig, spec, bg)
    with pytest.raises(ShapeError, match="images"):
        grid(images[:, :2])
    with pytest.raises(InputError, match="window"):
        BayesConfig(window=4)
    with pytest.raises(InputError, match="pd"):
        BayesConfig(pd=1.0)
    with pytest.raises(InputError, match="shadow_min_share"):
        BayesConfig(shadow_min_share=1.5)
    empty = grid(bg_frame(bg)).occupied()
    assert int(empty.sum()) == 0  # nobody there: an empty grid


def bg_frame(bg) -> torch.Tensor:
    """An RGB frame equal to the background mean (inverse of the YUV transform)."""
    yuv = bg.mean_yuv.numpy()
    rgb = np.einsum("ij,cjhw->cihw", np.linalg.inv(RGB2YUV), yuv)
    return torch.from_numpy(rgb)[None]


@pytest.mark.parametrize("cfg, threshold", [(BayesConfig(pd=None), 0.5), (BayesConfig(), 0.5),
                                            (BayesConfig(pd=0.8, pfa=0.2, prior=0.3, window=3), 0.3),
                                            (BayesConfig(pd=0.95, shadow_layer_m=0.0), 0.7)])
def test_occupied_voxels_equal_the_dense_grid(cfg, threshold):
    """The grid's voxels above a threshold, found from the first views' evidence and a bound on the rest
    (``occupied_voxels``), are those of the grid summed over every camera at every voxel (``from_log_likelihood``,
    itself checked against Algorithm 1 above), with the same probabilities: an 8-camera ring with a box of random
    colours in every view (its cones cross where the box's voxels are, and near-misses abound at ``pd`` 0.95,
    where one view's background is outvoted), a floor shadow, and one camera's frame unreadable."""
    g = torch.Generator().manual_seed(3)
    rig = make_ring_rig(RigConfig(num_cameras=8, width=48, height=36, radius_m=3.0, k1=-0.05))
    empty = 0.2 + 0.6 * torch.rand(1, 8, 3, 36, 48, generator=g, dtype=torch.float64)
    empty = empty + 0.01 * torch.randn(6, 8, 3, 36, 48, generator=g, dtype=torch.float64)
    bg = BackgroundModel.from_frames(empty.clamp(0, 1), BackgroundConfig(compensate_gain=False, shadow_min_gain=0.4,
                                                                          shadow_min_ncc=0.0))
    images = empty[:3].clone()
    images[:, :, :, 12:26, 18:30] = torch.rand(3, 8, 3, 14, 12, generator=g, dtype=torch.float64)  # the "body"
    images[:, :, :, 28:36, 10:30] *= 0.6  # a "shadow"
    images[2, 5] = float("nan")  # an unreadable frame: no evidence from that camera
    spec = GridSpec((-1.0, -1.0, 0.0), (1.0, 1.0, 1.8), 0.1)
    grid = BayesianGrid(rig, spec, bg, cfg)
    assert grid.first_flat.shape[0] == 3 and grid.observed_floor < grid.observed_index.numel() <= spec.num_voxels
    assert (grid.observed_floor > 0) == (cfg.shadow_layer_m > 0)  # the floor layer's own bound is exercised
    # each voxel's first views, against a plain loop: the first 3 cameras that see it in farthest-point order
    centres = rig.centers().double()
    order = [0]
    while len(order) < 8:
        order.append(max((c for c in range(8) if c not in order),
                         key=lambda c: min(float((centres[c] - centres[o]).norm()) for o in order)))
    C, V = 8, spec.num_voxels
    for j in range(0, grid.observed_index.numel(), 97):
        v = int(grid.observed_index[j])
        cams = [c for c in order if int(grid.lookup.pixel_index[c, v]) >= 0][:3]
        want = [int(grid.lookup.flat_index.view(C, V)[c, v]) for c in cams] + [C * 48 * 36] * (3 - len(cams))
        assert grid.first_flat[:, j].tolist() == want
        assert int(grid.other_views[j]) == int(grid.lookup.num_views[v]) - len(cams)
    lit, shadowed, _ = bg.log_likelihood_and_yuv(images, shadows=cfg.shadow_layer_m > 0)
    dense = grid.from_log_likelihood(lit, shadowed).probability()  # (B, V)
    sparse = grid.occupied_voxels(lit, shadowed, threshold)
    for b, (idx, p) in enumerate(sparse):
        ref = (dense[b] > threshold).nonzero()[:, 0]
        assert 0 < ref.numel() < spec.num_voxels // 4  # some voxels kept, most not
        assert torch.equal(idx, ref)
        np.testing.assert_allclose(p.numpy(), dense[b, ref].numpy(), rtol=0, atol=1e-12)
    with pytest.raises(InputError, match="threshold"):
        grid.occupied_voxels(lit, shadowed, 1.0)
