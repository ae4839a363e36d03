"""Binary shape-from-silhouette: a voxel is occupied when every camera that sees it sees foreground there.

The baseline the probabilistic grid and the hull are compared with: silhouettes by thresholding the
background model's squared Mahalanobis distance, intersected over the cameras through the same
voxel -> pixel lookup.
"""

from __future__ import annotations

import torch
from torch import nn

from torchtrack.checks import check_shape
from torchtrack.occupancy.bayes import Occupancy
from torchtrack.occupancy.grid import GridSpec, VoxelLookup


def carve(masks: torch.Tensor, lookup: VoxelLookup, min_views: int) -> torch.Tensor:
    """Silhouette intersection.

    Args:
        masks: (B, C, H, W) bool foreground silhouettes.
        lookup: the grid's voxel -> pixel table.
        min_views: a voxel must be seen by at least this many cameras.

    Returns:
        (B, V) bool: seen by >= min_views cameras and foreground in all of those.
    """
    B, C = masks.shape[:2]
    flat = masks.reshape(B, C, -1)
    candidates = (lookup.num_views >= min_views).nonzero()[:, 0]  # (V0,)
    out = torch.zeros(B, lookup.num_views.shape[0], dtype=torch.bool, device=masks.device)
    # Progressive carving: each camera tests only the voxels the previous cameras kept. The loops over frames
    # and cameras are deliberate: the surviving set shrinks fast (to the body's few thousand voxels after
    # two or three views), which makes this several times faster than one dense (B, C, V) gather.
    for b in range(B):
        alive = candidates
        for c in range(C):
            idx = lookup.pixel_index[c, alive]  # (n,) -1 where camera c does not see the voxel
            alive = alive[(idx < 0) | flat[b, c, idx.clamp(min=0)]]
        out[b, alive] = True
    return out


class SilhouetteCarving(nn.Module):
    """Shape-from-silhouette over ``spec`` with silhouettes from a background model."""

    def __init__(self, rig: nn.Module, spec: GridSpec, background: nn.Module, threshold: float | None = None,
                 min_views: int | None = None) -> None:
        super().__init__()
        from torchtrack.background import FOREGROUND_MAHALANOBIS2

        self.spec = spec
        self.lookup = VoxelLookup(rig, spec)
        self.background = background
        self.threshold = FOREGROUND_MAHALANOBIS2 if threshold is None else float(threshold)
        self.min_views = rig.num_cameras if min_views is None else int(min_views)
        self.image_size_wh = tuple(int(v) for v in rig.image_size_wh[0])

    def masks(self, images: torch.Tensor) -> torch.Tensor:
        """(B, C, 3, H, W) RGB -> (B, C, H, W) bool foreground (NaN pixels are foreground: no veto)."""
        W, H = self.image_size_wh
        check_shape(images, ("B", None, 3, H, W), "images")
        d2 = self.background.mahalanobis2(images)
        return (d2 > self.threshold) | torch.isnan(d2)

    def forward(self, images: torch.Tensor) -> Occupancy:
        """Occupancy as log-odds of +-inf (P = 1 inside the carved hull, 0 elsewhere)."""
        occ = carve(self.masks(images), self.lookup, self.min_views)
        inf = torch.tensor(float("inf"), device=occ.device)
        return Occupancy(torch.where(occ, inf, -inf), self.lookup.num_views >= self.min_views, self.spec)
