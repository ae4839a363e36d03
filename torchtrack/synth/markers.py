"""Coloured ball markers on the synthetic body (``torchtrack synth --markers``), for the colour marker detector.

Each marker is a sphere resting on the skin of one blob: a point of the blob's ellipsoid surface, given by how far
along the bone and at which angle round it, pushed out along the surface normal by the ball's radius.
The set follows Vicon Plug-in-Gait's names and places (a head band, trunk, arms, pelvis, legs), so that the marker
tracker's joint-centre regressions know it; the right side mirrors the left. The renderer draws the balls as
ellipsoids of the body, so the body hides them as it hides itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from torchtrack.checks import InputError, check_shape

__all__ = ["MARKER_PLACES", "MarkerStyle", "marker_names", "marker_positions", "visible_centroids"]

#: (name, blob, along, angle) of the midline and left markers: the ball rests on the blob's surface at ``along`` times
#: the semi-axis along the bone (-1 proximal end .. 1 distal end; the head's and trunk's upwards), at ``angle``
#: degrees round the bone from the blob's axis 1 towards its axis 2. Blob frames (configs/blobs.yaml, standing at
#: rest): the trunk's and head's axis 1 points forward and axis 2 left; the limbs' axis 1 points back and axis 2 left
#: (outwards on the left side); the foot's axis 1 points down and back.
MARKER_PLACES: tuple[tuple[str, str, float, float], ...] = (
    ("LFHD", "head", 0.2, 45.0), ("LBHD", "head", 0.2, 135.0),
    ("C7", "neck", -0.5, 180.0), ("T10", "chest", -0.5, 180.0), ("RBAK", "chest", 0.3, -135.0),
    ("CLAV", "chest", 0.75, 0.0), ("STRN", "chest", 0.1, 0.0),
    ("LASI", "pelvis", 0.3, 50.0), ("LPSI", "pelvis", 0.3, 150.0),
    ("LSHO", "l_upperarm", -0.9, 90.0), ("LELB", "l_upperarm", 0.85, 90.0),
    ("LWRA", "l_forearm", 0.85, 90.0), ("LWRB", "l_forearm", 0.85, -90.0), ("LFIN", "l_hand", 0.6, 0.0),
    ("LTHI", "l_thigh", 0.0, 90.0), ("LKNE", "l_thigh", 0.85, 90.0),
    ("LTIB", "l_shank", 0.0, 90.0), ("LANK", "l_shank", 0.85, 90.0),
    ("LHEE", "l_foot", -0.9, 0.0), ("LTOE", "l_foot", 0.7, 180.0),
)


def _mirrored() -> list[tuple[str, str, float, float]]:
    """MARKER_PLACES with each left marker's right twin (``L`` -> ``R``, ``l_`` -> ``r_``, the angle mirrored)."""
    out = []
    for name, blob, along, angle in MARKER_PLACES:
        out.append((name, blob, along, angle))
        if name.startswith("L"):
            twin_blob = "r_" + blob[2:] if blob.startswith("l_") else blob
            out.append(("R" + name[1:], twin_blob, along, -angle))
    return out


def marker_names() -> list[str]:
    """The synthetic set's labels, in the order of :func:`marker_positions`."""
    return [n for n, _, _, _ in _mirrored()]


@dataclass(frozen=True)
class MarkerStyle:
    """The balls' look: ``radius_m`` (m) and ``colour`` (RGB albedo in [0, 1]). The default is a saturated magenta,
    a chrominance that neither the template's clothing nor the room has."""

    radius_m: float = 0.02
    colour: tuple[float, float, float] = (0.95, 0.1, 0.75)

    def __post_init__(self) -> None:
        if not 0.002 <= self.radius_m <= 0.1:
            raise InputError(f"marker radius must be in [0.002, 0.1] m, got {self.radius_m}")
        if len(self.colour) != 3 or not all(0.0 <= v <= 1.0 for v in self.colour):
            raise InputError(f"marker colour needs an RGB triple in [0, 1], got {self.colour}")


def marker_positions(blob_names: list[str], centres: torch.Tensor, R_world_blob: torch.Tensor,
                     semi_axes: torch.Tensor, radius_m: float) -> torch.Tensor:
    """The balls' centres of the synthetic set on a posed blob body.

    Args:
        blob_names: (K,) the body's blob names. centres: (T, K, 3) blob centres. R_world_blob: (T, K, 3, 3) blob
        axes as columns. semi_axes: (K, 3). radius_m: the balls' radius.

    Returns:
        (T, M, 3) ball centres (world, m), M = ``len(marker_names())``.
    """
    check_shape(centres, ("T", len(blob_names), 3), "centres")
    check_shape(R_world_blob, (centres.shape[0], len(blob_names), 3, 3), "R_world_blob")
    places = _mirrored()
    missing = sorted({p[1] for p in places} - set(blob_names))
    if missing:
        raise InputError(f"synthetic markers: the body has no blobs {missing}")
    k = torch.tensor([blob_names.index(p[1]) for p in places], device=centres.device)
    f = torch.tensor([p[2] for p in places], dtype=centres.dtype, device=centres.device)  # (M,)
    ang = torch.deg2rad(torch.tensor([p[3] for p in places], dtype=centres.dtype, device=centres.device))
    a = semi_axes.to(centres)[k]  # (M, 3)
    ring = (1 - f.square()).clamp(min=0).sqrt()  # the cross-section's size at ``along``
    s = torch.stack([f * a[:, 0], ring * a[:, 1] * ang.cos(), ring * a[:, 2] * ang.sin()], -1)  # on the surface
    n = torch.nn.functional.normalize(s / a.square(), dim=-1)  # the surface normal there (blob frame)
    local = s + radius_m * n  # (M, 3) the ball's centre, resting on the skin
    return centres[:, k] + (R_world_blob[:, k] @ local[..., None])[..., 0]


def visible_centroids(part_ids: torch.Tensor, first_marker: int, num_markers: int
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Each marker's visible pixels in each view, from the renderer's part map (markers are parts ``first_marker ..
    first_marker + num_markers - 1``).

    Args:
        part_ids: (C, H, W) int64 visible part per pixel, -1 for none.

    Returns:
        (C, M, 2) mean pixel (u, v) of the marker's visible pixels, NaN where none; (C, M) int64 their count.
    """
    C, H, W = part_ids.shape
    m = part_ids.reshape(C, -1) - first_marker
    ok = (m >= 0) & (m < num_markers)
    cam = torch.arange(C, device=part_ids.device)[:, None].expand_as(m)[ok]
    key = cam * num_markers + m[ok]
    pix = ok.nonzero()[:, 1]
    u, v = (pix % W).double(), torch.div(pix, W, rounding_mode="floor").double()
    count = torch.bincount(key, minlength=C * num_markers)
    su = torch.bincount(key, weights=u, minlength=C * num_markers)
    sv = torch.bincount(key, weights=v, minlength=C * num_markers)
    uv = torch.stack([su, sv], -1) / count[:, None].clamp(min=1)
    uv = torch.where(count[:, None] > 0, uv, np.nan)
    return uv.reshape(C, num_markers, 2), count.reshape(C, num_markers)
