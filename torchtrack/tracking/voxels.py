"""A frame's 3D observation as data: the weighted, coloured voxel set the tracker fits (:class:`VoxelObservation`)
and each camera's coarse foreground (:class:`ViewSilhouettes`). No observation model here
(:mod:`torchtrack.tracking.observation` makes them), so that the per-frame core imports none.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import nn

from torchtrack.blobs.model import SURFACE_MAHALANOBIS2
from torchtrack.checks import InputError

#: ``Observer(silhouettes=True)``: each camera's foreground is kept at cells of this many pixels (of the processing
#: size) a side, a few kilobytes a frame.
SILHOUETTE_CELL_PX = 4


@dataclass(frozen=True)
class ViewSilhouettes:
    """Each camera's foreground of one frame at coarse cells, with the cameras that saw it: what the start search
    compares a body's projection with, camera by camera (:func:`~torchtrack.tracking.search.two_way_score`).

    Attributes:
        fg: (C, h, w) bool, cells whose pixels are mostly foreground (the grid's per-pixel evidence > 0).
        cell_px: the cells' side in pixels of ``rig``'s images.
        rig: the CameraRig at the processing size.
    """

    fg: torch.Tensor
    cell_px: int
    rig: nn.Module

    @classmethod
    def from_evidence(cls, evidence: torch.Tensor, rig: nn.Module, cell_px: int = SILHOUETTE_CELL_PX
                      ) -> ViewSilhouettes:
        """From one frame's per-pixel log ratio ``(C, H, W)`` (> 0: foreground)."""
        fg = (evidence > 0).float()[:, None]
        return cls(F.avg_pool2d(fg, cell_px, ceil_mode=True)[:, 0] > 0.5, cell_px, rig)


@dataclass(frozen=True)
class VoxelObservation:
    """Occupied voxels of one frame (N voxels, C views).

    Attributes:
        points: (N, 3) centres (m). sizes: (N,) edges (m). weights: (N,) EM weights.
        colours: (N, C, 3) per-view colour (gain-normalised YUV), NaN where the view does not see the voxel.
        cameras_valid: (C,) bool, the cameras whose frame was readable.
        cell_m: the cell size the voxels were merged per (:meth:`pooled`), 0 for the model's own voxels.
        observed_voxels: how many of the model's voxels were merged into these (-1: not merged).
        camera_centres: (C, 3) the cameras' centres in the world frame, or None (then the tracker cannot
            explain ghost voxels away: :mod:`torchtrack.tracking.ghosts`).
        volume_m: the box the observation model looks in, (lower, upper) corners (m), or None (unbounded):
            nothing outside it is observed, so a body part that reaches out of it shows only its inside part
            (:meth:`outside`).
        silhouettes: each camera's foreground (:class:`ViewSilhouettes`), or None.
    """

    points: torch.Tensor
    sizes: torch.Tensor
    weights: torch.Tensor
    colours: torch.Tensor
    cameras_valid: torch.Tensor
    cell_m: float = 0.0
    observed_voxels: int = -1
    camera_centres: torch.Tensor | None = None
    volume_m: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    silhouettes: ViewSilhouettes | None = None

    @property
    def num_voxels(self) -> int:
        return int(self.points.shape[0])

    @property
    def num_observed(self) -> int:
        """Voxels the observation model gave (before any merging per cell)."""
        return self.observed_voxels if self.observed_voxels >= 0 else self.num_voxels

    def height_span(self) -> tuple[float, float]:
        """(soles, top): the 0.2 % and 99.8 % height quantiles of the voxels' bottoms and tops (m). Each voxel's
        own extent counts: the hull's coarse interior cubes (12 cm) would put the soles 5 cm low at their
        centres; the quantiles leave out a few stray voxels."""
        z, half = self.points[:, 2], 0.5 * self.sizes.to(self.points.dtype)
        return float(torch.quantile(z - half, 0.002)), float(torch.quantile(z + half, 0.998))

    def without_floor_band(self, band_m: float) -> VoxelObservation:
        """The voxels whose centres lie less than ``band_m`` above the observed volume's floor given no weight: a
        floor shadow that the background takes for foreground in every view is a thin ghost volume there, which
        pulls the feet into the floor (``TrackerConfig.floor_band_m``). The voxels stay (the body's height is still
        measured from them). As it is where the volume is unknown, ``band_m`` is 0, or it would leave no weight."""
        if not band_m > 0 or self.volume_m is None or self.num_voxels == 0:
            return self
        keep = self.points[:, 2] >= self.volume_m[0][2] + band_m
        w = self.weights * keep.to(self.weights.dtype)
        # the weights as they were where the band holds every voxel (chosen on the device: no synchronisation)
        return replace(self, weights=torch.where((w > 0).any(), w, self.weights))

    def volume_m3(self) -> float:
        return float((self.sizes.double() ** 3).sum())

    def outside(self, mean: torch.Tensor, cov: torch.Tensor) -> torch.Tensor:
        """(K,) the share of each blob's solid ellipsoid (``mean (K, 3)``, ``cov (K, 3, 3)``) out of the volume's
        sides or top (:func:`share_outside`); zeros when the volume is unknown."""
        if self.volume_m is None:
            return mean.new_zeros(mean.shape[0])
        lower, upper = (mean.new_tensor(c) for c in self.volume_m)
        return share_outside(mean, cov, lower, upper)

    def parts(self, cell_m: float = 0.06) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The occupied volume's connected parts: each voxel marks the cells of a ``cell_m`` lattice its box
        overlaps, and marked cells that touch (26-neighbours) are one part. Voxels less than a cell apart are
        always one part, two cells or more apart always two (between, it depends on where the lattice falls):
        two people, or a person and phantom volume. Returns, on the CPU, ``(N,)`` each voxel's part, numbered
        largest first, and per part its volume ``(K,)`` (m^3) and its ``(K, 2)`` height span (bottom and top of
        its voxels, m).

        The labelling is scipy's (:func:`scipy.ndimage.label`), on the CPU: the tracker asks on each frame until
        it has started."""
        import numpy as np
        from scipy import ndimage

        if self.num_voxels == 0:
            return (torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.float64),
                    torch.zeros(0, 2, dtype=torch.float64))
        pts = self.points.detach().double().cpu().numpy()
        half = 0.5 * self.sizes.detach().double().cpu().numpy()[:, None]
        # the cells each voxel's box overlaps; a box that ends on a cell's side (within float32's rounding of a
        # lattice-aligned grid) does not reach into the next
        lo = np.floor((pts - half) / cell_m + 1e-3).astype(np.int64)
        hi = np.floor((pts + half) / cell_m - 1e-3).astype(np.int64)
        centre = np.floor(pts / cell_m).astype(np.int64)  # the voxel's own cell, even for a box of no size
        lo, hi = np.minimum(lo, centre), np.maximum(hi, centre)
        origin = lo.min(0)
        lo, hi, centre = lo - origin, hi - origin, centre - origin
        grid = np.zeros(hi.max(0) + 1, dtype=bool)
        for dx, dy, dz in np.ndindex(*((hi - lo).max(0) + 1)):  # a few offsets: voxels span at most a few cells
            cell = lo + (dx, dy, dz)
            ok = (cell <= hi).all(1)
            grid[tuple(cell[ok].T)] = True
        labels, n = ndimage.label(grid, structure=np.ones((3, 3, 3), dtype=bool))
        part = labels[tuple(centre.T)] - 1  # (N,) 0-based
        vol = np.bincount(part, weights=(2 * half[:, 0]) ** 3, minlength=n)
        bottom = np.full(n, np.inf)
        top = np.full(n, -np.inf)
        np.minimum.at(bottom, part, pts[:, 2] - half[:, 0])
        np.maximum.at(top, part, pts[:, 2] + half[:, 0])
        order = np.argsort(-vol, kind="stable")
        rank = np.empty(n, dtype=np.int64)
        rank[order] = np.arange(n)
        return (torch.from_numpy(rank[part]), torch.from_numpy(vol[order]),
                torch.from_numpy(np.stack([bottom[order], top[order]], 1)))

    def split(self, max_m: float) -> VoxelObservation:
        """Voxels larger than ``max_m`` cut into ``n^3`` equal children (``n = ceil(size / max_m)``), each with
        ``1 / n^3`` of the weight and the parent's colours; smaller ones come back as they are. For the bone fit
        (:meth:`MarkerlessTracker._fit_bone_lengths`): EM gives each voxel to one blob, and a hull's 12 cm
        interior cube that spans two blobs moves the one it goes to."""
        if not max_m > 0:
            raise InputError(f"VoxelObservation.split: the size must be > 0, got {max_m}")
        n = torch.ceil(self.sizes / max_m - 1e-6).clamp(min=1).long()  # within rounding of max_m: kept whole
        if self.num_voxels == 0 or int(n.max()) <= 1:
            return self
        parts = []
        for k in n.unique().tolist():
            sel = n == k
            pts, sizes, w, col = self.points[sel], self.sizes[sel], self.weights[sel], self.colours[sel]
            if k > 1:
                g = (torch.arange(k, dtype=pts.dtype, device=pts.device) + 0.5) / k - 0.5  # child centres / size
                offsets = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(1, -1, 3)  # (1, k^3, 3)
                pts = (pts[:, None, :] + sizes[:, None, None] * offsets).reshape(-1, 3)
                sizes = (sizes / k).repeat_interleave(k ** 3)
                w = (w / k ** 3).repeat_interleave(k ** 3)
                col = col.repeat_interleave(k ** 3, dim=0)
            parts.append((pts, sizes, w, col))
        return replace(self, points=torch.cat([p[0] for p in parts]), sizes=torch.cat([p[1] for p in parts]),
                       weights=torch.cat([p[2] for p in parts]), colours=torch.cat([p[3] for p in parts]),
                       cell_m=0.0, observed_voxels=self.num_observed)

    def pooled(self, cell_m: float) -> VoxelObservation:
        """Voxels merged per cell of a ``cell_m`` lattice (for a cheaper EM): weight-averaged centres and
        colours (per view, over the voxels that view sees), summed weights, volume-equivalent sizes.
        Voxels already merged per ``cell_m`` come back as they are."""
        if not cell_m > 0:
            raise InputError(f"VoxelObservation.pooled: the cell size must be > 0, got {cell_m}")
        if cell_m == self.cell_m:
            return self
        key3 = torch.floor(self.points / cell_m).long()  # (N, 3)
        if key3.shape[0] == 0:
            return self
        key3 = key3 - key3.amin(0)
        span = key3.amax(0) + 1
        key = (key3[:, 0] * span[1] + key3[:, 1]) * span[2] + key3[:, 2]
        cells, inv = torch.unique(key, return_inverse=True)
        M = cells.shape[0]
        w = self.weights
        W = w.new_zeros(M).index_add_(0, inv, w)
        pts = self.points.new_zeros(M, 3).index_add_(0, inv, w[:, None] * self.points) / W.clamp(min=1e-30)[:, None]
        vol = self.sizes.new_zeros(M).index_add_(0, inv, self.sizes ** 3)
        seen = torch.isfinite(self.colours).all(-1)  # (N, C)
        cw = w[:, None] * seen  # (N, C)
        csum = self.colours.new_zeros(M, *self.colours.shape[1:]).index_add_(
            0, inv, cw[..., None] * torch.nan_to_num(self.colours))
        cwt = cw.new_zeros(M, cw.shape[1]).index_add_(0, inv, cw)
        colours = torch.where(cwt[..., None] > 0, csum / cwt.clamp(min=1e-30)[..., None], torch.nan)
        return VoxelObservation(pts, vol ** (1.0 / 3.0), W, colours, self.cameras_valid, cell_m, self.num_observed,
                                self.camera_centres, self.volume_m, self.silhouettes)


def share_outside(mean: torch.Tensor, cov: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor) -> torch.Tensor:
    """(..., K) the share of each solid ellipsoid (``mean (..., K, 3)``, ``cov (..., K, 3, 3)`` of a uniform
    ellipsoid) that lies out of the box ``lower``, ``upper`` (``(3,)`` or ``(..., 1, 3)``; +-inf: unbounded) through
    its sides or top (the floor is no cut: nothing stands below it).

    A plane at signed distance ``d`` (in units of the ellipsoid's half width along its normal, positive towards the
    centre) cuts off the share ``(1 - d)^2 (2 + d) / 4`` of it (a ball's cap under the affine map); the caps of the
    five planes are summed (their overlaps at the box's edges counted twice)."""
    half = (SURFACE_MAHALANOBIS2 * torch.diagonal(cov, dim1=-2, dim2=-1)).clamp(min=1e-12).sqrt()  # (..., K, 3)
    d = torch.cat([((mean - lower) / half)[..., :2], (upper - mean) / half], -1).clamp(-1.0, 1.0)  # (..., K, 5)
    return ((1 - d) ** 2 * (2 + d) / 4).sum(-1).clamp(max=1.0)
