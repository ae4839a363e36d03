"""Regular voxel grids and the voxel -> pixel lookup of a static rig.

Voxel ``v`` of a grid of shape (nx, ny, nz) has integer coordinates (ix, iy, iz) with
``v = (ix * ny + iy) * nz + iz`` and centre ``lower + (i + 0.5) * voxel_size``.
"""

from __future__ import annotations

import copy
import logging
import math
from dataclasses import dataclass

import torch
from torch import nn

from torchtrack.checks import InputError

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GridSpec:
    """An axis-aligned box of cubic voxels.

    Attributes:
        lower_m, upper_m: box corners (world, metres); the upper side is rounded up to whole voxels.
        voxel_size_m: voxel edge length.
    """

    lower_m: tuple[float, float, float]
    upper_m: tuple[float, float, float]
    voxel_size_m: float

    def __post_init__(self) -> None:
        if not self.voxel_size_m > 0:
            raise InputError(f"voxel_size_m must be positive, got {self.voxel_size_m}")
        if any(not (u > l) for l, u in zip(self.lower_m, self.upper_m)):
            raise InputError(f"grid: upper_m {self.upper_m} must exceed lower_m {self.lower_m} on every axis")

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(max(1, math.ceil((u - l) / self.voxel_size_m - 1e-9))
                     for l, u in zip(self.lower_m, self.upper_m))  # type: ignore[return-value]

    def covered_box(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """The box the voxels cover: ``lower_m`` to ``lower_m + shape * voxel_size_m`` (``upper_m`` rounded up
        to whole voxels)."""
        return self.lower_m, tuple(lo + n * self.voxel_size_m for lo, n in zip(self.lower_m, self.shape))

    @property
    def num_voxels(self) -> int:
        nx, ny, nz = self.shape
        return nx * ny * nz

    def centres(self, dtype: torch.dtype = torch.float32, device: torch.device | None = None) -> torch.Tensor:
        """(V, 3) voxel centres in world metres."""
        axes = [l + (torch.arange(n, dtype=torch.float64, device=device) + 0.5) * self.voxel_size_m
                for l, n in zip(self.lower_m, self.shape)]
        grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1)  # (nx, ny, nz, 3)
        return grid.reshape(-1, 3).to(dtype)

    def index_of(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 3) world points -> flat voxel indices (N,) int64 and an inside mask (N,)."""
        lower = torch.tensor(self.lower_m, dtype=points.dtype, device=points.device)
        ijk = torch.floor((points - lower) / self.voxel_size_m).long()  # (N, 3)
        dims = torch.tensor(self.shape, device=points.device)
        inside = ((ijk >= 0) & (ijk < dims)).all(dim=-1)
        ijk = torch.minimum(ijk.clamp(min=0), dims - 1)
        return (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2], inside


def format_point(p: tuple[float, ...], digits: int = 3) -> str:
    """``(x, y, z)`` rounded for messages: ``(-1.2, -1.2, 0)``, not ``(-1.1999999999999997, ...)``."""
    return "(" + ", ".join(f"{round(float(v), digits):g}" for v in p) + ")"


def capture_views(num_cameras: int, model: str = "bayes") -> int:
    """How many cameras must see a point for it to be in the capture volume by default.

    The Bayesian grid: half of them, at least three (all of a rig of three or fewer). More would shrink the volume
    to what the narrowest views share, where a subject who walks towards the edge of the area (or a starfish's hand)
    is lost; fewer than three leaves the two-view voxels, whose silhouette cones cross far from the body, and on a
    large ring three of eight views let the phantom volume of a few near-parallel cones pull the track. The colour
    hull and silhouette carving: all of them (fewer cost the hull much of its accuracy). docs/results.md, "The
    capture volume", has the figures for both."""
    if num_cameras < 1:
        raise InputError(f"capture_views: need at least one camera, got {num_cameras}")
    if model != "bayes":  # the hull and silhouette carving
        return num_cameras
    return max(min(num_cameras, 3), -(-num_cameras // 2))


def grid_from_rig(rig: nn.Module, voxel_size_m: float, floor_z_m: float = 0.0, top_z_m: float = 2.1,
                  min_views: int | None = None, margin_m: float = 0.0, search_radius_m: float = 5.0) -> GridSpec:
    """The box over the floor region that at least ``min_views`` cameras see (default: all of them).

    A floor point counts as seen by a camera when both it and the point ``top_z_m`` above it project
    inside the image. The box spans the seen region in x and y (plus ``margin_m``) and
    ``[floor_z_m, top_z_m]`` in z.
    """
    C = rig.num_cameras
    need = C if min_views is None else int(min_views)
    step = 0.05
    n = int(2 * search_radius_m / step) + 1
    xs = torch.linspace(-search_radius_m, search_radius_m, n, dtype=torch.float64)
    gx, gy = torch.meshgrid(xs, xs, indexing="ij")
    pts = torch.stack([gx, gy, torch.full_like(gx, floor_z_m)], -1).reshape(-1, 3)  # (n*n, 3)
    top = pts.clone()
    top[:, 2] = top_z_m
    rig64 = copy.deepcopy(rig).double()  # nn.Module.double() works in place: never convert the caller's rig
    _, v0 = rig64.project(pts.to(rig64.K.device))
    _, v1 = rig64.project(top.to(rig64.K.device))
    seen = (v0 & v1).sum(dim=0).cpu() >= need  # (n*n,)
    if not bool(seen.any()):
        raise InputError(f"no floor region between z={floor_z_m} and {top_z_m} m is seen by {need} of the "
                         f"{C} cameras; pass the volume explicitly (lower_m/upper_m)")
    sel = pts[seen]
    lo = sel[:, :2].min(0).values - margin_m
    hi = sel[:, :2].max(0).values + margin_m
    spec = GridSpec((float(lo[0]), float(lo[1]), floor_z_m), (float(hi[0]), float(hi[1]), top_z_m), voxel_size_m)
    log.info("grid from the rig's common view (%d of %d cameras): %s to %s m, %s voxels of %.3f m", need, C,
             format_point(spec.lower_m), format_point(spec.upper_m), "x".join(map(str, spec.shape)), voxel_size_m)
    return spec


class VoxelLookup(nn.Module):
    """For a static rig and grid: the pixel each voxel centre projects to, in every camera.

    Buffers:
        pixel_index: (C, V) int64 flat index ``v * W + u`` of the nearest pixel into that camera's (H, W)
            image, or -1 where the centre is behind the camera or outside the image.
        num_views: (V,) int64 number of cameras that see the voxel centre.
        flat_index: (C * V,) int64 index into the concatenation of all cameras' (H * W) pixels plus one
            trailing "fill" entry, which unseen voxels point to (one gather per voxel and camera, no masking).
    """

    pixel_index: torch.Tensor
    num_views: torch.Tensor
    flat_index: torch.Tensor

    def __init__(self, rig: nn.Module, spec: GridSpec, chunk: int = 1 << 20) -> None:
        super().__init__()
        self.spec = spec
        C, V = rig.num_cameras, spec.num_voxels
        centres = spec.centres(dtype=rig.K.dtype, device=rig.K.device)
        index = torch.empty(C, V, dtype=torch.int64, device=rig.K.device)
        wh = rig.image_size_wh.to(rig.K.device)  # (C, 2)
        for s in range(0, V, chunk):
            uv, valid = rig.project(centres[s:s + chunk])  # (C, n, 2), (C, n)
            px = torch.round(uv).long()
            flat = px[..., 1] * wh[:, 0:1] + px[..., 0]  # (C, n)
            index[:, s:s + chunk] = torch.where(valid, flat, torch.full_like(flat, -1))
        self.register_buffer("pixel_index", index)
        self.register_buffer("num_views", (index >= 0).sum(dim=0))
        HW = int(wh[0, 0] * wh[0, 1])
        if bool((wh[:, 0] * wh[:, 1] != HW).any()):
            raise InputError("VoxelLookup needs one image size for all cameras; got "
                             + ", ".join(f"{n} {tuple(s.tolist())}" for n, s in zip(rig.names, wh)))
        offsets = torch.arange(C, device=index.device)[:, None] * HW  # (C, 1)
        self.register_buffer("flat_index", torch.where(index >= 0, index + offsets, C * HW).reshape(-1),
                             persistent=False)
        for c in range(C):
            if not bool((index[c] >= 0).any()):
                log.warning("camera %s sees none of the voxel grid %s to %s m", rig.names[c],
                            format_point(spec.lower_m), format_point(spec.upper_m))

    def gather(self, per_pixel: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
        """Per-pixel values at every voxel.

        Args:
            per_pixel: (B, C, H, W) with H, W the cameras' common image size.

        Returns:
            (B, C, V), ``fill`` where the camera does not see the voxel.
        """
        B, C = per_pixel.shape[:2]
        flat = torch.cat([per_pixel.reshape(B, -1), per_pixel.new_full((B, 1), fill)], dim=1)  # (B, C*H*W + 1)
        return flat[:, self.flat_index].view(B, C, -1)

    def gather_sum(self, per_pixel: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) -> (B, V): the sum over cameras of the values at each voxel's pixel (0 where unseen)."""
        return self.gather(per_pixel, fill=0.0).sum(dim=1)
