"""Simulated 2D marker detections (Canton-Ferrer §4.1): real 3D markers projected into a calibrated rig.

A marker is seen by a camera where it projects inside the image and no body ellipsoid hides it: the ray from the
camera centre to the marker enters an ellipsoid more than ``skin_m`` before the marker (markers sit on the skin,
which the blobs only approximate, so a marker a few centimetres inside its own blob stays visible from its side).
A generic detector then misses each seen marker with probability ``p_miss``, adds Gaussian pixel noise of
``sigma_px`` to what it finds, and makes false detections: a Poisson number per view and frame (mean
``false_rate``), each labelled as a marker drawn uniformly and placed uniformly in the image. Every random draw
comes from the caller's ``torch.Generator``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from torchtrack.checks import InputError, check_shape
from torchtrack.ellipsoids import ray_ellipsoid_pair_hits

__all__ = ["DetectorModel", "Detections", "marker_visibility", "simulate_detections"]


@dataclass(frozen=True)
class DetectorModel:
    """The simulated detector's statistics (the paper's p_miss, false-positive rate and sigma).

    Attributes:
        p_miss: probability that a seen marker is not detected in a view.
        false_rate: false detections per view and frame (Poisson mean).
        sigma_px: standard deviation of each true detection's pixel noise, per axis.
        skin_m: a body ellipsoid hides a marker where the ray to it enters the ellipsoid more than this before it.
    """

    p_miss: float = 0.2
    false_rate: float = 0.1
    sigma_px: float = 2.0
    skin_m: float = 0.05

    def __post_init__(self) -> None:
        for name, ok in (("p_miss", 0.0 <= self.p_miss <= 1.0), ("false_rate", 0.0 <= self.false_rate),
                         ("sigma_px", 0.0 <= self.sigma_px), ("skin_m", 0.0 <= self.skin_m)):
            if not (ok and math.isfinite(getattr(self, name))):
                raise InputError(f"DetectorModel.{name}: {getattr(self, name)} is out of range "
                                 "(p_miss in [0, 1], the others >= 0)")


@dataclass(frozen=True)
class Detections:
    """Simulated detections of T frames, C cameras, M markers, K candidates.

    Attributes:
        uv: (T, C, M, K, 2) candidate pixels, NaN where none (in no particular order).
        true_index: (T, C, M) int64, the candidate that is the marker, -1 where it was not detected.
        visible: (T, C, M) bool, the marker in the image and not hidden by the body (before the misses).
    """

    uv: torch.Tensor
    true_index: torch.Tensor
    visible: torch.Tensor


def marker_visibility(markers: torch.Tensor, rig: nn.Module, centres: torch.Tensor | None = None,
                      R: torch.Tensor | None = None, semi_axes: torch.Tensor | None = None, skin_m: float = 0.05,
                      chunk: int = 1 << 21) -> tuple[torch.Tensor, torch.Tensor]:
    """Each marker's projection in each camera and whether the camera sees it.

    Args:
        markers: (T, M, 3) world positions (m), NaN where the capture lost the marker.
        rig: CameraRig (:meth:`project` with lens distortion, :meth:`centers`).
        centres, R, semi_axes: the body's ellipsoids per frame, (T, K, 3), (T, K, 3, 3) (columns: the axes) and
            (K, 3) or (T, K, 3); None: nothing hides a marker.
        skin_m: see :class:`DetectorModel`. chunk: (camera, frame, marker, ellipsoid) tests held at once.

    Returns:
        uv (T, C, M, 2) pixels and visible (T, C, M) bool.
    """
    check_shape(markers, ("T", "M", 3), "markers")
    T, M, _ = markers.shape
    finite = torch.isfinite(markers).all(-1)  # (T, M)
    uv, inside = rig.project(torch.nan_to_num(markers).to(rig.K.dtype))  # (C, T, M, 2), (C, T, M)
    visible = inside & finite[None]
    if centres is not None:
        check_shape(centres, (T, "K", 3), "centres")
        K = centres.shape[1]
        semi = semi_axes.to(markers).expand(T, K, 3)
        eye = rig.centers().to(markers)  # (C, 3)
        C = eye.shape[0]
        hidden = torch.zeros(C, T, M, dtype=torch.bool, device=markers.device)
        step = max(1, chunk // max(1, C * M * K))
        for t0 in range(0, T, step):
            t1 = min(T, t0 + step)
            n = t1 - t0
            ray = markers[None, t0:t1] - eye[:, None, None]  # (C, n, M, 3)
            length = ray.norm(dim=-1)  # (C, n, M)
            d = ray / length.clamp(min=1e-9)[..., None]
            cam = torch.arange(C, device=markers.device)[:, None, None, None].expand(C, n, M, K)
            frame = torch.arange(t0, t1, device=markers.device)[None, :, None, None].expand(C, n, M, K)
            k = torch.arange(K, device=markers.device)[None, None, None, :].expand(C, n, M, K)
            flat = (frame * K + k).reshape(-1)  # the ellipsoid of each test among all T * K
            hit = ray_ellipsoid_pair_hits(eye[cam.reshape(-1)], d[..., None, :].expand(C, n, M, K, 3).reshape(-1, 3),
                                          flat, centres.reshape(-1, 3), R.reshape(-1, 3, 3), semi.reshape(-1, 3))
            hidden[:, t0:t1] = (hit.view(C, n, M, K) < (length - skin_m)[..., None]).any(-1)
        visible &= ~hidden
    return uv.permute(1, 0, 2, 3), visible.permute(1, 0, 2)


def simulate_detections(uv: torch.Tensor, visible: torch.Tensor, image_size_wh: torch.Tensor, model: DetectorModel,
                        generator: torch.Generator) -> Detections:
    """The detector of :class:`DetectorModel` run on the markers' projections.

    Args:
        uv: (T, C, M, 2) true pixels, visible: (T, C, M) (:func:`marker_visibility`).
        image_size_wh: (C, 2) each camera's image size (false detections fall uniformly inside it).
        model: the detector's statistics. generator: every random draw's source (on ``uv``'s device).

    Returns:
        :class:`Detections`.
    """
    check_shape(uv, ("T", "C", "M", 2), "uv")
    T, C, M, _ = uv.shape
    check_shape(visible, (T, C, M), "visible")
    dev, dt = uv.device, uv.dtype
    detected = visible & (torch.rand(T, C, M, generator=generator, device=dev) >= model.p_miss)
    noisy = uv + model.sigma_px * torch.randn(T, C, M, 2, generator=generator, device=dev, dtype=dt)
    # false detections: a Poisson count per (frame, view), each with a marker label and a pixel
    counts = torch.poisson(torch.full((T, C), float(model.false_rate), device=dev), generator=generator).long()
    tc = torch.arange(T * C, device=dev).repeat_interleave(counts.reshape(-1))  # (F,) the (frame, view) of each
    F = tc.shape[0]
    label = torch.randint(M, (F,), generator=generator, device=dev)
    size = image_size_wh.to(dev, dt)[tc % C]  # (F, 2)
    fake = torch.rand(F, 2, generator=generator, device=dev, dtype=dt) * size - 0.5
    # every candidate (true ones first, then the false) with its (frame, view, marker) group, in a random order
    # within its group: the order tells nothing
    true_group = detected.reshape(-1).nonzero()[:, 0]  # (D,)
    group = torch.cat([true_group, tc * M + label])  # (D + F,)
    points = torch.cat([noisy.reshape(-1, 2)[true_group], fake])
    is_true = torch.cat([torch.ones_like(true_group, dtype=torch.bool), torch.zeros(F, dtype=torch.bool, device=dev)])
    key = group.double() + torch.rand(group.shape[0], generator=generator, device=dev, dtype=torch.float64)
    order = key.argsort()
    group, points, is_true = group[order], points[order], is_true[order]
    first = torch.searchsorted(group, group)  # the sorted position where each one's group starts
    slot = torch.arange(group.shape[0], device=dev) - first
    K = max(1, int(slot.max()) + 1) if group.numel() else 1
    out = torch.full((T * C * M, K, 2), math.nan, device=dev, dtype=dt)
    out[group, slot] = points
    true_index = torch.full((T * C * M,), -1, dtype=torch.long, device=dev)
    true_index[group[is_true]] = slot[is_true]
    return Detections(out.view(T, C, M, K, 2), true_index.view(T, C, M), visible)
