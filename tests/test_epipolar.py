"""The epipolar cost of model markers against 2D detections (torchtrack.tracking.epipolar) against independent
references: a plain loop of the closed-form point-to-epiline distances, kornia's symmetric epipolar distance, the
rig's own projection for the undistorted pixels; subjects padded into one batch against each alone. The reprojection
cost against a plain loop, and the filter's polish on it against scipy's least_squares."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest import demo_rig
from torchtrack.checks import InputError
from torchtrack.tracking.epipolar import (EpipolarCost, epipolar_cost, fundamental_matrices, pinhole_pixels,
                                          projection_matrices)


def _points_in_view(rig, M: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """M random points in the demo rig's volume ``(M, 3)``, its pinhole projections ``(C, 3, 4)`` and the points'
    pinhole pixels ``(C, M, 2)``."""
    truth = torch.rand(M, 3, generator=gen, dtype=torch.float64) * torch.tensor([1.5, 1.0, 1.6]) + torch.tensor(
        [-1.6, -0.5, 0.2])
    P = projection_matrices(rig)
    uv = torch.einsum("cij,mj->cmi", P, torch.cat([truth, torch.ones(M, 1, dtype=torch.float64)], -1))
    return truth, P, uv[..., :2] / uv[..., 2:]


@pytest.mark.parametrize("tau", [20.0, 1e8])  # a cap beyond the far line of a missing candidate too
def test_epipolar_cost_matches_a_plain_loop(tau):
    rig = demo_rig()
    gen = torch.Generator().manual_seed(0)
    C, M, K, B = rig.num_cameras, 6, 3, 4
    truth, P, uv = _points_in_view(rig, M, gen)
    det = uv[:, :, None].repeat(1, 1, K, 1) + 3 * torch.randn(C, M, K, 2, generator=gen, dtype=torch.float64)
    det[:, :, 1:] += 200 * torch.randn(C, M, K - 1, 2, generator=gen, dtype=torch.float64)  # false candidates
    det[0, 0] = math.nan  # marker 0 unseen in view 0
    det[1, 2, 0] = math.nan  # one candidate missing
    det[2, 3, 0], det[2, 3, 1:] = math.nan, uv[2, 3] + 1e7  # one missing, the others wild: only a huge cap counts them
    points = truth[None] + 0.01 * torch.randn(B, M, 3, generator=gen, dtype=torch.float64)
    F = fundamental_matrices(rig)
    got = epipolar_cost(points, det, P, F, tau)
    grad_path = epipolar_cost(points.clone().requires_grad_(True), det, P, F, tau).detach()
    single = epipolar_cost(points.float(), det, P, F, tau)
    Pn, Fn, zn = P.numpy(), F.numpy(), det.numpy()
    for b in range(B):
        total = 0.0
        for m in range(M):
            X = np.append(points[b, m].numpy(), 1.0)
            for i in range(C):
                cands = [z for z in zn[i, m] if np.isfinite(z).all()]
                if not cands:
                    continue
                for j in range(C):
                    if i == j:
                        continue
                    y = Pn[j] @ X
                    y = np.append(y[:2] / y[2], 1.0)
                    best = math.inf
                    for z in cands:
                        z = np.append(z, 1.0)
                        line_j = Fn[i, j] @ z  # z's epiline in view j
                        line_i = Fn[i, j].T @ y  # the epiline of y in view i
                        d = (y @ line_j) ** 2 / (line_j[0] ** 2 + line_j[1] ** 2) + (z @ line_i) ** 2 / (
                            line_i[0] ** 2 + line_i[1] ** 2)
                        best = min(best, d)
                    total += min(best, tau ** 2)
        assert float(got[b]) == pytest.approx(total, rel=1e-6)
        # the differentiable path (points that need a gradient) and the particle layers' float32 give the same sums
        assert float(grad_path[b]) == pytest.approx(total, rel=1e-6)
        assert float(single[b]) == pytest.approx(total, rel=1e-3, abs=1e-2)
    # padded with empty candidate slots (before and between the real ones), as a sequence's detections are: the same
    padded = torch.full((C, M, K + 2, 2), math.nan, dtype=torch.float64)
    padded[:, :, 1], padded[:, :, 3:] = det[:, :, 0], det[:, :, 1:]
    torch.testing.assert_close(epipolar_cost(points, padded, P, F, tau), got, rtol=1e-9, atol=0.0)
    # a point on the markers' rays costs nothing: the true points against exact detections
    exact = epipolar_cost(truth[None], uv[:, :, None], P, F, tau)
    assert float(exact[0]) < 1e-12


def test_each_subjects_own_outlier_cap_is_its_cost_alone():
    """Three subjects in one cost, each with its own cap (1, 5 and 40 px), against each one's cost alone: the same
    costs and residuals."""
    rig = demo_rig()
    gen = torch.Generator().manual_seed(4)
    C, M, K, N = rig.num_cameras, 6, 2, 5
    P, F = projection_matrices(rig), fundamental_matrices(rig)
    det = torch.rand(3, C, M, K, 2, generator=gen, dtype=torch.float64) * torch.tensor([1000.0, 800.0]) + 300.0
    pts = torch.rand(3, M, 3, N, generator=gen, dtype=torch.float64) + torch.tensor([-1.0, -0.5, 0.5])[:, None]
    caps = torch.tensor([1.0, 5.0, 40.0], dtype=torch.float64)
    both = EpipolarCost(det, P.expand(3, -1, -1, -1), F.expand(3, -1, -1, -1, -1), caps)
    cost, (res, _) = both.cost(pts), both.residuals(pts)
    for q in range(3):
        alone = EpipolarCost(det[q], P, F, float(caps[q]))
        torch.testing.assert_close(cost[q], alone.cost(pts[q:q + 1])[0], rtol=1e-12, atol=0.0)
        torch.testing.assert_close(res[q], alone.residuals(pts[q:q + 1])[0][0], rtol=1e-12, atol=0.0)
    # the first subject's own 1 px cap, not the largest
    assert not torch.allclose(cost[0], EpipolarCost(det[0], P, F, 40.0).cost(pts[:1])[0])
    with pytest.raises(InputError):
        EpipolarCost(det, P.expand(3, -1, -1, -1), F.expand(3, -1, -1, -1, -1), torch.tensor([1.0, 0.0, 2.0]))


def test_epipolar_cost_is_kornias_symmetric_distance():
    from kornia.geometry.epipolar import symmetrical_epipolar_distance

    rig = demo_rig()
    gen = torch.Generator().manual_seed(8)
    C = rig.num_cameras
    z = torch.tensor([[[[812.0, 640.0]]]], dtype=torch.float64).expand(C, 1, 1, 2).clone()
    z[1:] = math.nan  # one detection, in view 0
    points = torch.rand(6, 1, 3, generator=gen, dtype=torch.float64) + torch.tensor([-1.5, -0.5, 0.5])
    P, F = projection_matrices(rig), fundamental_matrices(rig)
    got = epipolar_cost(points, z, P, F, outlier_px=1e6)
    h = torch.cat([points[:, 0], torch.ones(6, 1, dtype=torch.float64)], -1)
    want = torch.zeros(6, dtype=torch.float64)
    for j in range(1, C):
        y = h @ P[j].T
        y = y[:, :2] / y[:, 2:]
        want += symmetrical_epipolar_distance(z[0, 0].expand(6, 2)[:, None], y[:, None], F[0, j])[:, 0]
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9)


def test_pinhole_pixels_undo_the_lens():
    rig = demo_rig()
    pts = torch.tensor([[-1.0, 0.0, 1.0], [-0.5, 0.3, 0.2]], dtype=torch.float64)
    distorted, _ = rig.project(pts)  # (C, 2, 2)
    h = torch.cat([pts, torch.ones(2, 1, dtype=torch.float64)], -1)
    pin = torch.einsum("cij,mj->cmi", projection_matrices(rig), h)
    # the undistortion is iterative: within a thousandth of a pixel
    torch.testing.assert_close(pinhole_pixels(rig, distorted), pin[..., :2] / pin[..., 2:], atol=1e-3, rtol=0)
    assert torch.isnan(pinhole_pixels(rig, torch.full((rig.num_cameras, 1, 2), math.nan))).all()


def test_epipolar_cost_of_padded_subjects_is_each_ones_own():
    """Two subjects in one cost, of 4 and 3 views and 6 and 4 markers (the second padded with NaN detections and a
    view without epipolar geometry): each subject's costs and residuals are those of its own cost alone."""
    rig = demo_rig()
    gen = torch.Generator().manual_seed(1)
    P4, F4 = projection_matrices(rig), fundamental_matrices(rig)
    sub = rig.subset([0, 2, 3])
    P3, F3 = projection_matrices(sub), fundamental_matrices(sub)
    N = 5
    own, points = [], []
    for P, F, C, M in ((P4, F4, 4, 6), (P3, F3, 3, 4)):
        X = torch.rand(M, 3, generator=gen, dtype=torch.float64) + torch.tensor([-1.2, -0.4, 0.4])
        h = torch.cat([X, torch.ones(M, 1, dtype=torch.float64)], -1)
        uv = torch.einsum("cij,mj->cmi", P, h)
        det = (uv[..., :2] / uv[..., 2:])[:, :, None] + 2 * torch.randn(C, M, 2, 2, generator=gen,
                                                                         dtype=torch.float64)
        det[0, 1] = math.nan
        pts = X[None] + 0.02 * torch.randn(N, M, 3, generator=gen, dtype=torch.float64)
        own.append((EpipolarCost(det, P, F, 20.0), det, pts))
        points.append(pts)
    det = torch.full((2, 4, 6, 2, 2), math.nan, dtype=torch.float64)
    det[0], det[1, :3, :4] = own[0][1], own[1][1]
    P = torch.stack([P4, torch.cat([P3, P3[:1]])])
    F = torch.zeros(2, 4, 4, 3, 3, dtype=torch.float64)
    F[0], F[1, :3, :3] = F4, F3
    pts = torch.zeros(2, 6, 3, N, dtype=torch.float64)
    pts[0], pts[1, :4] = points[0].permute(1, 2, 0), points[1].permute(1, 2, 0)
    both = EpipolarCost(det, P, F, 20.0)
    cost, per = both.cost(pts), both.cost(pts, per_marker=True)
    r, _ = both.residuals(pts)
    for q, (alone, _, x) in enumerate(own):
        M = x.shape[1]
        torch.testing.assert_close(cost[q], alone(x), rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(per[q, :M], alone(x, per_marker=True).T, rtol=1e-12, atol=1e-12)
        assert float(per[q, M:].abs().sum()) == 0.0
        r_alone, _ = alone.residuals(x.permute(1, 2, 0)[None])
        torch.testing.assert_close(r[q].square().sum(-1), r_alone[0].square().sum(-1), rtol=1e-12, atol=1e-12)


def test_reprojection_cost_matches_a_plain_loop():
    """The polish's reprojection cost against a plain loop: each marker projected by P into each view, its nearest
    candidate's squared pixel distance capped at the cap, views without a candidate adding nothing; its residuals (at
    the state's own nearest candidates): each view's and marker's projection minus that candidate, 0 beyond the cap;
    and a second subject with a cap of its own in the same cost, each the same as alone."""
    from torchtrack.tracking.epipolar import ReprojectionCost

    rig = demo_rig()
    gen = torch.Generator().manual_seed(2)
    C, M, K, N = rig.num_cameras, 5, 3, 3
    truth, P, uv = _points_in_view(rig, M, gen)
    det = uv[:, :, None].repeat(1, 1, K, 1) + 4 * torch.randn(C, M, K, 2, generator=gen, dtype=torch.float64)
    det[:, :, 2] += 60.0  # a candidate beyond the cap
    det[0, 0] = math.nan  # marker 0 unseen in view 0
    det[1, 2, 0] = math.nan
    det[2, 4, :2] = math.nan  # marker 4's only candidate in view 2 beyond the cap
    pts = (truth[None] + 0.005 * torch.randn(N, M, 3, generator=gen, dtype=torch.float64)).permute(1, 2, 0)
    caps = (15.0, 6.0)
    both = ReprojectionCost(torch.stack([det, det.flip(2)]), P[None].expand(2, -1, -1, -1),
                            torch.tensor(caps, dtype=torch.float64))
    got = both.cost(pts[None].expand(2, -1, -1, -1))
    Pn, zn = P.numpy(), det.numpy()
    for q, tau in enumerate(caps):
        alone = ReprojectionCost(det[None], P[None], tau)
        torch.testing.assert_close(got[q], alone.cost(pts[None])[0], rtol=1e-12, atol=0.0)
        for n in range(N):
            total, signed = 0.0, np.zeros((C, M, 2))
            for m in range(M):
                X = np.append(pts[m, :, n].numpy(), 1.0)
                for c in range(C):
                    y = Pn[c] @ X
                    y = y[:2] / y[2]
                    cands = [z for z in zn[c, m] if np.isfinite(z).all()]
                    if cands:
                        near = min(cands, key=lambda z: float(np.sum((y - z) ** 2)))
                        d = float(np.sum((y - near) ** 2))
                        total += min(d, tau ** 2)
                        signed[c, m] = y - near if d < tau ** 2 else 0.0
            assert float(got[q, n]) == pytest.approx(total, rel=1e-9)
            res, _ = alone.residuals(pts[None, ..., n:n + 1])  # each state's own nearest candidates
            np.testing.assert_allclose(res[0, 0].view(C, M, 2).numpy(), signed, rtol=0, atol=1e-9)


def test_the_reprojection_polish_reaches_scipys_least_squares():
    """The filter's polish on the reprojection cost, from a pose a few degrees off, against scipy's least_squares
    on the same residuals written out as a plain projection of the markers (the state within the joint limits):
    the same least, on a body whose markers partly lie off it (three moved 3 cm, so no pose meets every ray) and
    with markers seen in one view only. The epipolar cost's own least is another pose."""
    from scipy.optimize import least_squares

    from torchtrack.markers.model import MarkerSet
    from torchtrack.skeleton import Skeleton
    from torchtrack.tracking.epipolar import ReprojectionCost
    from torchtrack.tracking.particles import APFConfig, MarkerAPF

    rig = demo_rig()
    skel = Skeleton.from_urdf().double()
    gen = torch.Generator().manual_seed(3)
    M = 2 * len(skel.bone_names)
    bones = torch.arange(M) % len(skel.bone_names)
    mset = MarkerSet(tuple(f"m{i}" for i in range(M)), bones,
                     0.06 * torch.randn(M, 3, generator=gen, dtype=torch.float64))
    apf = MarkerAPF(skel, mset, rig, APFConfig(polish_steps=60))
    truth = skel.rest_angles().double()
    truth[:3] = torch.tensor([-0.6, 0.2, 0.95])
    X = apf.markers(truth[None])[0]
    X[:3] += 0.03 * torch.nn.functional.normalize(torch.randn(3, 3, generator=gen, dtype=torch.float64), dim=-1)
    P = projection_matrices(rig)
    uv = torch.einsum("cij,mj->cmi", P, torch.cat([X, torch.ones(M, 1, dtype=torch.float64)], -1))
    det = (uv[..., :2] / uv[..., 2:])[:, :, None].clone()
    det[1:, 5:8] = math.nan  # three markers in view 0 alone
    cap = 1e4
    cost = ReprojectionCost(det[None], apf.P, cap)
    start = apf.clamp(truth[None] + 0.05 * torch.randn(1, skel.num_dofs, generator=gen, dtype=torch.float64))
    got = apf._polish(start, cost, torch.ones(1, dtype=torch.bool))[0][0]

    Pn, zn = P.numpy(), det[:, :, 0].numpy()
    seen = np.isfinite(zn).all(-1)

    def residuals(theta):
        Y = apf.markers(torch.from_numpy(theta)[None])[0].numpy()
        out = []
        for c in range(rig.num_cameras):
            for m in range(M):
                if seen[c, m]:
                    y = Pn[c] @ np.append(Y[m], 1.0)
                    out.extend(y[:2] / y[2] - zn[c, m])
        return np.asarray(out)

    lo, hi = apf.lower[0].numpy(), apf.upper[0].numpy()
    ref = least_squares(residuals, start[0].numpy(), bounds=(lo, hi), xtol=1e-12, ftol=1e-12, gtol=1e-12)
    best = float(np.sum(ref.fun ** 2))
    mine = float(np.sum(residuals(got.numpy()) ** 2))
    assert best > 1.0  # the moved markers leave a residual: no pose meets every ray
    assert mine == pytest.approx(best, rel=5e-3)  # the polish stops where a step gains under 1e-4 of the cost
    ideal = apf.markers(torch.from_numpy(ref.x)[None])[0]
    assert float((apf.markers(got[None])[0] - ideal).norm(dim=-1).max()) < 3e-3
    # the epipolar cost's least is another pose (docs/results.md, "Marker-based capture")
    epi = apf._polish(start, EpipolarCost(det[None], apf.P, apf.F, cap), torch.ones(1, dtype=torch.bool))[0][0]
    assert float(np.sum(residuals(epi.numpy()) ** 2)) > 1.03 * best
