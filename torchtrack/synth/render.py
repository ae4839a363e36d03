"""Shading of the synthetic renderer's body parts (the ray casting is :mod:`torchtrack.ellipsoids`)."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from torchtrack.checks import InputError, check_shape

__all__ = ["shade"]


def shade(
    normal: torch.Tensor,
    part_id: torch.Tensor,
    colours: torch.Tensor,
    light_dir_world: torch.Tensor,
    ambient: float = 0.35,
    variation: torch.Tensor | None = None,
    variation_amplitude: float = 0.0,
) -> torch.Tensor:
    """Lambertian + ambient shading of body parts from one directional light.

    ``rgb = colour[part] * (ambient + (1 - ambient) * max(0, n . l)) * (1 + variation_amplitude * variation)``,
    clamped to [0, 1]; zero where ``part_id < 0``.

    Args:
        normal: (..., 3) outward unit normals (world).
        part_id: (...) int64 part of each point, -1 for none.
        colours: (K, 3) RGB base colour per part in [0, 1].
        light_dir_world: (3,) direction *towards* the light (normalized here).
        ambient: fraction of the light that reaches every surface, in [0, 1].
        variation: optional (...) texture-free variation per point in [-1, 1] (e.g. the position along the
            part's long axis), so that a part is not one flat colour.
        variation_amplitude: relative brightness change at ``|variation| = 1``.

    Returns:
        rgb: (..., 3) in [0, 1].
    """
    check_shape(colours, ("K", 3), "colours")
    check_shape(light_dir_world, (3,), "light_dir_world")
    check_shape(normal, (*part_id.shape, 3), "normal")
    if not 0.0 <= ambient <= 1.0:
        raise InputError(f"ambient must be in [0, 1], got {ambient}")
    light = F.normalize(light_dir_world.to(normal), dim=0)
    lambert = (normal @ light).clamp_min(0)  # (...)
    gain = ambient + (1.0 - ambient) * lambert  # (...)
    if variation is not None:
        check_shape(variation, tuple(part_id.shape), "variation")
        gain = gain * (1.0 + variation_amplitude * variation.clamp(-1, 1))
    valid = part_id >= 0
    rgb = colours.to(normal)[part_id.clamp_min(0)] * gain[..., None]  # (..., 3)
    return torch.where(valid[..., None], rgb.clamp(0, 1), torch.zeros_like(rgb))
