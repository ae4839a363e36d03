"""A frame's 3D observation as a weighted, coloured voxel set, from either observation model.

* ``bayes``: the Franco-Boyer grid (de Bem); voxels with P(occupied) > threshold, weight P * s^3, each voxel's
  colour in a view is the background model's gain-normalised YUV at the pixel its centre projects to.
* ``hull``: the hierarchical colour visual hull (Caillette); voxels of several sizes, weight s^3, with the mean
  sample colour per view the hull computes.
"""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import nn

from torchtrack.checks import InputError
from torchtrack.occupancy import BayesConfig, BayesianGrid, HierarchicalHull, HullConfig, capture_views, grid_from_rig
from torchtrack.tracking.voxels import ViewSilhouettes, VoxelObservation

#: What the tracker's data types are re-exported for: callers that import them from here.
__all__ = ["MODELS", "Observer", "ViewSilhouettes", "VoxelObservation", "default_silhouettes"]

MODELS = ("bayes", "hull")


def default_silhouettes(model: str = "bayes") -> bool:
    """Whether the tracking keeps each camera's foreground by default (``observation.silhouettes: null``): for the
    Bayesian grid on every rig, where the start search then scores bodies in the images and keeps both headings
    (:mod:`~torchtrack.tracking.search`; docs/results.md, "The start search"). The hull keeps no per-pixel
    evidence."""
    return model == "bayes"


class Observer(nn.Module):
    """Turns batches of camera frames into :class:`VoxelObservation` s.

    Args:
        rig: CameraRig at the processing image size. background: BackgroundModel of the same size.
        model: "bayes" or "hull". voxel_size_m: grid voxel (bayes) or finest hull voxel.
        lower_m, upper_m: the tracking volume (default: the box over the floor that ``min_views`` cameras see,
            floor to 2.1 m).
        threshold: occupancy probability above which a Bayesian voxel is kept.
        min_views: a voxel counts where at least this many cameras see it (None:
            :func:`~torchtrack.occupancy.capture_views`: for the grid half of them and at least three, for the hull
            all).

        bayes, hull: optional model configs (their volume and voxel fields are overridden).
    """

    def __init__(self, rig: nn.Module, background: nn.Module, model: str = "bayes", voxel_size_m: float = 0.03,
                 lower_m: tuple[float, float, float] | None = None, upper_m: tuple[float, float, float] | None = None,
                 threshold: float = 0.5, min_views: int | None = None, bayes: BayesConfig | None = None,
                 hull: HullConfig | None = None, silhouettes: bool = False) -> None:
        super().__init__()
        if model not in MODELS:
            raise InputError(f"observation model must be one of {MODELS}, got {model!r}")
        self.model, self.threshold, self.rig, self.background = model, threshold, rig, background
        if silhouettes and model != "bayes":
            raise InputError("observation silhouettes: only the Bayesian grid keeps each camera's foreground")
        self.silhouettes = silhouettes
        if min_views is None:
            min_views = capture_views(rig.num_cameras, model)
        elif not 1 <= int(min_views) <= rig.num_cameras:
            raise InputError(f"observation min_views: {min_views} cameras of the rig's {rig.num_cameras}")
        self.min_views = int(min_views)
        if lower_m is None or upper_m is None:
            spec = grid_from_rig(rig, voxel_size_m, min_views=min_views)
        else:
            from torchtrack.occupancy import GridSpec

            spec = GridSpec(tuple(lower_m), tuple(upper_m), voxel_size_m)
        self.spec = spec
        if model == "bayes":
            cfg = replace(bayes or BayesConfig(), min_views=min_views)
            self.grid = BayesianGrid(rig, spec, background, cfg)
            self.register_buffer("centres", spec.centres(dtype=rig.K.dtype, device=rig.K.device), persistent=False)
        else:
            base = hull or HullConfig()
            fields = {**base.__dict__, "lower_m": spec.lower_m, "upper_m": spec.upper_m,
                      "finest_voxel_m": voxel_size_m, "min_views": min_views}
            self.hull_config = HullConfig(**fields)
            self.hull = HierarchicalHull(rig, self.hull_config)

    def forward(self, images: torch.Tensor, cameras_valid: torch.Tensor | None = None) -> list[VoxelObservation]:
        """(B, C, 3, H, W) RGB frames (NaN: unreadable) -> B observations."""
        if cameras_valid is None:
            cameras_valid = torch.isfinite(images.flatten(2)).all(-1)
        if self.model == "hull":
            out = []
            cams = self.rig.centers()  # the cameras' centres, from the rig as it is now
            for b in range(images.shape[0]):
                v = self.hull.from_images(self.background, images[b])
                w = v.sizes ** 3
                out.append(VoxelObservation(v.centres, v.sizes, w, v.colours.to(v.centres.dtype), cameras_valid[b],
                                            camera_centres=cams.to(v.centres.dtype),
                                            volume_m=self.hull_config.covered_box()))
            return out
        lit, shadowed, yuv = self.background.log_likelihood_and_yuv(images, shadows=True)  # (B, C, H, W) x2, YUV
        out = self._voxels(self.grid.occupied_voxels(lit, shadowed, self.threshold), yuv, cameras_valid)
        if self.silhouettes:
            ev = self.grid.pixel_evidence(lit)  # (B, C, H, W), without the shadow test
            out = [replace(o, silhouettes=ViewSilhouettes.from_evidence(ev[b], self.rig)) for b, o in enumerate(out)]
        return out

    def from_probability(self, prob: torch.Tensor, yuv: torch.Tensor, cameras_valid: torch.Tensor
                         ) -> list[VoxelObservation]:
        """Bayesian grid only: observations from an occupancy probability per grid voxel ``(B, V)`` (the grid's
        own, or another over the same grid, e.g. a silhouette carving through ``self.grid.lookup``) and the
        gain-normalised YUV images ``(B, C, 3, H, W)`` the voxels take their colours from."""
        if self.model != "bayes":
            raise InputError(f"Observer.from_probability needs the Bayesian grid's voxels, not model {self.model!r}")
        keep = prob > self.threshold
        kept = [(keep[b].nonzero()[:, 0], prob[b][keep[b]]) for b in range(prob.shape[0])]
        return self._voxels(kept, yuv, cameras_valid)

    def _voxels(self, kept: list[tuple[torch.Tensor, torch.Tensor]], yuv: torch.Tensor, cameras_valid: torch.Tensor
                ) -> list[VoxelObservation]:
        """Per frame (grid voxel indices (n,), their P(occupied) (n,)) -> observations coloured from ``yuv``."""
        s = self.spec.voxel_size_m
        cams = self.rig.centers()  # the cameras' centres
        out = []
        for b, (idx, p) in enumerate(kept):
            pts = self.centres[idx]
            pix = self.grid.lookup.pixel_index[:, idx]  # (C, n)
            flat = yuv[b].flatten(2)  # (C, 3, H*W)
            col = flat.gather(2, pix.clamp(min=0)[:, None, :].expand(-1, 3, -1))  # (C, 3, n)
            col = torch.where((pix >= 0)[:, None, :], col, torch.nan).permute(2, 0, 1)  # (n, C, 3)
            sizes = torch.full_like(pts[:, 0], s)
            out.append(VoxelObservation(pts, sizes, p * s ** 3, col, cameras_valid[b],
                                        camera_centres=cams.to(pts.dtype),
                                        volume_m=self.spec.covered_box()))
        return out
