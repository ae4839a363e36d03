"""Ghost voxels: occupied voxels that the predicted body already explains in every view.

A visual hull (and a Bayesian occupancy grid, which fuses the same silhouettes) from few cameras holds *ghost*
volumes: regions every view sees as foreground only because each view's ray through them passes through some
real part of the body elsewhere. With 4 cameras 90 deg apart, two legs on the diagonal give two more leg-sized
ghosts on the other diagonal; EM hands their voxels to the nearest blobs, which pulls the legs, arms and trunk.

The tracker knows where the body should be (the blobs regenerated from the predicted pose, eq. 17-18), so it can
explain a voxel away: a voxel outside the predicted body (every blob's ellipsoid grown by ``inside_scale``) is a
ghost when, in every view that sees it, the ray from the camera through its centre passes through the predicted
body (an ellipsoid grown by ``cover_scale``): that view's foreground there is accounted for without it. A real
voxel the prediction misses (a limb that moved faster than predicted) survives as long as one view sees it against
no predicted body. Only blobs with voxels of their own may explain a ray (``covers``: the tracker passes those its
last accepted frame filled), so a limb the views lost, e.g. a stance leg a video's background holds, explains
nothing away. Nor does a blob explain the voxels of its own near shell (inside its ellipsoid grown by
``self_scale``): an arm raised past its prediction and seen by cameras that look down along it has every view's
ray through the predicted arm, and would otherwise lose the voxels it has to follow (as the Pose2Sim demo's raised
right arm did without it). The tracker lowers ghosts' EM weights (``TrackerConfig.ghost_weight``); what that does
with 4 and 8 cameras: ``scripts/eval_tracking.py``, docs/results.md, "Tracker settings".

Limits. The test trusts the prediction: a prediction that sits on the ghosts explains the real voxels away
and confirms itself (the tracker's re-acquisition, after its divergence test, searches without it). Each voxel
is tested at its centre, so a hull's coarse interior cube or a merged cell is kept or lowered whole. The inside
margin is relative, so thin limbs get a few millimetres of it. Visibility is not modelled: a view "sees" every
voxel inside its image. The shell (``self_scale``) trades the other way: a shell too wide keeps a limb's own
ghosts, which then pull it (wider shells lost the synthetic 4-camera walk's right wrist; docs/results.md,
"Tracker settings").

The start's and re-acquisition's comparison of finished bodies on few views' voxels runs the same test on each body
against itself (:func:`~torchtrack.tracking.search.two_way_score`): its ghosts count neither for it nor against it.

This is this project's extension to de Bem's and Caillette's EM, not part of either paper: both tracked from
enough cameras that ghosts were small.
"""

from __future__ import annotations

import torch

from torchtrack.blobs.em import mahalanobis2
from torchtrack.blobs.model import SURFACE_MAHALANOBIS2 as _SURFACE_M2  # the blobs are uniform solid ellipsoids
from torchtrack.checks import InputError, check_shape


def ghost_voxels(points: torch.Tensor, seen: torch.Tensor, camera_centres: torch.Tensor, mean: torch.Tensor,
                 cov: torch.Tensor, inside_scale: float = 1.15, cover_scale: float = 1.2,
                 covers: torch.Tensor | None = None, self_scale: float = 0.0, chunk: int = 4096,
                 dense: bool | None = None) -> torch.Tensor:
    """Which voxels the predicted body explains away (see the module docstring).

    Args:
        points: (N, 3) voxel centres (m). seen: (N, C) bool, whether camera c sees voxel n (its colour is
            finite and its frame readable). camera_centres: (C, 3) in the world frame.
        mean, cov: (K, 3), (K, 3, 3) the predicted blobs (uniform-ellipsoid covariances).
        inside_scale: a voxel inside any blob's ellipsoid grown by this is never a ghost.
        cover_scale: a ray through any blob's ellipsoid grown by this is explained by the body.
        covers: (K,) bool, the blobs that may explain a ray (default: all); every blob counts for "inside".
        self_scale: a blob does not explain a ray for a voxel inside its ellipsoid grown by this (0: it does;
            only values above ``inside_scale`` act, since voxels inside that are never ghosts).
        chunk: voxels per batch (bounds the (chunk, K, C) temporaries).
        dense: test every voxel of a chunk rather than only the candidates (seen, outside the body): the same
            answer, without the wait for the device that selecting them costs on a GPU (None: dense off the CPU).
        B frames at once (the lockstep tracker's sequences): a leading B on every tensor, each frame's voxels
        against its own cameras and body; padding: NaN points, and cameras that see nothing (``seen`` False).

    Returns:
        ([B,] N) bool. A voxel that no view sees is not a ghost.
    """
    if points.dim() == 2:
        return ghost_voxels(points[None], seen[None], camera_centres[None], mean[None], cov[None], inside_scale,
                            cover_scale, None if covers is None else covers[None], self_scale, chunk, dense)[0]
    B, N = points.shape[:2]
    check_shape(points, (B, N, 3), "points")
    C = camera_centres.shape[1]
    check_shape(seen, (B, N, C), "seen")
    check_shape(camera_centres, (B, C, 3), "camera_centres")
    K = mean.shape[1]
    check_shape(mean, (B, K, 3), "mean")
    check_shape(cov, (B, K, 3, 3), "cov")
    if not (inside_scale > 0 and cover_scale > 0):
        raise InputError(f"ghost_voxels: the scales must be > 0, got {inside_scale} and {cover_scale}")
    if not self_scale >= 0:
        raise InputError(f"ghost_voxels: self_scale must be >= 0 (0: off), got {self_scale}")
    out = torch.zeros(B, N, dtype=torch.bool, device=points.device)
    dense = points.device.type != "cpu" if dense is None else dense
    if covers is not None:
        check_shape(covers, (B, K), "covers")
    if N == 0 or K == 0:
        return out
    cover_k = (torch.ones(B, K, dtype=torch.bool, device=points.device) if covers is None
               else covers.to(device=points.device, dtype=torch.bool))[..., None]  # (B, K, 1)
    # Mahalanobis distances under each blob's covariance (A = cov^-1 = W^T W): a voxel x is inside a blob when
    # |W (x - m)|^2 is small; the ray from a camera c through x passes the blob's mean at the squared
    # distance (c - m)^T A (c - m) - ((c - m)^T A (x - c))^2 / (x - c)^T A (x - c), on the camera's side when the
    # middle term is negative. All about the blobs' centroid, so that float32 keeps its precision however far
    # the world origin lies from the subject.
    dt = points.dtype
    origin = mean.to(dt).mean(1, keepdim=True)  # (B, 1, 3)
    cov = cov.to(dt)
    m, c = mean.to(dt) - origin, camera_centres.to(dt) - origin  # (B, K, 3), (B, C, 3)
    eye = torch.eye(3, dtype=dt, device=points.device).expand_as(cov)
    W = torch.linalg.solve_triangular(torch.linalg.cholesky_ex(cov).L, eye, upper=False)  # (B, K, 3, 3)
    A = W.mT @ W
    d = c[:, None] - m[:, :, None]  # (B, K, C, 3) from each blob's mean to each camera
    v = torch.einsum("bkij,bkcj->bkci", A, d)  # A (c - m)
    dAd = (v * d).sum(-1)  # (B, K, C)
    vc = (v * c[:, None]).sum(-1)  # (B, K, C): (c - m)^T A c
    Wc = torch.einsum("bkij,bcj->bkci", W, c)  # (B, K, C, 3)
    r_in2 = _SURFACE_M2 * inside_scale ** 2
    r_cov2 = _SURFACE_M2 * cover_scale ** 2
    r_self2 = _SURFACE_M2 * self_scale ** 2
    for lo in range(0, N, chunk):
        x, sn = points[:, lo:lo + chunk].to(dt) - origin, seen[:, lo:lo + chunk]
        d2 = mahalanobis2(x, m, cov)  # (B, n, K); NaN (padding) is inside nothing
        inside = (d2 <= r_in2).any(-1)  # (B, n)
        candidate = ~inside & sn.any(-1)  # (B, n)
        if dense:
            along = torch.einsum("bnj,bkcj->bnkc", x, v) - vc[:, None]  # (B, n, K, C)
            y = torch.einsum("bkij,bnj->bnki", W, x)[:, :, :, None] - Wc[:, None]  # (B, n, K, C, 3)
            qq = y.square().sum(-1).clamp(min=1e-30)
            hit = (dAd[:, None] - along.square() / qq <= r_cov2) & (along < 0) & cover_k[:, None]
            if self_scale > 0:
                hit &= (d2 > r_self2)[..., None]
            out[:, lo:lo + chunk] = candidate & (hit.any(2) | ~sn).all(-1)
            continue
        bi, ni = candidate.nonzero(as_tuple=True)
        if bi.numel() == 0:
            continue
        xc = x[bi, ni]  # (M, 3) the candidates, each with its frame's cameras and blobs (bi)
        along = torch.einsum("mj,mkcj->mkc", xc, v[bi]) - vc[bi]  # (c - m)^T A (x - c); < 0: in front of c
        y = torch.einsum("mkij,mj->mki", W[bi], xc)[:, :, None] - Wc[bi]  # (M, K, C, 3): W (x - c)
        qq = y.square().sum(-1).clamp(min=1e-30)  # (x - c)^T A (x - c)
        hit = (dAd[bi] - along.square() / qq <= r_cov2) & (along < 0) & cover_k[bi]  # (M, K, C)
        if self_scale > 0:  # not by the blob whose own shell holds the voxel
            hit &= (d2[bi, ni] > r_self2)[..., None]
        covered = hit.any(1)  # (M, C)
        out[bi, lo + ni] = (covered | ~sn[bi, ni]).all(-1)
    return out
