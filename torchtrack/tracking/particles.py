"""Marker-based tracking by an annealed particle filter (Canton-Ferrer et al. 2010; Deutscher & Reid's annealing).

Per frame: the particles (states of the skeleton) start from the last estimate; each of ``layers`` layers
perturbs them by a truncated Gaussian inside the joint limits (its spread shrinking layer by layer), weighs them by
``exp(-beta * cost)`` with ``beta`` set for a target survival rate, and resamples. The cost of a state is the
symmetric epipolar distance between each model marker's projection in one view and the marker's detections in
another (the best of the candidates, capped at an outlier threshold; kornia's fundamental matrices), summed over
markers and ordered pairs of views. The estimate is the weighted mean
of the last layer. No I/O here; one frame is a few large tensor operations over the particles.

Detections are compared in each camera's undistorted (pinhole) pixels, where the epipolar geometry holds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from kornia.geometry.epipolar import fundamental_from_projections
from torch import nn

from torchtrack.checks import InputError, check_shape
from torchtrack.markers.model import MarkerSet
from torchtrack.skeleton.model import Skeleton

__all__ = ["APFConfig", "EpipolarCost", "MarkerAPF", "annealing_beta", "epipolar_cost", "fundamental_matrices",
           "pinhole_pixels", "projection_matrices", "resample", "truncated_normal"]


@dataclass(frozen=True)
class APFConfig:
    """The filter's settings.

    Attributes:
        particles: particles per layer. layers: annealing layers per frame (the paper's best: 5).
        survival: the survival rate each layer's ``beta`` is set for (effective sample size / particles).
        outlier_px: a marker's epipolar distance to a view's detections counts at most this much (pixels): a
            detection farther off is another marker's or a false one.
        root_m, root_rad, joint_rad: the first layer's perturbation (standard deviation) of the root's translation,
            its rotation and every joint angle; ``shrink``: each later layer's, as a factor of the one before.
        partitioned: each limb's joints resampled by the limb's own markers (the trunk's by all of them), not whole
            particles by the total cost alone.
        velocity: the share of the last frame's motion the prediction carries on (0: none).
        polish_steps: Levenberg-Marquardt iterations on the same cost from the filter's estimate (0: none).
        The figures behind these values: docs/results.md, "Marker-based capture".
    """

    particles: int = 500
    layers: int = 5
    survival: float = 0.5
    outlier_px: float = 20.0
    root_m: float = 0.02
    root_rad: float = 0.03
    joint_rad: float = 0.05
    shrink: float = 0.5
    partitioned: bool = True
    velocity: float = 0.8
    polish_steps: int = 20

    def __post_init__(self) -> None:
        if self.particles < 2 or self.layers < 1 or not 0 < self.survival < 1 or not self.outlier_px > 0:
            raise InputError(f"APFConfig: particles >= 2, layers >= 1, survival in (0, 1), outlier_px > 0; got {self}")
        if min(self.root_m, self.root_rad, self.joint_rad) < 0 or not 0 < self.shrink <= 1:
            raise InputError(f"APFConfig: perturbations >= 0 and shrink in (0, 1]; got {self}")


#: The polish's forward-difference step (m for the root's translation, rad for angles), and the relative fall of
#: the cost below which it stops (a ten-thousandth: well under a pixel's worth over the markers).
FD_STEP, POLISH_TOL = 1e-6, 1e-4
#: The limbs whose joints the filter resamples by their own markers: name prefixes of their DOFs and bones.
LIMBS = (("l_shoulder", "l_elbow", "l_wrist", "l_upperarm", "l_forearm", "l_hand"),
         ("r_shoulder", "r_elbow", "r_wrist", "r_upperarm", "r_forearm", "r_hand"),
         ("l_hip", "l_knee", "l_ankle", "l_thigh", "l_shank", "l_foot"),
         ("r_hip", "r_knee", "r_ankle", "r_thigh", "r_shank", "r_foot"))


def _part(name: str) -> int:
    """The body part of a DOF or bone name: 1 + its limb in ``LIMBS``, or 0 (root, trunk, head)."""
    for g, prefixes in enumerate(LIMBS):
        if name.startswith(prefixes):
            return g + 1
    return 0


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
    """The cost of states' markers against one frame's detections (:func:`epipolar_cost`), with the detections'
    epipolar lines computed once for the frame: each layer of each frame then costs two small contractions per
    view pair. Hand-written over kornia's :func:`~kornia.geometry.epipolar.symmetrical_epipolar_distance` (the
    same distance, tested against it) because that one recomputes every candidate's line for every state.

    The distance is invariant to each fundamental matrix's scale and to the lines' scale, so both are normalised
    here (in float64): the lines then give pixel distances directly, and the states' side runs in their own dtype
    (float32 for the particle filter's layers) without the ill-scaled products of a raw F.

    Args:
        detections: (C, M, K, 2) each marker's candidate detections per view in pinhole pixels, NaN where none.
        P: (C, 3, 4) pinhole projections. F: (C, C, 3, 3) fundamental matrices (:func:`fundamental_matrices`).
        outlier_px: see :class:`APFConfig`.
    """

    def __init__(self, detections: torch.Tensor, P: torch.Tensor, F: torch.Tensor, outlier_px: float) -> None:
        C, M, K, _ = detections.shape
        dtype, dev = detections.dtype, detections.device
        self.P, self.cap = P.to(dtype), outlier_px ** 2
        i, j = (~torch.eye(C, dtype=torch.bool, device=dev)).nonzero(as_tuple=True)  # the ordered view pairs
        self.j = j
        Fij = F.to(dev, torch.float64)[i, j]  # (S, 3, 3): x_j^T Fij x_i = 0
        Fij = Fij / Fij.flatten(1).norm(dim=1).clamp(min=1e-300)[:, None, None]
        z = detections.double()
        seen = torch.isfinite(z).all(-1)  # (C, M, K)
        z = torch.cat([torch.nan_to_num(z), torch.ones_like(z[..., :1])], -1)  # (C, M, K, 3)
        lines = torch.einsum("scd,smkd->smkc", Fij, z[i])  # (S, M, K, 3): z_ik's epiline in view j
        norm2 = lines[..., :2].square().sum(-1)  # (S, M, K)
        self.ok = seen[i] & (norm2 > 1e-300)  # a candidate at the epipole has no line there
        unit = lines / norm2.clamp(min=1e-300).sqrt()[..., None]  # y . unit: y's distance from the line, px
        # laid out for states last (B contiguous): each contraction is one batched product, each mask broadcast
        # along B, each reduction over K runs along contiguous rows (several times faster than states first)
        self.unit = unit.to(dtype)  # (S, M, K, 3)
        self.norm2 = torch.where(self.ok, norm2, 0.0)[..., None].to(dtype)  # (S, M, K, 1)
        self.F12_T = Fij[..., :2].transpose(-1, -2)[:, None].contiguous().to(dtype)  # (S, 1, 2, 3): (F^T y)_12
        self.P = self.P[:, None]  # (C, 1, 3, 4)
        self.not_ok = ~self.ok[..., None]  # (S, M, K, 1)
        self.pair = self.ok.any(-1)  # (S, M): view i has a candidate of marker m
        self.no_pair = ~self.pair[..., None]  # (S, M, 1)

    def _terms(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Points ``(M, 3, B)``, states last -> each candidate's signed distance from the projection's epiline
        ``(S, M, K, B)`` (px) and ``1 + |(F z)_12|^2 / |(F^T y)_12|^2`` ``(S, M, K, B)``: the symmetric distance is
        their product with the first squared."""
        h = torch.cat([points, torch.ones_like(points[:, :1])], 1)  # (M, 4, B)
        y = self.P.to(h) @ h[None]  # (C, M, 3, B)
        y = (y / y[:, :, 2:3])[self.j]  # (S, M, 3, B) each pair's second view's projection, w = 1
        dist = self.unit.to(y) @ y  # (S, M, K, B): y_j from z_ik's epiline, px
        b = self.F12_T.to(y) @ y  # (S, M, 2, B)
        back = (b[:, :, 0].square() + b[:, :, 1].square()).clamp(min=1e-30)  # (S, M, B): |(F^T y_j)_12|^2
        return dist, self.norm2.to(y) / back[:, :, None] + 1

    def __call__(self, points: torch.Tensor, per_marker: bool = False, states_last: bool = False) -> torch.Tensor:
        """``points (B, M, 3)`` (``states_last``: ``(M, 3, B)``) -> (B,) costs, or (B, M) with ``per_marker``. In
        place where no gradient is asked for (the particle filter's layers)."""
        if not states_last:
            points = points.permute(1, 2, 0)
        dist, factor = self._terms(points)
        if torch.is_grad_enabled() and (points.requires_grad or dist.requires_grad or factor.requires_grad):
            d = (dist.square() * factor).masked_fill(self.not_ok, math.inf)
            d = d.amin(2).clamp(max=self.cap).masked_fill(self.no_pair, 0.0)
        else:
            d = dist.square_().mul_(factor).masked_fill_(self.not_ok, math.inf)
            d = d.amin(2).clamp_(max=self.cap).masked_fill_(self.no_pair, 0.0)  # (S, M, B)
        cost = d.sum(0)  # (M, B)
        return cost.T if per_marker else cost.sum(0)

    def residuals(self, points: torch.Tensor, pick: torch.Tensor | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
        """``points (B, M, 3)`` -> (B, S * M) signed residuals whose squares sum to the cost's terms below the
        outlier cap (0 for the others), each pair's and marker's nearest candidate, or the candidates ``pick (S, M)``
        (the nearest are returned with the residuals, to keep them while a Jacobian is taken)."""
        B = points.shape[0]
        dist, factor = self._terms(points.permute(1, 2, 0))
        r = dist * factor.sqrt()  # (S, M, K, B)
        r2 = r.square().masked_fill(self.not_ok, math.inf)
        if pick is None:
            pick = r2[..., 0].argmin(-1)  # (S, M): the first state's nearest candidate
        idx = pick[:, :, None, None].expand(*r.shape[:2], 1, r.shape[3])
        use = self.pair[..., None] & (r2.gather(2, idx)[:, :, 0] < self.cap)  # (S, M, B)
        out = torch.where(use, r.gather(2, idx)[:, :, 0], 0.0)
        return out.permute(2, 0, 1).reshape(B, -1), pick


def epipolar_cost(points: torch.Tensor, detections: torch.Tensor, P: torch.Tensor, F: torch.Tensor,
                  outlier_px: float, per_marker: bool = False) -> torch.Tensor:
    """The cost of each state's markers against one frame's detections.

    Args:
        points: (B, M, 3) the model markers of B states (world, m).
        detections: (C, M, K, 2) each marker's candidate detections per view in pinhole pixels, NaN where none.
        P: (C, 3, 4) pinhole projections. F: (C, C, 3, 3) fundamental matrices (:func:`fundamental_matrices`).
        outlier_px: see :class:`APFConfig`.

    Returns:
        (B,) the sum over markers m and ordered pairs of views i != j of ``min(outlier_px^2, min_k d(z_mik,
        y_mj))``, ``d`` the symmetric epipolar distance (sum of the two squared point-to-epiline distances, px^2)
        between the candidate ``z_mik`` in view i and the marker's projection ``y_mj`` in view j; views i without
        a candidate of the marker add nothing. ``per_marker``: (B, M), each marker's sum.
    """
    return EpipolarCost(detections.to(points), P, F, outlier_px)(points, per_marker)


def annealing_beta(cost: torch.Tensor, survival: float, stages: int = 6, points: int = 8) -> torch.Tensor:
    """Per row of ``cost (..., N)``, the ``beta`` whose weights ``exp(-beta * (cost - min))`` have an effective
    sample size of ``survival`` times N; the survival rate falls as beta grows, so each of ``stages`` rounds
    evaluates it at ``points`` values of log beta in one tensor operation and keeps the bracket where it crosses
    ``survival`` (from [-30, 30]: log beta to within 60 / (points - 1)^stages, 5e-4 by default). Returns ``(...,)``
    float64; 0 where a row's costs are all equal."""
    c = (cost - cost.amin(-1, keepdim=True)).double()  # (..., N)
    n = c.shape[-1]
    lo = c.new_full(c.shape[:-1], -30.0)
    hi = c.new_full(c.shape[:-1], 30.0)
    steps = torch.linspace(0.0, 1.0, points, dtype=c.dtype, device=c.device)
    for _ in range(stages):
        grid = lo[..., None] + (hi - lo)[..., None] * steps  # (..., P) log beta
        w = torch.exp(-grid.exp()[..., None] * c[..., None, :])  # (..., P, N)
        rate = w.sum(-1) ** 2 / (n * (w * w).sum(-1))  # (..., P), falling along P
        k = (rate > survival).sum(-1, keepdim=True).clamp(1, points - 1)  # the first point at or below
        lo, hi = grid.gather(-1, k - 1)[..., 0], grid.gather(-1, k)[..., 0]
    return torch.where(c.amax(-1) > 0, (0.5 * (lo + hi)).exp(), 0.0)


def resample(weights: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Indices ``(..., N)`` drawn by systematic resampling from each row of unnormalised ``weights (..., N)`` (one
    uniform offset per row)."""
    w = weights.double()
    N = w.shape[-1]
    cdf = w.cumsum(-1) / w.sum(-1, keepdim=True)
    u = (torch.rand((*w.shape[:-1], 1), generator=generator, device=w.device, dtype=torch.float64)
         + torch.arange(N, device=w.device, dtype=torch.float64)) / N
    return torch.searchsorted(cdf.contiguous(), u.contiguous()).clamp(max=N - 1)


def truncated_normal(mean: torch.Tensor, std: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor,
                     generator: torch.Generator) -> torch.Tensor:
    """Samples of N(mean, std^2) truncated to [lower, upper], elementwise (``mean (..., D)``, the others
    broadcasting), by the inverse CDF: exact, no rejection loop. ``std`` 0 gives ``mean`` clamped."""
    dt = torch.float64
    m, s = mean.to(dt), std.to(dt).expand_as(mean)
    lo, hi = lower.to(dt).expand_as(mean), upper.to(dt).expand_as(mean)
    safe = s > 0
    s1 = torch.where(safe, s, 1.0)
    a = torch.special.ndtr((lo - m) / s1)
    b = torch.special.ndtr((hi - m) / s1)
    u = a + (b - a) * torch.rand(mean.shape, generator=generator, device=mean.device, dtype=dt)
    eps = torch.finfo(dt).tiny
    x = m + s1 * torch.special.ndtri(u.clamp(eps, 1 - 1e-16))
    x = torch.where(safe, x, m)
    return torch.minimum(torch.maximum(x, lo), hi).to(mean.dtype)


class MarkerAPF:
    """The annealed particle filter of one subject.

    Args:
        skeleton: the subject's skeleton (its bone lengths). marker_set: its markers. rig: the cameras.
        config: the filter's settings. generator: every random draw's source.
    """

    def __init__(self, skeleton: Skeleton, marker_set: MarkerSet, rig: nn.Module, config: APFConfig = APFConfig(),
                 generator: torch.Generator | None = None) -> None:
        self.skeleton, self.marker_set, self.rig, self.config = skeleton, marker_set, rig, config
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.P = projection_matrices(rig).double()
        self.F = fundamental_matrices(rig)
        D, dev = skeleton.num_dofs, skeleton.lower.device  # everything on the skeleton's device
        std = torch.full((D,), config.joint_rad, dtype=torch.float64, device=dev)
        std[:3], std[3:6] = config.root_m, config.root_rad
        self.std = std
        self.lower, self.upper = skeleton.lower.double(), skeleton.upper.double()
        # the body's parts: each limb's joints and the markers on its bones (the trunk, root and head: part 0)
        self.dof_part = torch.tensor([_part(n) for n in skeleton.dof_names], device=dev)
        self.marker_part = torch.tensor([_part(skeleton.bone_names[b]) for b in marker_set.bone.tolist()], device=dev)
        self.state: torch.Tensor | None = None
        self.spread: float = math.nan

    def reset(self, angles: torch.Tensor) -> None:
        """Start from the state ``angles (D,)``."""
        check_shape(angles, (self.skeleton.num_dofs,), "angles")
        self.state = angles.detach().double().clone()
        self.previous = self.state.clone()

    def _polish(self, angles: torch.Tensor, score: EpipolarCost) -> torch.Tensor:
        """Levenberg-Marquardt on the cost's residuals from the filter's estimate, within the joint limits: the
        Jacobian by forward differences, the estimate and every column's state in one batch (a single state's
        autograd, as L-BFGS took it, cost several times as much per step for the same result). Hand-written over
        scipy's ``least_squares`` because a step is kept only where the true cost falls (each marker's nearest
        candidate and the outlier cap change under it): scipy's LM and TRF stalled on such frames
        (docs/results.md, "Marker-based capture")."""
        theta = angles.detach().double()
        D = theta.shape[0]
        step = torch.full((D,), FD_STEP, dtype=theta.dtype, device=theta.device)
        eye = torch.eye(D, dtype=theta.dtype, device=theta.device)
        cost = float(score(self.markers(theta[None]))[0])
        lam = 1e-3
        for _ in range(self.config.polish_steps):
            states = torch.cat([theta[None], theta + torch.diag(step)])  # the estimate, then one DOF moved each
            r, _ = score.residuals(self.markers(states))  # (D + 1, R), each candidate the estimate's nearest
            J = (r[1:] - r[0]) / step[:, None]  # (D, R)
            A, g = J @ J.T, J @ r[0]
            for _ in range(4):  # damp until the cost falls
                delta = torch.linalg.solve(A + lam * (torch.diag(A.diagonal()) + 1e-9 * eye), -g)
                trial = self.skeleton.clamp(theta + delta)
                trial_cost = float(score(self.markers(trial[None]))[0])
                if trial_cost < cost:
                    break
                lam *= 10.0
            else:
                break
            converged = cost - trial_cost < POLISH_TOL * cost
            theta, cost, lam = trial, trial_cost, max(lam / 10.0, 1e-7)
            if converged:
                break
        return theta

    def hold(self) -> None:
        """A frame without detections: the state stays, and the next frame predicts without velocity."""
        if self.state is not None:
            self.previous = self.state.clone()

    def markers(self, angles: torch.Tensor) -> torch.Tensor:
        """(B, D) states -> (B, M, 3) their model markers, in the states' dtype."""
        return self.markers_last(angles).permute(2, 0, 1)

    def markers_last(self, angles: torch.Tensor) -> torch.Tensor:
        """(B, D) states -> (M, 3, B) their model markers, states last."""
        return self.marker_set.positions_last(*self.skeleton.bone_poses_last(angles))

    def step(self, detections: torch.Tensor) -> torch.Tensor:
        """One frame: ``detections (C, M, K, 2)`` in pinhole pixels (:func:`pinhole_pixels`) -> the estimate
        ``(D,)``; :attr:`spread` is the last layer's weighted RMS distance of the particles' markers from the
        estimate's (m), the paper's lost-track signal (it stays small where the whole cloud follows a wrong pose:
        :mod:`torchtrack.markers.track` tests the estimate against the triangulated markers instead)."""
        if self.state is None:
            raise InputError("MarkerAPF.step: no state yet; call reset() with a start pose")
        cfg, gen = self.config, self.generator
        predicted = self.skeleton.clamp(self.state + cfg.velocity * (self.state - self.previous))
        x = predicted[None].expand(cfg.particles, -1)
        std = self.std
        G = len(LIMBS) + 1
        # the layers weigh the particles in float32 (costs in px^2, a thousandth of a pixel's precision is plenty);
        # the polish and the estimate stay in float64
        layer_score = EpipolarCost(detections.float(), self.P, self.F, cfg.outlier_px)
        for _ in range(cfg.layers):
            x = truncated_normal(x, std, self.lower, self.upper, gen)
            per = layer_score(self.markers_last(x.float()), per_marker=True, states_last=True).double()
            parts = per.new_zeros(per.shape[0], G).index_add_(1, self.marker_part, per)  # (N, G)
            # row 0 weighs whole particles by the total cost; with ``partitioned``, row g weighs limb g's joints by
            # the limb's own markers (the trunk's as the whole particle drew them)
            costs = torch.cat([parts.sum(1, keepdim=True), parts[:, 1:]], 1).T  # (G, N)
            if not cfg.partitioned:
                costs = costs[:1]
            W = torch.exp(-annealing_beta(costs, cfg.survival)[:, None] * (costs - costs.amin(1, keepdim=True)))
            keep, w = x, W[0]
            drawn = keep[resample(W, gen)]  # (G or 1, N, D): each row's draw of whole particles
            part = self.dof_part if cfg.partitioned else torch.zeros_like(self.dof_part)  # the row each DOF takes
            x = drawn.gather(0, part[None, None].expand(1, *drawn.shape[1:]))[0]
            std = std * cfg.shrink
        w = w / w.sum()
        estimate = (w[:, None] * keep).sum(0)
        if cfg.polish_steps > 0:
            estimate = self._polish(estimate, EpipolarCost(detections.double(), self.P, self.F, cfg.outlier_px))
        self.previous, self.state = self.state, estimate
        with torch.no_grad():
            pts = self.markers(torch.cat([self.state[None], keep]).float())
        self.spread = float((w * ((pts[1:] - pts[:1]) ** 2).sum(-1).mean(-1)).sum().sqrt())
        return self.state.clone()
