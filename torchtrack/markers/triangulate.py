"""Robust triangulation of labelled markers from their candidate detections (several per view, some false).

Per frame and marker: every pair of candidates in two views gives a hypothesis (the linear two-view triangulation
of kornia), each view then votes for it where one of its candidates reprojects within ``inlier_px``; the
hypothesis with the most views (then the least reprojection error) is triangulated again from all of them (the
linear n-view solution, a least-squares SVD). Fewer than two agreeing views: NaN. Batched over frames and markers.
"""

from __future__ import annotations

import itertools
import math

import torch
from kornia.geometry.epipolar import triangulate_points

from torchtrack.checks import check_shape

__all__ = ["triangulate_candidates"]


def _project(P: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """(C, 3, 4), (..., 3) -> (C, ..., 2) pinhole pixels."""
    h = torch.cat([X, torch.ones_like(X[..., :1])], -1)
    y = torch.einsum("cij,...j->c...i", P, h)
    return y[..., :2] / y[..., 2:3]


def triangulate_candidates(detections: torch.Tensor, P: torch.Tensor, inlier_px: float = 10.0, chunk: int = 64
                           ) -> tuple[torch.Tensor, torch.Tensor]:
    """Markers from candidate detections (module docstring).

    Args:
        detections: (T, C, M, K, 2) candidates in pinhole pixels
            (:func:`~torchtrack.tracking.epipolar.pinhole_pixels`), NaN where none.
        P: (C, 3, 4) the cameras' pinhole projections.
        inlier_px: a view agrees with a point where one of its candidates lies within this of the point's
            projection.
        chunk: frames solved at once.

    Returns:
        (T, M, 3) points (NaN where fewer than two views agree) and (T, M) how many views agree.
    """
    check_shape(detections, ("T", P.shape[0], "M", "K", 2), "detections")
    T, C, M, K, _ = detections.shape
    P = P.to(detections)
    if T > chunk:  # bounded memory: the hypotheses' distances are (C, frames, M, H, K)
        parts = [triangulate_candidates(detections[t:t + chunk], P, inlier_px) for t in range(0, T, chunk)]
        return torch.cat([x for x, _ in parts]), torch.cat([v for _, v in parts])
    z = detections.permute(0, 2, 1, 3, 4)  # (T, M, C, K, 2)
    # every pair of views (i < j) and of their candidates, one linear two-view triangulation each
    ii, jj = (torch.tensor(v, device=z.device) for v in zip(*itertools.combinations(range(C), 2)))
    S = ii.numel()
    a = z[:, :, ii, :, None].expand(T, M, S, K, K, 2).reshape(T, M, S, K * K, 2)
    b = z[:, :, jj, None, :].expand(T, M, S, K, K, 2).reshape(T, M, S, K * K, 2)
    ok = torch.isfinite(a).all(-1) & torch.isfinite(b).all(-1)
    X = triangulate_points(P[ii].expand(T, M, S, 3, 4), P[jj].expand(T, M, S, 3, 4), torch.nan_to_num(a),
                           torch.nan_to_num(b))  # (T, M, S, K*K, 3)
    X = torch.where(ok[..., None], X, math.nan).reshape(T, M, S * K * K, 3)  # (T, M, H, 3)
    # each view's nearest candidate to each hypothesis's projection
    y = _project(P, torch.nan_to_num(X))  # (C, T, M, H, 2)
    cand = z.permute(2, 0, 1, 3, 4)[:, :, :, None]  # (C, T, M, 1, K, 2)
    dist = (y[..., None, :] - cand).norm(dim=-1).nan_to_num(math.inf).amin(-1)  # (C, T, M, H)
    dist = torch.where(torch.isfinite(X).all(-1)[None], dist, math.inf)
    inlier = dist < inlier_px
    votes = inlier.sum(0)  # (T, M, H)
    err = torch.where(inlier, dist, 0.0).sum(0)
    score = votes.to(err) * 1e6 - err
    best = score.argmax(-1)  # (T, M)
    views = votes.gather(-1, best[..., None])[..., 0]  # (T, M)
    agree = inlier.gather(-1, best[None, ..., None].expand(C, T, M, 1))[..., 0]  # (C, T, M)
    X0 = X.gather(2, best[..., None, None].expand(T, M, 1, 3))[:, :, 0]  # (T, M, 3)
    # every agreeing view's nearest candidate, then the linear n-view triangulation
    y0 = _project(P, torch.nan_to_num(X0))  # (C, T, M, 2)
    d = (y0[..., None, :] - z.permute(2, 0, 1, 3, 4)).norm(dim=-1).nan_to_num(math.inf)  # (C, T, M, K)
    pick = d.argmin(-1)  # (C, T, M)
    uv = z.permute(2, 0, 1, 3, 4).gather(3, pick[..., None, None].expand(C, T, M, 1, 2))[..., 0, :]  # (C, T, M, 2)
    rows = torch.stack([uv[..., 0, None] * P[:, None, None, 2] - P[:, None, None, 0],
                        uv[..., 1, None] * P[:, None, None, 2] - P[:, None, None, 1]], -2)  # (C, T, M, 2, 4)
    rows = torch.where(agree[..., None, None], torch.nan_to_num(rows), 0.0)
    A = rows.permute(1, 2, 0, 3, 4).reshape(T, M, 2 * C, 4)
    A = A / A.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    V = torch.linalg.svd(A)[2]  # (T, M, 4, 4)
    h = V[..., -1, :]
    Xn = h[..., :3] / h[..., 3:4]
    good = (views >= 2) & (h[..., 3].abs() > 1e-12)
    return torch.where(good[..., None], Xn, math.nan), torch.where(good, views, 0)
