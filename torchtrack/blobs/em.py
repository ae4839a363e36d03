"""Expectation-maximisation of the body blobs on a frame's voxels (Caillette §4.1 eq. 2-3, de Bem §III-C).

Each blob j has a position Gaussian (mu_j, K_j) and a colour Gaussian (mu'_j, K'_j). The E-step gives each voxel
to the blob of least

    d(v, j) = (P_v - mu_j)^T K_j^-1 (P_v - mu_j) + min_i (C_v,i - mu'_j)^T K'_j^-1 (C_v,i - mu'_j)

where i runs over the views that see the voxel (the best-fitting view's colour; no visibility test). The M-step
re-estimates the blobs from their voxels with weights w_v (the voxel's volume s_v^3 for the hull, occupancy
probability times volume for the Bayesian grid), adding each cube's own spread s_v^2/12 to the covariance, then
pulls each blob back towards its prior (the blob regenerated from the predicted pose) in proportion to the
prior's expected fill, so a blob that is half hidden or starved keeps its shape. A colour covariance whose
determinant falls below a floor is rescaled up to it. A blob whose fill (weight over its prior volume) falls
under ``EMConfig.min_fill`` is de-activated (Caillette §4.3): it keeps its prior and gives no goals.

Shapes: N voxels, C views, K blobs. Colours are whatever space the observation gives (the background model's
gain-normalised YUV in the tracker); NaN marks a view that does not see the voxel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from functools import partial
from typing import NamedTuple

import torch

from torchtrack.checks import InputError, check_shape


@dataclass(frozen=True)
class EMConfig:
    """EM settings.

    Attributes:
        iterations: E/M passes per frame.
        gate_mahalanobis2: voxels farther than this (position Mahalanobis^2) from every blob are left out
            (phantoms, distractors).
        position_prior: strength of the pull of a blob's mean towards its prior, in units of its prior volume.
        shape_prior: the same for the covariance.
        colour_weight: factor on the colour term of the E-step (0 = position only).
        colour_rate: how fast the colour model follows the frames (running average rate).
        min_colour_std: floor of the colour covariance's geometric-mean std (the determinant rescale).
        min_fill: de-activate a blob whose fill falls under this fraction of its prior volume.
    """

    iterations: int = 3
    gate_mahalanobis2: float = 64.0
    position_prior: float = 0.05
    shape_prior: float = 0.5
    colour_weight: float = 1.0
    colour_rate: float = 0.2
    min_colour_std: float = 0.03
    min_fill: float = 0.2

    def __post_init__(self) -> None:
        if self.iterations < 1:
            raise InputError(f"EMConfig.iterations must be >= 1, got {self.iterations}")
        for name in ("gate_mahalanobis2", "min_colour_std"):
            if not getattr(self, name) > 0:
                raise InputError(f"EMConfig.{name} must be > 0, got {getattr(self, name)}")
        for name in ("position_prior", "shape_prior", "colour_weight", "min_fill"):
            if getattr(self, name) < 0:
                raise InputError(f"EMConfig.{name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 <= self.colour_rate <= 1.0:
            raise InputError(f"EMConfig.colour_rate must be in [0, 1], got {self.colour_rate}")


@dataclass(frozen=True)
class Blobs:
    """State of K blobs.

    Attributes:
        mean: (K, 3) position means (m). cov: (K, 3, 3) position covariances (m^2).
        colour_mean: (K, 3). colour_cov: (K, 3, 3). colour_known: (K,) bool, whether each blob's colour is
            learnt (the E-step ignores colour for a blob until it is).
        fill: (K,) weight assigned over prior volume (1 = as full as expected). active: (K,) bool.
    """

    mean: torch.Tensor
    cov: torch.Tensor
    colour_mean: torch.Tensor
    colour_cov: torch.Tensor
    colour_known: torch.Tensor
    fill: torch.Tensor
    active: torch.Tensor

    @property
    def num_blobs(self) -> int:
        return int(self.mean.shape[0])


def prior_blobs(mean: torch.Tensor, cov: torch.Tensor, colour_mean: torch.Tensor | None = None,
                colour_std: float = 0.2) -> Blobs:
    """Blobs at the prior (regenerated) placement, with an uninformative colour model unless given."""
    check_shape(mean, ("K", 3), "mean")
    K = mean.shape[0]
    check_shape(cov, (K, 3, 3), "cov")
    eye = torch.eye(3, dtype=mean.dtype, device=mean.device)
    cm = colour_mean if colour_mean is not None else mean.new_zeros(K, 3)
    known = torch.full((K,), colour_mean is not None, dtype=torch.bool, device=mean.device)
    return Blobs(mean, cov, cm, (colour_std ** 2) * eye.expand(K, 3, 3).clone(), known,
                 mean.new_ones(K), torch.ones(K, dtype=torch.bool, device=mean.device))


def ellipsoid_volume(cov: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) covariance of a uniform solid ellipsoid -> (...) its volume (semi-axes = sqrt(5) * std)."""
    return (4.0 / 3.0) * math.pi * 5.0 ** 1.5 * torch.linalg.det(cov).clamp(min=0).sqrt()


#: colour given to a view that does not see a voxel in the E-step: 1e4 from the colour space's unit range, so
#: its squared distance (>= 1e8 / the colour covariance's largest variance) loses to any seen view's
_UNSEEN_COLOUR = 1e4


def mahalanobis2(x: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
    """x (..., 3), mean (K, 3), covariances (K, 3, 3) -> (..., K) squared Mahalanobis distances; or B sets at
    once: x (B, ..., 3), mean (B, K, 3), cov (B, K, 3, 3) -> (B, ..., K), each x[b] against blobs b.

    Whitened with the inverse Cholesky factors W_k (W_k^T W_k = cov_k^-1): ``|W_k x - W_k mu_k|^2``, all K blobs
    in one matrix product; the subtraction is of first-order terms, so float32 keeps its precision.
    """
    K = mean.shape[-2]
    eye = torch.eye(3, dtype=cov.dtype, device=cov.device).expand_as(cov)
    # cholesky_ex: no host synchronisation for the check (the covariances are regularised positive definite)
    W = torch.linalg.solve_triangular(torch.linalg.cholesky_ex(cov).L, eye, upper=False)  # ([B,] K, 3, 3)
    Wmu = torch.einsum("...kij,...kj->...ki", W, mean)  # ([B,] K, 3)
    # the squares summed per blob by a matrix product with a (3 K, K) block of ones: faster than a strided sum
    groups = torch.eye(K, dtype=x.dtype, device=x.device).repeat_interleave(3, dim=0)
    if mean.dim() == 2:
        flat = x.reshape(-1, 3)  # one matrix product (a strided 3D operand would run as a loop of small ones)
        y = torch.addmm(-Wmu.reshape(1, K * 3), flat, W.reshape(K * 3, 3).T)  # (M, 3 K): W_k x - W_k mu_k
        return (y.square_() @ groups).view(*x.shape[:-1], K)
    B = mean.shape[0]
    y = torch.baddbmm(-Wmu.reshape(B, 1, K * 3), x.reshape(B, -1, 3), W.reshape(B, K * 3, 3).mT)  # (B, M, 3 K)
    return (y.square_() @ groups).view(*x.shape[:-1], K)


def quadric_distance2(x: torch.Tensor, centres: torch.Tensor, A: torch.Tensor) -> torch.Tensor:
    """x (..., 3), quadrics ``A (K, 3, 3)`` (symmetric) about ``centres (K, 3)`` -> (..., K) ``(x - c)^T A (x - c)``;
    or B sets at once: x (B, ..., 3), centres (B, K, 3), A (B, K, 3, 3) -> (B, ..., K).

    One matrix product of the points' quadratic monomials with each quadric's coefficients (``A``, ``-2 A c`` and
    ``c^T A c``): an output of K per point instead of :func:`mahalanobis2`'s 3 K whitened coordinates. About the
    centres' mean, so that float32 keeps the difference of the terms for points near them (for the colours of
    E-step, where each voxel has one per view, the most of its work).
    """
    batched = centres.dim() == 3
    if not batched:
        x, centres, A = x[None], centres[None], A[None]
    B, K = centres.shape[:2]
    mid = centres.mean(1, keepdim=True)  # (B, 1, 3)
    c = centres - mid
    p = (x.reshape(B, -1, 3) - mid).unbind(-1)  # 3 x (B, M)
    b = (A @ c[..., None])[..., 0]  # (B, K, 3)
    mono = torch.stack([p[0] * p[0], p[1] * p[1], p[2] * p[2], 2 * p[0] * p[1], 2 * p[0] * p[2], 2 * p[1] * p[2],
                        -2 * p[0], -2 * p[1], -2 * p[2], torch.ones_like(p[0])], -1)  # (B, M, 10)
    quad = torch.stack([A[..., 0, 0], A[..., 1, 1], A[..., 2, 2], A[..., 0, 1], A[..., 0, 2], A[..., 1, 2],
                        b[..., 0], b[..., 1], b[..., 2], (c * b).sum(-1)], -1)  # (B, K, 10)
    out = torch.bmm(mono, quad.mT)  # (B, M, K)
    return out.view(*x.shape[:-1], K)[0] if not batched else out.view(*x.shape[:-1], K)


class ColourTerm(NamedTuple):
    """The E-step's colour term of a frame's voxels against a colour model (:func:`colour_term`): which views see
    each voxel ``seen_views ([B,] N, C)``, and where some blob's colour is known, each voxel's least colour distance
    to each blob over the views that see it ``least ([B,] N, K)`` (0 where none sees it or the blob's colour is
    unknown) and that view ``view ([B,] N, K)``; None without colours."""

    seen_views: torch.Tensor | None
    least: torch.Tensor | None
    view: torch.Tensor | None


def colour_term(colours: torch.Tensor | None, blobs: Blobs, config: EMConfig) -> ColourTerm:
    """The colour half of :func:`e_step`'s distance (eq. 2), for voxels' ``colours ([B,] N, C, 3)`` and ``blobs``'
    colour model. It depends on nothing EM changes within a frame (the colour model learns only after its last
    E-step), so :func:`fit_blobs` computes it once."""
    if colours is None:
        return ColourTerm(None, None, None)
    seen_views = torch.isfinite(colours).all(-1)  # ([B,] N, C)
    # no colour known yet (a start): nothing to compute. Asked only on the CPU, where it costs nothing; on a GPU
    # the answer would wait for the device each frame, and the distances of unknown colours are masked to 0 below
    if config.colour_weight <= 0 or (colours.device.type == "cpu" and not bool(blobs.colour_known.any())):
        return ColourTerm(seen_views, None, None)
    # an unseen view's colour put far out of every blob's colour range, so that it never is the nearest
    # (cheaper than masking the (N, C, K) distances); voxels no view sees get no colour term
    far = torch.where(seen_views[..., None], colours, _UNSEEN_COLOUR)
    A = torch.cholesky_inverse(torch.linalg.cholesky_ex(blobs.colour_cov).L)
    least, view = quadric_distance2(far, blobs.colour_mean, A).min(dim=-2)  # ([B,] N, K)
    seen = seen_views.any(dim=-1, keepdim=True) & blobs.colour_known.unsqueeze(-2)  # ([B,] N, K)
    return ColourTerm(seen_views, torch.where(seen, least, 0.0), view)


def e_step(points: torch.Tensor, colours: torch.Tensor | None, blobs: Blobs, config: EMConfig, views: bool = True,
           colour: ColourTerm | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Assign every voxel to its blob (eq. 2-3).

    Args:
        points: (N, 3) voxel centres. colours: (N, C, 3) per-view colours (NaN: unseen) or None. Or B voxel sets
            at once, each against its own blobs: points (B, N, 3), colours (B, N, C, 3), ``blobs`` (B, K, ...); a
            NaN point (padding) is no blob's.
        views: find each voxel's view (False: ``view`` all -1, for an M-step that learns no colour).
        colour: :func:`colour_term` of ``colours`` and ``blobs`` where the caller has it (default: computed).

    Returns:
        assign ([B,] N) int64 blob index, -1 for voxels outside the gate; view ([B,] N) int64 the view whose colour
        was used, or for a blob without a colour model yet the first view that sees the voxel (-1 if none);
        cost ([B,] N) the least distance.
    """
    colour = colour_term(colours, blobs, config) if colour is None else colour
    d_pos = mahalanobis2(points, blobs.mean, blobs.cov)  # ([B,] N, K)
    d_pos = torch.where(blobs.active.unsqueeze(-2), d_pos, torch.inf)
    view = torch.full(points.shape[:-1], -1, dtype=torch.long, device=points.device)
    cost = d_pos if colour.least is None else d_pos + config.colour_weight * colour.least
    cost = torch.where(d_pos <= config.gate_mahalanobis2, cost, torch.inf)  # only blobs within the gate compete
    least, assign = cost.min(dim=-1)
    assign = torch.where(torch.isfinite(least), assign, -1)
    if colour.seen_views is not None and views:
        v = colour.seen_views.to(torch.uint8).argmax(dim=-1)  # the first view that sees the voxel
        if colour.view is not None:  # blobs with a colour model: the view whose colour fits it best
            a = assign.clamp(min=0)
            v = torch.where(blobs.colour_known.gather(-1, a), colour.view.gather(-1, a[..., None])[..., 0], v)
        view = torch.where((assign >= 0) & colour.seen_views.any(dim=-1), v, -1)
    return assign, view, least


def _weighted_moments(x: torch.Tensor, w: torch.Tensor, assign: torch.Tensor, K: int
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-blob sum of weights (K,), weighted mean (K, 3) and covariance about that mean (K, 3, 3) of the rows of
    x assigned to it (``assign`` -1: none). Two passes (mean, then centred scatter) to keep float32 precise. Rows
    assigned to none add zeros rather than being selected out: the same sums, and no wait for the device to count
    them on a GPU."""
    ok = assign >= 0
    a, xs, ws = assign.clamp(min=0), torch.where(ok[:, None], x, 0.0), torch.where(ok, w, 0.0)
    total = torch.zeros(K, dtype=x.dtype, device=x.device).index_add_(0, a, ws)
    safe = total.clamp(min=1e-30)
    mean = torch.zeros(K, 3, dtype=x.dtype, device=x.device).index_add_(0, a, ws[:, None] * xs) / safe[:, None]
    d = xs - mean[a]
    cov = torch.zeros(K, 9, dtype=x.dtype, device=x.device).index_add_(
        0, a, ws[:, None] * (d[:, :, None] * d[:, None, :]).reshape(-1, 9)).view(K, 3, 3) / safe[:, None, None]
    return total, mean, cov


def m_step(points: torch.Tensor, weights: torch.Tensor, sizes: torch.Tensor, colours: torch.Tensor | None,
           assign: torch.Tensor, view: torch.Tensor, blobs: Blobs, prior: Blobs, config: EMConfig,
           learn_colour: bool | torch.Tensor = True) -> Blobs:
    """Re-estimate the blobs from their voxels, pulled towards ``prior`` (see the module docstring).

    Args:
        points (N, 3), weights (N,), sizes (N,) voxel edge (m), colours (N, C, 3) or None, assign and view
        from :func:`e_step`; blobs: the current estimate (its colour model is updated); prior: the regenerated
        blobs (position mean and covariance used). learn_colour: update the colour model, or (K,) bool which blobs'.
    """
    K = blobs.num_blobs
    total, mu, scatter_obs = _weighted_moments(points, weights, assign, K)
    own = torch.zeros(K, dtype=points.dtype, device=points.device)
    own.index_add_(0, assign.clamp(min=0), torch.where(assign >= 0, weights * sizes ** 2 / 12.0, 0.0))
    eye = torch.eye(3, dtype=points.dtype, device=points.device)
    cov = scatter_obs + (own / total.clamp(min=1e-30))[:, None, None] * eye
    prior_volume = ellipsoid_volume(prior.cov)  # (K,)
    fill = total / prior_volume
    # MAP-style blend with the prior: weights of pseudo-observations proportional to the prior volume
    wp = config.position_prior * prior_volume
    ws = config.shape_prior * prior_volume
    mean = (total[:, None] * mu + wp[:, None] * prior.mean) / (total + wp).clamp(min=1e-30)[:, None]
    # covariance about the new mean: observed scatter plus the prior's shape centred at the new mean
    d = mu - mean
    scatter = cov + d[:, :, None] * d[:, None, :]
    cov = ((total[:, None, None] * scatter + ws[:, None, None] * prior.cov)
           / (total + ws).clamp(min=1e-30)[:, None, None])
    active = fill >= config.min_fill
    mean = torch.where(active[:, None], mean, prior.mean)
    cov = torch.where(active[:, None, None], cov, prior.cov)
    colour_mean, colour_cov, known = blobs.colour_mean, blobs.colour_cov, blobs.colour_known
    learn = learn_colour if isinstance(learn_colour, torch.Tensor) else None
    if colours is not None and (learn is not None or learn_colour):
        has = (assign >= 0) & (view >= 0)
        c = colours.gather(1, view.clamp(min=0)[:, None, None].expand(-1, 1, 3))[:, 0]  # (N, 3) the chosen view's
        ctot, cmu, ccov = _weighted_moments(c, weights, torch.where(has, assign, -1), K)  # colour, where there is one
        ccov = _floor_determinant(ccov + 1e-6 * eye, config.min_colour_std)
        rate = torch.where(known, config.colour_rate, 1.0).to(cmu.dtype)  # (K,): a blob's first colours in full
        upd = (ctot > 0) & active if learn is None else (ctot > 0) & active & learn.to(active.device)
        colour_mean = torch.where(upd[:, None], (1 - rate[:, None]) * colour_mean + rate[:, None] * cmu, colour_mean)
        colour_cov = torch.where(upd[:, None, None], (1 - rate[:, None, None]) * colour_cov
                                 + rate[:, None, None] * ccov, colour_cov)
        known = known | upd
    return Blobs(mean, cov, colour_mean, colour_cov, known, fill, active)


def _floor_determinant(cov: torch.Tensor, min_std: float) -> torch.Tensor:
    """Rescale (K, 3, 3) covariances whose geometric-mean std is under ``min_std`` up to it."""
    gstd = torch.linalg.det(cov).clamp(min=1e-30) ** (1.0 / 6.0)
    scale = torch.where(gstd < min_std, (min_std / gstd) ** 2, torch.ones_like(gstd))
    return cov * scale[:, None, None]


def fit_blobs(points: torch.Tensor, weights: torch.Tensor, sizes: torch.Tensor, colours: torch.Tensor | None,
              prior: Blobs, config: EMConfig = EMConfig(), learn_colour: bool | torch.Tensor = True
              ) -> tuple[Blobs, torch.Tensor]:
    """EM from the prior blobs (with its colour model) on one frame's voxels, or on B frames' at once.

    Args:
        points: (N, 3) voxel centres (m). weights: (N,). sizes: (N,) voxel edges (m).
        colours: (N, C, 3) or None. prior: :class:`Blobs` regenerated from the predicted pose.
        learn_colour: whether the colour model learns from this frame (for B frames: one flag, or (B,) bool).
        B frames (the lockstep tracker's sequences): points (B, N, 3), weights, sizes (B, N), colours
        (B, N, C, 3), prior (B, K, ...); a set of fewer voxels padded with NaN points of weight 0 (no blob's).
        Each frame's EM is the one it gets alone.

    Returns:
        the fitted blobs ([B,] K, ...) and ``assign ([B,] N)`` of the last E-step (-1: left out).
    """
    batched = points.dim() == 3
    N = points.shape[-2]
    lead = tuple(points.shape[:-2])
    check_shape(points, (*lead, N, 3), "points")
    check_shape(weights, (*lead, N), "weights")
    check_shape(sizes, (*lead, N), "sizes")
    if colours is not None:
        check_shape(colours, (*lead, N, None, 3), "colours")
    blobs = prior
    assign = torch.full((*lead, N), -1, dtype=torch.long, device=points.device)
    if batched:  # the M-step is per blob: the B frames' blobs as B K blobs, their voxels as B N
        B, K = prior.mean.shape[:2]
        flat = partial(_reshape_blobs, shape=(B * K,))
        prior_flat = flat(prior)
        offset = (torch.arange(B, device=points.device) * K)[:, None]  # (B, 1)
        pts, w, sz = points.reshape(B * N, 3), weights.reshape(B * N), sizes.reshape(B * N)
        col = None if colours is None else colours.reshape(B * N, *colours.shape[2:])
        if isinstance(learn_colour, torch.Tensor):  # (B,) -> per blob
            learn_colour = learn_colour.to(torch.bool).repeat_interleave(K)
    colour = colour_term(colours, prior, config)  # the colour model stays the prior's until the last M-step
    for it in range(config.iterations):
        last = it == config.iterations - 1
        learn = learn_colour if last else False
        assign, view, _ = e_step(points, colours, blobs, config,
                                 views=isinstance(learn, torch.Tensor) or bool(learn), colour=colour)
        if batched:
            joined = torch.where(assign >= 0, assign + offset, -1).reshape(-1)
            blobs = _reshape_blobs(m_step(pts, w, sz, col, joined, view.reshape(-1), flat(blobs), prior_flat, config,
                                          learn_colour=learn), (B, K))
        else:
            blobs = m_step(points, weights, sizes, colours, assign, view, blobs, prior, config, learn_colour=learn)
        if not last:  # keep every blob in play for the next E-step; activity is decided on the last pass
            blobs = replace(blobs, active=prior.active)
    return blobs, assign


def _reshape_blobs(b: Blobs, shape: tuple[int, ...]) -> Blobs:
    """The blobs' tensors with their leading blob dimensions reshaped to ``shape`` (e.g. B bodies' K <-> B K)."""
    lead = b.mean.dim() - 1  # the blob dimensions: those before the mean's 3
    return Blobs(*(getattr(b, f.name).reshape(*shape, *getattr(b, f.name).shape[lead:]) for f in fields(Blobs)))
