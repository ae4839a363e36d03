"""Occupancy quality against a ground-truth body: IoU and false connected components."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from torchtrack.occupancy.grid import GridSpec


def inside_ellipsoids(points: torch.Tensor, centres: torch.Tensor, R_world: torch.Tensor, semi_axes: torch.Tensor,
                      chunk: int = 1 << 18) -> torch.Tensor:
    """Points inside any ellipsoid: (p - c)^T R diag(1/a^2) R^T (p - c) <= 1.

    Args:
        points: (N, 3); centres: (K, 3); R_world: (K, 3, 3) ellipsoid axes as columns; semi_axes: (K, 3).

    Returns:
        (N,) bool.
    """
    out = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
    for s in range(0, points.shape[0], chunk):
        d = points[s:s + chunk, None, :] - centres[None]  # (n, K, 3)
        local = torch.einsum("nkj,kji->nki", d, R_world) / semi_axes[None]  # (n, K, 3)
        out[s:s + chunk] = ((local ** 2).sum(-1) <= 1.0).any(dim=1)
    return out


def iou(pred: torch.Tensor, truth: torch.Tensor) -> float:
    """Intersection over union of two boolean voxel sets of the same shape."""
    inter = (pred & truth).sum().item()
    union = (pred | truth).sum().item()
    return inter / union if union else 1.0


@dataclass(frozen=True)
class FalseComponents:
    """Connected components of predicted voxels that touch no ground-truth voxel (26-connectivity).

    Attributes:
        count: number of such components.
        largest_voxels: voxels in the largest one; largest_m3 its volume; largest_extent_m its bounding-box
            diagonal (a human-size component would be > ~1 m).
    """

    count: int
    largest_voxels: int
    largest_m3: float
    largest_extent_m: float


def false_components(pred: torch.Tensor, truth: torch.Tensor, spec: GridSpec, tolerance_voxels: int = 2
                     ) -> FalseComponents:
    """Components of ``pred`` farther than ``tolerance_voxels`` from any ``truth`` voxel.

    Args:
        pred, truth: (V,) bool over ``spec``.
    """
    from scipy import ndimage

    shape = spec.shape
    p = pred.reshape(shape).cpu().numpy()
    t = truth.reshape(shape).cpu().numpy()
    near = ndimage.binary_dilation(t, iterations=tolerance_voxels) if t.any() else t
    labels, n = ndimage.label(p, structure=np.ones((3, 3, 3)))
    touching = np.unique(labels[near & p])
    best = (0, 0.0)
    count = 0
    for lab, sl in enumerate(ndimage.find_objects(labels), start=1):
        if sl is None or lab in touching:
            continue
        count += 1
        size = int((labels[sl] == lab).sum())
        if size > best[0]:
            ext = np.array([s.stop - s.start for s in sl]) * spec.voxel_size_m
            best = (size, float(np.linalg.norm(ext)))
    return FalseComponents(count, best[0], best[0] * spec.voxel_size_m ** 3, best[1])
