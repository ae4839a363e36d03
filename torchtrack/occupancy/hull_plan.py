"""The plan of the hierarchical hull: what is fixed for one rig and zone, held as module buffers.

Level 0 projected exactly, the per-voxel quadratic projection model the finer levels read their sample pixels from,
the footprint windows of the early-out (see :mod:`torchtrack.occupancy.hull` for the pattern). Built once from the
rig; ``.to(device)`` moves it with the module that holds it (the rig itself is not kept).
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

from torchtrack.cameras import distortion
from torchtrack.cameras.rig import MIN_DEPTH
from torchtrack.checks import InputError

if TYPE_CHECKING:
    from torchtrack.occupancy.hull import HullConfig

__all__ = ["HullPlan"]

#: Per axis, the children's sample offsets from the parent centre in parent edges, index ``2 s + c`` for sample s
#: of child c: child 0 (centre -1/4) samples at -3/8 and -1/8, child 1 (centre +1/4) at +1/8 and +3/8.
TAU = (-0.375, 0.125, -0.125, 0.375)


class HullPlan(nn.Module):
    """What is fixed for one rig and zone; its tensors are non-persistent buffers (``.to(device)`` moves them).

    Attributes:
        lower (list), lower_t (3,) float64, e0, n0, L, C, H, W: the grids and images.
        idx0: (C, 8, V0) int32 flat level-0 sample indices in the row-offset layout ``(v + c H) W + u`` (one flat
            map of all cameras; 0 where unseen); sees0 (C, V0) bool; ijk0 (V0, 3) int64.
        model: (V0, C * 2 * 13) float64 per level-0 voxel, camera and pixel coordinate: value, gradient (3) and
            Hessian (3 x 3) w.r.t. the world offset (m) of the quadratic fitted (least squares) to the exact
            projections of ``centre + {-h, 0, h}^3``, ``h = 3/8 e0``. model_ok: (C, V0) all 27 in front and
            inside the distortion model's range.
        footprint: per level, the odd max-filter width (px) of the footprint early-out; 1: none.

    Sample tables are (C, 8, V), the voxel index innermost, so ops and the 8-sample reductions run on long rows.
    Keep the float64 buffers in float64 (the module is moved by device, not cast): the model's pixel coordinates
    need its precision.
    """

    def __init__(self, rig: nn.Module, config: HullConfig) -> None:
        super().__init__()
        if config.lower_m is None:
            raise InputError("HullConfig.lower_m / upper_m (the zone of interest) must be set")
        if bool((rig.image_size_wh != rig.image_size_wh[0]).any()):
            raise InputError(f"hierarchical_hull needs cameras of one image size, got {rig.image_size_wh.tolist()}")
        lo = config.lower_m
        self.L, self.e0, self.n0 = config.level0()
        self.C = rig.num_cameras
        self.W, self.H = (int(v) for v in rig.image_size_wh[0].tolist())
        if self.C * self.H * self.W >= 2 ** 31:
            raise InputError("hierarchical_hull: more than 2^31 pixels over all cameras")
        dev = rig.K.device
        self.lower = list(lo)
        buffers = {
            "lower_t": torch.tensor(lo, dtype=torch.float64, device=dev),
            "tau": torch.tensor(TAU, dtype=torch.float64, device=dev)[:, None],  # (4, 1)
            "size_wh": torch.tensor([self.W, self.H], device=dev)[None, :, None, None],  # (1, 2, 1, 1)
            "shift": torch.stack([torch.full((self.C,), 0.5, device=dev),
                                  torch.arange(self.C, device=dev) * self.H + 0.5], -1)[:, :, None],  # (C, 2, 1)
            "child": torch.tensor([[a, b, c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], device=dev)[:, None],
            "neighbours": torch.tensor([[a, b, c] for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)
                                        if (a, b, c) != (0, 0, 0)], device=dev),  # (26, 3)
            "ijk0": torch.stack(torch.meshgrid(*[torch.arange(n, device=dev) for n in self.n0], indexing="ij"),
                                -1).reshape(-1, 3),  # (V0, 3)
            "pixel0": torch.arange(self.C, device=dev)[:, None, None] * (self.H * self.W),  # (C, 1, 1)
        }
        for name, value in buffers.items():
            self.register_buffer(name, value, persistent=False)
        self._cast: dict[tuple[str, torch.dtype], Tensor] = {}
        with torch.no_grad():
            idx0, sees0 = self._level0(rig)
            model, model_ok = self._model(rig)
        for name, value in (("idx0", idx0), ("sees0", sees0), ("model", model), ("model_ok", model_ok)):
            self.register_buffer(name, value, persistent=False)
        self.footprint = footprint_windows(self)

    @property
    def device(self) -> torch.device:
        return self.lower_t.device

    def edge(self, level: int) -> float:
        return self.e0 / 2 ** level

    def as_(self, name: str, dtype: torch.dtype) -> Tensor:
        """Buffer ``name`` cast to ``dtype`` (cached until the module moves)."""
        if (name, dtype) not in self._cast:
            self._cast[name, dtype] = getattr(self, name).to(dtype)
        return self._cast[name, dtype]

    def _apply(self, fn, recurse: bool = True):  # type: ignore[no-untyped-def]
        self._cast.clear()  # the casts are of the buffers before the move
        return super()._apply(fn, recurse)

    def _level0(self, rig: nn.Module) -> tuple[Tensor, Tensor]:
        """Exact sample pixels of every level-0 voxel (``CameraRig.project``, nearest pixel): idx0, sees0."""
        dev = self.device
        sign = torch.tensor([-0.25, 0.25], dtype=torch.float64, device=dev)
        pattern = torch.stack(torch.meshgrid(sign, sign, sign, indexing="ij"), -1).reshape(8, 1, 3)
        uv, valid = rig.project((self.lower_t + (self.ijk0 + 0.5 + pattern) * self.e0).to(rig.K.dtype))
        px = torch.floor(uv + 0.5).long()  # (C, 8, V0, 2)
        idx = (px[..., 1] + torch.arange(self.C, device=dev)[:, None, None] * self.H) * self.W + px[..., 0]
        for c in range(self.C):
            if not bool(valid[c].any()):
                warnings.warn(f"hierarchical_hull: camera {rig.names[c]!r} sees none of the zone {self.lower} - "
                              f"{[l + n * self.e0 for l, n in zip(self.lower, self.n0)]}; it is skipped",
                              UserWarning, stacklevel=6)
        return torch.where(valid, idx, torch.zeros_like(idx)).to(torch.int32), valid.all(1)  # (C, 8, V0), (C, V0)

    def _model(self, rig: nn.Module) -> tuple[Tensor, Tensor]:
        """Quadratic projection model of every level-0 voxel (see the class docstring): model, model_ok."""
        C, V0, h = self.C, self.ijk0.shape[0], 0.375 * self.e0
        r = torch.tensor([-h, 0.0, h], dtype=torch.float64, device=self.device)
        offs = torch.stack(torch.meshgrid(r, r, r, indexing="ij"), -1).reshape(27, 3)
        pts = offs[:, None] + self.lower_t + (self.ijk0 + 0.5) * self.e0  # (27, V0, 3)
        uv, ok = _project_unclipped(rig, pts.reshape(-1, 3).to(rig.K.dtype))  # (C, 27 V0, 2), (C, 27 V0)
        x, y, z = offs.T
        basis = torch.stack([torch.ones_like(x), x, y, z, x * x / 2, x * y / 2, x * z / 2, x * y / 2, y * y / 2,
                             y * z / 2, x * z / 2, y * z / 2, z * z / 2], -1)  # (27, 13) for value, grad, Hessian
        coef = torch.linalg.pinv(basis) @ uv.double().reshape(C, 27, V0, 2).permute(1, 0, 3, 2).reshape(27, -1)
        return (coef.reshape(13, C * 2, V0).permute(2, 1, 0).reshape(V0, C * 26).contiguous(),
                ok.reshape(C, 27, V0).all(1))  # (V0, C * 26), (C, V0)


def footprint_windows(plan: HullPlan) -> list[int]:
    """Per level, the odd width (px) of the max filter of ``HullConfig.footprint_early_out``: the projected
    width of a child (edge ``e / 2``) at the median level-0 voxel of the camera that sees the zone largest; 1 (no
    filter) where that is under 2 px, and at the finest level (no early-out there)."""
    grad = plan.model.reshape(-1, plan.C, 2, 13)[..., 1:4]  # (V0, C, uv, 3) pixels per metre along x, y, z
    width = grad.abs().sum(-1).amax(-1)  # (V0, C): projected width (px) of a 1 m cube, the wider image axis
    ok = (plan.model_ok & plan.sees0).T  # (V0, C)
    per_camera = [float(width[ok[:, c], c].median()) for c in range(plan.C) if bool(ok[:, c].any())]
    px_per_m = max(per_camera, default=0.0)
    windows = []
    for level in range(plan.L + 1):
        radius = int(px_per_m * plan.edge(level) / 4) if level < plan.L else 0  # half a child's width
        windows.append(2 * radius + 1)
    return windows


def _project_unclipped(rig: nn.Module, pts: Tensor) -> tuple[Tensor, Tensor]:
    """(N, 3) world points -> distorted pixels (C, N, 2) and ok (C, N): in front and inside the radius where the
    distortion model is monotonic; unlike ``CameraRig.project``, not clipped to the image."""
    cam = rig.world_to_camera(pts)  # (C, N, 3)
    z = cam[..., 2]
    ok = z > MIN_DEPTH
    xy = cam[..., :2] / torch.where(ok, z, torch.ones_like(z))[..., None]  # (C, N, 2)
    ok &= (xy * xy).sum(-1) < distortion.fold_radius_sq(rig.dist, rig.fisheye_mask)[:, None]
    xy_d = distortion.distort(xy, rig.dist.to(xy.dtype), rig.fisheye_mask)  # (C, N, 2)
    K = rig.K.to(xy.dtype)
    return xy_d * torch.stack([K[:, 0, 0], K[:, 1, 1]], -1)[:, None, :] + K[:, None, :2, 2], ok
