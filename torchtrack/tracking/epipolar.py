"""The symmetric epipolar distance of model markers to 2D marker detections, the marker filter's likelihood
(:mod:`torchtrack.tracking.particles`; Canton-Ferrer et al. 2010): each model marker projected into one view against
its candidate detections in another, summed over markers and ordered pairs of views, in each camera's undistorted
(pinhole) pixels, where the epipolar geometry holds. And the reprojection error of the same markers
(:class:`ReprojectionCost`), which the filter's final polish minimises.
"""

from __future__ import annotations

import math

import torch
from kornia.geometry.epipolar import fundamental_from_projections
from torch import nn

from torchtrack.checks import InputError

__all__ = ["EpipolarCost", "ReprojectionCost", "epipolar_cost", "fundamental_matrices", "pinhole_pixels",
           "projection_matrices"]

#: The distance (px) of every point from the line of a candidate that has none (:class:`EpipolarCost`; ten times
#: the outlier cap where that is more): beyond the cap, and its square within float32's range.
FAR_PX = 1e6


def pinhole_pixels(rig: nn.Module, uv: torch.Tensor) -> torch.Tensor:
    """Distorted pixels ``(C, ..., N, 2)`` of each camera -> the same points in its undistorted pinhole image (the
    camera's K on the undistorted normalized coordinates); NaN stays NaN."""
    finite = torch.isfinite(uv).all(-1, keepdim=True)
    _, d = rig.pixel_rays(torch.where(finite, uv, torch.zeros_like(uv)))  # (C, ..., N, 3) world directions
    K, R = rig.K.to(d), rig.R_cam_world.to(d)
    shape = d.shape
    d_cam = torch.einsum("cij,cmj->cmi", R, d.reshape(shape[0], -1, 3))  # (C, *, 3)
    pix = torch.einsum("cij,cmj->cmi", K, d_cam / d_cam[..., 2:3])[..., :2]
    return torch.where(finite, pix.reshape(*shape[:-1], 2), torch.nan)


def fundamental_matrices(rig: nn.Module) -> torch.Tensor:
    """(C, C, 3, 3) ``F[i, j]`` with ``x_j^T F[i, j] x_i = 0`` for pinhole pixels ``x_i``, ``x_j`` of one point in
    views i and j (kornia's convention; the diagonal is zero), in float64."""
    P = projection_matrices(rig).double()  # (C, 3, 4)
    C = P.shape[0]
    F = fundamental_from_projections(P[:, None].expand(C, C, 3, 4), P[None].expand(C, C, 3, 4))
    return F * (1 - torch.eye(C, dtype=F.dtype, device=F.device))[..., None, None]


def projection_matrices(rig: nn.Module) -> torch.Tensor:
    """(C, 3, 4) each camera's pinhole projection ``K [R | t]`` (world points to undistorted pixels)."""
    K, R, t = rig.K, rig.R_cam_world, rig.t_cam_world
    return K @ torch.cat([R, t[..., None]], -1)


class EpipolarCost:
    """The cost of states' markers against one frame's detections (:func:`epipolar_cost`), of Q subjects at once,
    with the detections' epipolar lines computed once for the frame: each layer of each frame then costs two
    products (the projections and their lines in the other views) and a few elementwise passes. Hand-written over
    kornia's :func:`~kornia.geometry.epipolar.symmetrical_epipolar_distance` (the same distance, tested against it)
    because that one recomputes every candidate's line for every state.

    The distance is invariant to each fundamental matrix's scale and to the lines' scale, so both are normalised
    here (in float64): the lines then give pixel distances directly, and the states' side runs in their own dtype
    (float32 for the particle filter's layers) without the ill-scaled products of a raw F.

    Args:
        detections: (Q, C, M, K, 2) each subject's markers' candidate detections per view in pinhole pixels, NaN
            where none (subjects of fewer views or markers padded with NaN); (C, M, K, 2): one subject.
        P: (Q, C, 3, 4) pinhole projections (padded views: any finite camera). F: (Q, C, C, 3, 3) fundamental
            matrices (:func:`fundamental_matrices`; zero for a padded view's pairs). Without Q for one subject.
        outlier_px: the cap on each marker's and view pair's distance (pixels; :class:`~torchtrack.tracking.
            particles.APFConfig`'s ``outlier_rad`` in the rig's pixels): one for all subjects, or each one's ``(Q,)``.
        far_px: the distance of a missing candidate's line from every point (default: ``FAR_PX``, or ten times the
            largest cap where that is more), given by a caller that checked its caps (no device sync here).
    """

    def __init__(self, detections: torch.Tensor, P: torch.Tensor, F: torch.Tensor,
                 outlier_px: float | torch.Tensor, far_px: float | None = None) -> None:
        if detections.dim() == 4:  # one subject
            detections, P, F = detections[None], P[None], F[None]
        Q, C, M, K, _ = detections.shape
        # on a CPU, each marker's candidates first in each view, and as many kept as the most any marker has here:
        # a frame's cost then runs over the candidates it has, not the sequence's padding (a GPU keeps the padding
        # rather than wait for the count)
        has = torch.isfinite(detections).all(-1)  # (Q, C, M, K)
        used = max(1, int(has.sum(-1).amax())) if has.numel() and detections.device.type == "cpu" else K
        if used < K:
            order = torch.sort((~has).to(torch.uint8), dim=-1, stable=True).indices[..., :used]
            detections = detections.gather(3, order[..., None].expand(*order.shape, 2))
            K = used
        dtype, dev = detections.dtype, detections.device
        if far_px is None:  # checked here (a caller that gives far_px checked its caps once, without a device sync)
            caps = torch.as_tensor(outlier_px, dtype=torch.float64).cpu()
            if not bool(((caps > 0) & torch.isfinite(caps)).all()):
                raise InputError(f"EpipolarCost: outlier_px must be finite and > 0; got {outlier_px}")
            far_px = max(FAR_PX, 10.0 * float(caps.max()))  # beyond the cap, whatever it is
        cap = torch.as_tensor(outlier_px, dtype=torch.float64).to(dev).expand(Q)
        self.cap = cap.square().to(dtype).view(Q, 1, 1, 1, 1)  # (Q, 1, 1, 1, 1): against the (Q, C, ., ., N) minima
        # the ordered view pairs grouped by their second view j (the one a state's marker is projected into): its
        # A = C - 1 first views i, so that each view j's and marker's terms take all its pairs' lines at once
        src = torch.tensor([[i for i in range(C) if i != j] for j in range(C)], dtype=torch.long, device=dev)  # (C, A)
        Fji = F.to(dev, torch.float64)[:, src, torch.arange(C, device=dev)[:, None]]  # (Q, C, A, 3, 3): x_j^T F x_i
        Fji = Fji / Fji.flatten(3).norm(dim=3).clamp(min=1e-300)[..., None, None]
        z = detections.double()
        seen = torch.isfinite(z).all(-1)  # (Q, C, M, K)
        z = torch.cat([torch.nan_to_num(z), torch.ones_like(z[..., :1])], -1)  # (Q, C, M, K, 3)
        lines = torch.einsum("qjacd,qjamkd->qjmakc", Fji, z[:, src])  # (Q, C, M, A, K, 3): z_ik's epiline in view j
        norm2 = lines[..., :2].square().sum(-1)  # (Q, C, M, A, K)
        # a candidate at the epipole (or of a padded view) has no line
        self.ok = seen[:, src].permute(0, 1, 3, 2, 4) & (norm2 > 1e-300)
        unit = lines / norm2.clamp(min=1e-300).sqrt()[..., None]  # y . unit: y's distance from the line, px
        self.pair = self.ok.any(-1)  # (Q, C, M, A): view i has a candidate of marker m
        # the masks folded into the lines, so that a layer's cost needs no pass of its own over them: a candidate
        # without a line is FAR from every point (beyond the cap, never the nearest of one that has), and a marker
        # without a candidate in view i is at distance 0 from every line of its pair (it adds nothing)
        far = torch.zeros_like(unit)
        far[..., 2] = torch.where(self.pair[..., None], far_px, 0.0)
        unit = torch.where(self.ok[..., None], unit, far)
        # laid out for states last (N contiguous), with view i before the marker: the layers' cost is then a few
        # elementwise passes over (Q, C, A, M, K, N) and one product per view (below), where batched products of
        # C x M small matrices and their temporaries took twice as long. Each line's three coefficients
        # (3, Q, C, A, M, K, 1); the pairs' F^T as (Q, C, 2A, 3), its row r = 0 for every view i in turn, then row
        # r = 1: F^T y's first two coefficients, whose squared norm scales the distance in view i
        self.lines = unit.permute(5, 0, 1, 3, 2, 4)[..., None].contiguous().to(dtype)
        self.norm2 = torch.where(self.ok, norm2, 0.0).transpose(2, 3)[..., None].contiguous().to(dtype)
        self.back = Fji[..., :2].permute(0, 1, 4, 2, 3).reshape(Q, C, 2 * (C - 1), 3).to(dtype)
        self.P = P.to(dtype)  # (Q, C, 3, 4)
        self.not_ok = ~self.ok[..., None]  # (Q, C, M, A, K, 1)

    def _project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points ``(Q, M, 3, N)`` -> their homogeneous pinhole pixels ``y (Q, C, 3, M, N)`` in each view (all
        views' rows of P in one (3C x 3) product with all the points) and the first two coefficients of their
        epilines ``F^T y`` in each other view, ``(Q, C, 2, A, M, N)`` (one (2A x 3) product per view)."""
        Q, M, _, N = points.shape
        C = self.P.shape[1]
        P = self.P.to(points)
        y = torch.baddbmm(P[..., 3].reshape(Q, 3 * C, 1), P[..., :3].reshape(Q, 3 * C, 3),
                          points.transpose(1, 2).reshape(Q, 3, M * N))  # (Q, 3C, M N)
        back = torch.bmm(self.back.to(y).view(Q * C, -1, 3), y.view(Q * C, 3, M * N))
        return y.view(Q, C, 3, M, N), back.view(Q, C, 2, C - 1, M, N)

    @staticmethod
    def _pixels(y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Homogeneous pixels ``y (Q, C, 3, M, N)`` -> ``u, v (Q, C, 1, M, 1, N)``, laid out against the lines."""
        w = y[:, :, 2]
        return (y[:, :, 0] / w)[:, :, None, :, None], (y[:, :, 1] / w)[:, :, None, :, None]

    def _terms(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points ``(Q, M, 3, N)``, states last -> each candidate's signed distance from the projection's epiline
        ``(Q, C, M, A, K, N)`` (px; view j, marker, view i, candidate) and ``1 + |(F z)_12|^2 / |(F^T y)_12|^2``
        (the same shape): the symmetric distance is their product with the first squared. Differentiable."""
        y, b = self._project(points)
        w, (u, v) = y[:, :, 2], self._pixels(y)
        back = (b[:, :, 0].square() + b[:, :, 1].square()).clamp(min=1e-30) / w.square()[:, :, None]  # (Q, C, A, M, N)
        L = self.lines.to(u)
        dist = L[2] + L[0] * u + L[1] * v  # y_j from z_ik's epiline, px
        factor = self.norm2.to(u) / back[:, :, :, :, None] + 1
        return dist.transpose(2, 3), factor.transpose(2, 3)

    def cost(self, points: torch.Tensor, per_marker: bool = False) -> torch.Tensor:
        """``points (Q, M, 3, N)``, N finite states of each subject (padded markers too: a marker without
        candidates adds its zero lines times its projection) -> (Q, N) costs, or (Q, M, N) with ``per_marker``. In
        place where no gradient is asked for (the particle filter's layers)."""
        if torch.is_grad_enabled() and any(t.requires_grad for t in (points, self.P, self.lines, self.back)):
            dist, factor = self._terms(points)
            cost = (dist.square() * factor).amin(4).clamp(max=self.cap).sum(3).sum(1)  # (Q, M, N)
            return cost if per_marker else cost.sum(1)
        # _terms' distance, each full-size tensor made once and the rest in place
        y, b = self._project(points)
        w, (u, v) = y[:, :, 2], self._pixels(y)
        # 1 / |(F^T y)_12|^2 of the projection y = (u, v, 1): of the homogeneous one's, times w^2
        inv = b[:, :, 0].square_().addcmul_(b[:, :, 1], b[:, :, 1]).clamp_(min=1e-30).reciprocal_().mul_(
            w.square()[:, :, None])  # (Q, C, A, M, N)
        L = self.lines.to(u)
        dist2 = torch.mul(u, L[0]).addcmul_(v, L[1]).add_(L[2]).square_()  # (Q, C, A, M, K, N)
        dist2.mul_(torch.mul(inv[:, :, :, :, None], self.norm2.to(u)).add_(1.0))
        d = dist2[:, :, :, :, 0]  # the nearest candidate, by a minimum per candidate (K is a few; a reduction over
        for k in range(1, dist2.shape[4]):  # so short an axis is several times slower)
            d = torch.minimum(d, dist2[:, :, :, :, k], out=d if k > 1 else None)
        cost = d.clamp_(max=self.cap).sum(2).sum(1)  # (Q, M, N)
        return cost if per_marker else cost.sum(1)

    def __call__(self, points: torch.Tensor, per_marker: bool = False) -> torch.Tensor:
        """One subject's ``points (B, M, 3)`` -> (B,) costs, or (B, M) with ``per_marker``."""
        cost = self.cost(points.permute(1, 2, 0)[None], per_marker)[0]
        return cost.T if per_marker else cost

    def residuals(self, points: torch.Tensor, pick: torch.Tensor | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
        """``points (Q, M, 3, N)`` -> (Q, N, R) signed residuals (R = views x markers x other views) whose squares
        sum to the cost's terms below the outlier cap (0 for the others), each pair's and marker's nearest
        candidate to the first state, or the candidates ``pick (Q, C, M, A)`` (the nearest are returned with the
        residuals, to keep them while a Jacobian is taken; indices into this cost's candidates, which on a CPU are
        sorted and trimmed as the constructor says)."""
        Q, N = points.shape[0], points.shape[-1]
        dist, factor = self._terms(points)
        r = dist * factor.sqrt()  # (Q, C, M, A, K, N)
        r2 = r.square().masked_fill(self.not_ok, math.inf)
        if pick is None:
            pick = r2[..., 0].argmin(-1)  # (Q, C, M, A)
        idx = pick[..., None, None].expand(*r.shape[:4], 1, N)
        use = self.pair[..., None] & (r2.gather(4, idx)[..., 0, :] < self.cap)  # (Q, C, M, A, N)
        out = torch.where(use, r.gather(4, idx)[..., 0, :], 0.0)
        return out.reshape(Q, -1, N).mT, pick


class ReprojectionCost:
    """The reprojection error of states' markers against one frame's detections, with :class:`EpipolarCost`'s
    interface (``cost``, ``residuals``): each model marker projected into each view against its nearest candidate
    there, squared pixel distance capped at the outlier cap; a view without a candidate of the marker adds nothing.
    Under the detector's Gaussian pixel noise its least is the maximum-likelihood pose given the detections the
    filter linked to each marker: the epipolar distance, a pair of views' agreement, weighs an error along an
    epipolar line not at all in that pair, so its least lies off the markers' rays where the rigid body cannot meet
    them all.

    Args:
        detections: (Q, C, M, K, 2) candidates in pinhole pixels, NaN where none. P: (Q, C, 3, 4) pinhole
        projections. outlier_px: the cap (pixels), one for all subjects or each one's ``(Q,)``.
    """

    def __init__(self, detections: torch.Tensor, P: torch.Tensor, outlier_px: float | torch.Tensor) -> None:
        Q, C, M, K, _ = detections.shape
        # a number checked here; a tensor is the filter's caps, checked once when it was built (no device sync)
        if not isinstance(outlier_px, torch.Tensor) and not 0 < outlier_px < math.inf:
            raise InputError(f"ReprojectionCost: outlier_px must be finite and > 0; got {outlier_px}")
        self.seen = torch.isfinite(detections).all(-1)  # (Q, C, M, K)
        self.z = torch.nan_to_num(detections)[..., None]  # (Q, C, M, K, 2, 1): states last
        self.P = P.to(detections)[:, :, None]  # (Q, C, 1, 3, 4)
        cap = torch.as_tensor(outlier_px, dtype=detections.dtype).to(detections.device).expand(Q)
        self.cap = cap.square().view(Q, 1, 1, 1)  # against (Q, C, M, N)

    def _offsets(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points ``(Q, M, 3, N)`` -> each candidate's offset from the projection ``(Q, C, M, K, 2, N)`` (px) and
        its squared length ``(Q, C, M, K, N)``, inf for a missing candidate; a point behind a camera (or on its
        plane) is infinitely far from every candidate there."""
        h = torch.cat([points, torch.ones_like(points[:, :, :1])], 2)  # (Q, M, 4, N)
        y = self.P.to(h) @ h[:, None]  # (Q, C, M, 3, N)
        ahead = y[:, :, :, 2:3] > 0
        y = torch.where(ahead, y[:, :, :, :2] / torch.where(ahead, y[:, :, :, 2:3], 1.0), math.inf)
        off = y[:, :, :, None] - self.z.to(y)
        return off, off.square().sum(4).masked_fill(~self.seen[..., None], math.inf)

    def cost(self, points: torch.Tensor, per_marker: bool = False) -> torch.Tensor:
        """``points (Q, M, 3, N)`` -> (Q, N) costs, or (Q, M, N) with ``per_marker``."""
        _, d2 = self._offsets(points)
        d = d2.amin(3).clamp(max=self.cap)  # (Q, C, M, N)
        d = torch.where(self.seen.any(3)[..., None], d, 0.0)
        cost = d.sum(1)  # (Q, M, N)
        return cost if per_marker else cost.sum(1)

    def residuals(self, points: torch.Tensor, pick: torch.Tensor | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
        """``points (Q, M, 3, N)`` -> (Q, N, R) signed residuals (R = views x markers x 2) whose squares sum to the
        cost's terms below the cap (0 for the others), each view's and marker's nearest candidate to the first
        state, or the candidates ``pick (Q, C, M)``; and the candidates used."""
        Q, N = points.shape[0], points.shape[-1]
        off, d2 = self._offsets(points)  # (Q, C, M, K, 2, N), (Q, C, M, K, N)
        if pick is None:
            pick = d2[..., 0].argmin(-1)  # (Q, C, M)
        idx = pick[..., None, None]
        near = d2.gather(3, idx.expand(*pick.shape, 1, N))[:, :, :, 0]  # (Q, C, M, N)
        r = off.gather(3, idx[..., None].expand(*pick.shape, 1, 2, N))[:, :, :, 0]  # (Q, C, M, 2, N)
        use = near[..., :1] < self.cap  # at the first state, as the picks (a missing candidate is inf: never used)
        out = torch.where(use[:, :, :, None], r, 0.0)
        return out.reshape(Q, -1, N).mT, pick


def epipolar_cost(points: torch.Tensor, detections: torch.Tensor, P: torch.Tensor, F: torch.Tensor,
                  outlier_px: float, per_marker: bool = False) -> torch.Tensor:
    """The cost of each state's markers against one frame's detections.

    Args:
        points: (B, M, 3) the model markers of B states (world, m).
        detections: (C, M, K, 2) each marker's candidate detections per view in pinhole pixels, NaN where none.
        P: (C, 3, 4) pinhole projections. F: (C, C, 3, 3) fundamental matrices (:func:`fundamental_matrices`).
        outlier_px: the cap in pixels (:class:`~torchtrack.tracking.particles.APFConfig`'s ``outlier_rad`` times
            the rig's focal length).

    Returns:
        (B,) the sum over markers m and ordered pairs of views i != j of ``min(outlier_px^2, min_k d(z_mik,
        y_mj))``, ``d`` the symmetric epipolar distance (sum of the two squared point-to-epiline distances, px^2)
        between the candidate ``z_mik`` in view i and the marker's projection ``y_mj`` in view j; views i without
        a candidate of the marker add nothing. ``per_marker``: (B, M), each marker's sum.
    """
    return EpipolarCost(detections.to(points), P, F, outlier_px)(points, per_marker)
