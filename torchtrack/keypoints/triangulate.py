"""Robust multi-view triangulation of 2D keypoints, batched over frames and keypoints.

Each keypoint is the point nearest, in the least-squares sense, to the rays of the views that detected it
(:func:`nearest_to_rays`); views whose detection lands far from the triangulated point's projection are dropped
one at a time, the worst first, while at least two remain (:func:`triangulate_keypoints`). Hand-written: OpenCV
and kornia triangulate from two views only, and the views to trust differ per keypoint.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchtrack.checks import ShapeError

#: Smallest summed weight of a keypoint's views, below which it is not triangulated.
MIN_WEIGHT = 1e-6
#: About the smallest angle (rad) between two of a keypoint's rays: nearly parallel rays leave its depth unknown.
MIN_RAY_ANGLE_RAD = 0.05


def nearest_to_rays(origins: Tensor, directions: Tensor, weights: Tensor) -> Tensor:
    """The point nearest to weighted rays: ``argmin_x sum_c w_c |(I - d_c d_c^T)(x - o_c)|^2``.

    Args:
        origins, directions: ``(C, ..., 3)`` ray origins and unit directions, one ray per view.
        weights: ``(C, ...)`` non-negative weights (0 drops a view).

    Returns:
        ``(..., 3)``; NaN where fewer than two views with rays at least :data:`MIN_RAY_ANGLE_RAD` apart count.
    """
    if origins.shape != directions.shape or origins.shape[:-1] != weights.shape:
        raise ShapeError(f"origins {tuple(origins.shape)}, directions {tuple(directions.shape)} and weights "
                         f"{tuple(weights.shape)} must be (C, ..., 3), (C, ..., 3) and (C, ...)")
    eye = torch.eye(3, dtype=origins.dtype, device=origins.device)
    proj = eye - directions[..., :, None] * directions[..., None, :]  # (C, ..., 3, 3)
    w = weights[..., None, None]
    A = (w * proj).sum(0)  # (..., 3, 3)
    b = (w * proj @ origins[..., None]).sum(0)[..., 0]  # (..., 3)
    # The smallest eigenvalue of A is the weight of the rays' spread: w (1 - |cos(angle)|) for two rays of weight w
    # (0 for parallel or opposite rays), so two rays count from about sqrt(2) MIN_RAY_ANGLE_RAD apart.
    spread = torch.linalg.eigvalsh(A)[..., 0]
    enough = spread > weights.sum(0).clamp_min(MIN_WEIGHT) * 0.5 * MIN_RAY_ANGLE_RAD ** 2
    safe = torch.where(enough[..., None, None], A, eye.expand_as(A))
    x = torch.linalg.solve(safe, torch.where(enough[..., None], b, torch.zeros_like(b)))
    return torch.where(enough[..., None], x, torch.full_like(x, float("nan")))


@dataclass(frozen=True)
class Triangulated:
    """Keypoints triangulated from several views.

    Attributes:
        points: ``(..., K, 3)`` world points (m), NaN where a keypoint has fewer than two consistent views.
        views: ``(C, ..., K)`` bool, the views each point was triangulated from.
        error_px: ``(C, ..., K)`` distance (px) from each detection to the point's projection (NaN where either
            is missing).
    """

    points: Tensor
    views: Tensor
    error_px: Tensor


def triangulate_keypoints(rig, uv_px: Tensor, confidence: Tensor, max_error_px: Tensor | float,
                          min_confidence: float = 0.5) -> Triangulated:
    """Triangulate detections of the same keypoints in every camera of ``rig``, dropping inconsistent views.

    Args:
        rig: the :class:`~torchtrack.cameras.CameraRig` the pixels are in (distorted pixel coordinates).
        uv_px: ``(C, ..., K, 2)`` detections (any value where the confidence is below ``min_confidence``).
        confidence: ``(C, ..., K)`` in [0, 1]; 0 where a camera found no person.
        max_error_px: a detection farther than this from the point's projection is dropped, a float or a
            ``(C, ...)`` tensor (e.g. a share of the person's size in each view).
        min_confidence: detections below it are not used.

    Returns:
        :class:`Triangulated`; a point keeps at least two views, each within ``max_error_px``.
    """
    if uv_px.dim() < 3 or uv_px.shape[0] != len(rig) or uv_px.shape[-1] != 2:
        raise ShapeError(f"uv_px: expected shape ({len(rig)}, ..., K, 2), got {tuple(uv_px.shape)}")
    if confidence.shape != uv_px.shape[:-1]:
        raise ShapeError(f"confidence: expected shape {tuple(uv_px.shape[:-1])}, got {tuple(confidence.shape)}")
    uv = torch.nan_to_num(uv_px.to(rig.K.dtype))
    limit = torch.as_tensor(max_error_px, dtype=uv.dtype, device=uv.device)
    limit = limit[..., None] if limit.dim() == uv.dim() - 2 else limit  # (C, ...) -> (C, ..., 1)
    origins, directions = rig.pixel_rays(uv)
    use = (confidence >= min_confidence) & torch.isfinite(uv_px).all(-1)
    C = len(rig)
    for _ in range(max(C - 1, 1)):  # at most one view dropped a round
        points = nearest_to_rays(origins, directions, use.to(uv.dtype))
        error = _reprojection_error(rig, points, uv)
        bad = use & ~(error <= limit)  # NaN errors (a point behind a camera) count as bad
        # drop each point's worst view, while more than two are used
        worst = torch.where(bad, error.nan_to_num(float("inf")), torch.zeros_like(error)).argmax(0, keepdim=True)
        drop = torch.zeros_like(use).scatter_(0, worst, True) & bad & (use.sum(0, keepdim=True) > 2)
        if not bool(drop.any()):
            break
        use = use & ~drop
    points = nearest_to_rays(origins, directions, use.to(uv.dtype))
    error = _reprojection_error(rig, points, uv)
    consistent = (use & (error <= limit)).sum(0) >= 2
    # a two-view point whose views disagree is no point
    consistent &= ~(use & ~(error <= limit)).any(0)
    points = torch.where(consistent[..., None], points, torch.full_like(points, float("nan")))
    use = use & consistent
    error = torch.where(torch.isfinite(uv_px).all(-1) & (confidence > 0), error, torch.full_like(error, float("nan")))
    return Triangulated(points, use, error)


def consistent_views(rig, uv_px: Tensor, confidence: Tensor, max_error_px: Tensor | float,
                     min_confidence: float = 0.5, min_agreement: float = 0.6) -> Tensor:
    """The views whose detections are of one and the same person, per frame (a RANSAC over pairs of views).

    Each pair of views triangulates every keypoint; a view agrees with the pair where at least
    ``min_agreement`` of its confident keypoints lie within ``max_error_px`` of the pair's points. The pair with
    the most agreeing views wins. A detector that found someone else in some views (a bystander) or a person's
    mirror image loses those views.

    Args:
        as :func:`triangulate_keypoints`: ``uv_px (C, ..., K, 2)``, ``confidence (C, ..., K)``, ``max_error_px``
            a float or ``(C, ...)``.

    Returns:
        ``(C, ...)`` bool; all False where no two views agree.
    """
    C = len(rig)
    uv = torch.nan_to_num(uv_px.to(rig.K.dtype))
    conf = (confidence >= min_confidence) & torch.isfinite(uv_px).all(-1)  # (C, ..., K)
    limit = torch.as_tensor(max_error_px, dtype=uv.dtype, device=uv.device)
    limit = limit[..., None] if limit.dim() == uv.dim() - 2 else limit
    pairs = torch.combinations(torch.arange(C, device=uv.device), 2)  # (P, 2)
    if len(pairs) == 0:
        return torch.zeros(conf.shape[:-1], dtype=torch.bool, device=conf.device)
    origins, directions = rig.pixel_rays(uv)  # (C, ..., K, 3)
    in_pair = torch.zeros(C, len(pairs), dtype=uv.dtype, device=uv.device)  # (C, P)
    in_pair[pairs[:, 0], torch.arange(len(pairs))] = 1.0
    in_pair[pairs[:, 1], torch.arange(len(pairs))] = 1.0
    shape = (C, len(pairs)) + (1,) * (conf.dim() - 1)
    weights = in_pair.reshape(shape) * conf[:, None].to(uv.dtype)  # (C, P, ..., K)
    points = nearest_to_rays(origins[:, None].expand(*weights.shape, 3), directions[:, None].expand(*weights.shape, 3),
                             weights)  # (P, ..., K, 3)
    error = _reprojection_error(rig, points, uv[:, None])  # (C, P, ..., K)
    near = conf[:, None] & (error <= (limit[:, None] if limit.dim() else limit))
    share = near.sum(-1) / conf[:, None].sum(-1).clamp_min(1)  # (C, P, ...)
    agree = (share >= min_agreement) & (conf[:, None].sum(-1) > 0)
    # the pair itself must agree; ties go to the pair with the smaller mean error of its agreeing views
    pair_ok = (agree.gather(0, _pair_index(pairs[:, 0], agree)).squeeze(0)
               & agree.gather(0, _pair_index(pairs[:, 1], agree)).squeeze(0))  # (P, ...)
    count = agree.sum(0).to(uv.dtype)  # (P, ...)
    mean_err = (torch.where(near, error, torch.zeros_like(error)).sum((0, -1))
                / near.sum((0, -1)).clamp_min(1))  # (P, ...)
    rank = torch.where(pair_ok, count - mean_err / (mean_err.max() + 1.0), torch.full_like(count, -1.0))
    best = rank.argmax(0)  # (...)
    chosen = agree.gather(1, best[None, None].expand(C, 1, *best.shape)).squeeze(1)  # (C, ...)
    return chosen & (rank.amax(0) >= 0)[None]


def _pair_index(view: Tensor, agree: Tensor) -> Tensor:
    """Index ``(1, P, ...)`` into ``agree (C, P, ...)``'s dim 0 picking each pair's ``view (P,)``."""
    return view.reshape(1, -1, *([1] * (agree.dim() - 2))).expand(1, *agree.shape[1:])


def _reprojection_error(rig, points: Tensor, uv: Tensor) -> Tensor:
    """``(..., K, 3)`` points, ``(C, ..., K, 2)`` pixels -> ``(C, ..., K)`` distances (NaN where a point is NaN or
    behind a camera)."""
    proj, _ = rig.project(torch.nan_to_num(points))
    inside = rig.in_lens_model(torch.nan_to_num(points)) & torch.isfinite(points).all(-1)
    err = (proj - uv).norm(dim=-1)
    return torch.where(inside, err, torch.full_like(err, float("nan")))
