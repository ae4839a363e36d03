"""Each marker's output position: measured where the views show it, filled from the body and time where not.

The rigid body's markers (the track's skeleton with the subject's marker offsets) cannot follow skin that slides on
the bones; a marker that enough views show is placed where they triangulate it, taken as this marker's where it lies
near the body's, nearer it than any other of the body's markers, and offset from it as its neighbours are (a body
off moves neighbouring markers alike; two labels swapped, as a video detector's linking may, differ by the markers'
distance). Its offset from the body's marker (the skin's motion, slow
against the detector's pixel noise) is smoothed over the frames that measure it; between such frames the marker keeps
that offset as interpolated in time, and over a longer gap the offset fades to the body's marker: the paper's
"estimated from the neighbouring landmarks and temporal coherence" (Canton-Ferrer et al. 2010, §3.4).
"""

from __future__ import annotations

import math

import torch
from kornia.filters import get_gaussian_kernel1d

from torchtrack.checks import check_shape

__all__ = ["BODY", "FILLED", "MEASURED", "NONE", "measured_markers"]

#: What each output marker's position is (``markers3d_source`` of ``poses.npz``): not tracked, triangulated from
#: the frame's detections, the body's marker moved by its measured offset interpolated in time, the body's alone.
NONE, MEASURED, FILLED, BODY = 0, 1, 2, 3
#: A triangulation counts where its offset from the body's marker lies, at the median, within AGREE_M of the offsets
#: of the measured markers the body has within NEIGHBOUR_M of it (about a limb segment; skin slides a few centimetres).
NEIGHBOUR_M, AGREE_M = 0.25, 0.03


def measured_markers(body: torch.Tensor, X: torch.Tensor, views: torch.Tensor, min_views: int = 2,
                     within_m: float = 0.05, gap: int = 15, smooth: float = 1.0, neighbour_m: float = NEIGHBOUR_M,
                     agree_m: float = AGREE_M) -> tuple[torch.Tensor, torch.Tensor]:
    """Markers from the body's and the triangulated ones (module docstring).

    Args:
        body: (T, M, 3) the tracked body's markers (NaN: a marker not tracked).
        X: (T, M, 3) the frames' triangulated markers, NaN where none. views: (T, M) how many views agree on each.
        min_views: a triangulation counts where at least this many views agree ...
        within_m: ... and it lies within this distance of the body's marker (farther: a detection of another
            marker, or a false one, linked to this label), nearer it than any other of the body's markers ...
        neighbour_m, agree_m: ... and the median distance of its offset from the body's marker to its neighbours'
            offsets (the other markers counted so far whose body markers lie within ``neighbour_m`` of its own;
            none: no test) is under ``agree_m``.
        gap: frames over which a measured offset is carried: a gap of at most this many frames between two
            measurements is bridged by the offsets' linear interpolation; past that, each side's offset fades
            linearly to none over this many frames.
        smooth: the standard deviation, in frames, of the Gaussian that averages each marker's offsets over the
            frames that measure it (0: each frame's own).

    Returns:
        (T, M, 3) the markers and (T, M) uint8 their sources (:data:`MEASURED`, :data:`FILLED`, :data:`BODY`,
        :data:`NONE`).
    """
    T, M, _ = body.shape
    check_shape(X, (T, M, 3), "X")
    check_shape(views, (T, M), "views")
    tracked = torch.isfinite(body).all(-1)
    dist = torch.cdist(X.nan_to_num(1e6), body.nan_to_num(-1e6))  # (T, M, M): triangulated -> every body marker
    own = dist.diagonal(dim1=1, dim2=2)
    ok = (views >= min_views) & tracked & torch.isfinite(X).all(-1) & (own < within_m) & (own <= dist.amin(-1))
    offset = torch.where(ok[..., None], X - body, 0.0)
    near = (torch.cdist(body.nan_to_num(1e6), body.nan_to_num(-1e6)) < neighbour_m) & ok[:, None, :]
    near &= ~torch.eye(M, dtype=torch.bool, device=body.device)
    apart = torch.where(near, torch.cdist(offset, offset), math.nan).nanmedian(-1).values  # NaN: no neighbour
    ok &= ~(apart >= agree_m)
    offset = torch.where(ok[..., None], X - body, 0.0)
    if smooth > 0:  # a normalised convolution: the measured frames' offsets weighed by a Gaussian in time
        R = math.ceil(3 * smooth)
        kernel = get_gaussian_kernel1d(2 * R + 1, float(smooth), device=body.device, dtype=body.dtype)[0]

        def conv(a: torch.Tensor) -> torch.Tensor:  # (T, ...) along time
            flat = a.reshape(T, -1).T[:, None]
            return torch.nn.functional.conv1d(torch.nn.functional.pad(flat, (R, R)), kernel[None, None])[:, 0].T \
                .reshape(a.shape)

        weight = ok.to(body)
        offset = torch.where(ok[..., None], conv(offset) / conv(weight).clamp(min=1e-12)[..., None], 0.0)
    t = torch.arange(T, device=body.device)[:, None].expand(T, M)
    prev = torch.where(ok, t, -1).cummax(0).values  # the last measurement at or before each frame (-1: none)
    nxt = torch.where(ok, t, T).flip(0).cummin(0).values.flip(0)  # the first at or after it (T: none)
    L = max(int(gap), 1)
    has_prev, has_next = prev >= 0, nxt < T
    at_prev = offset.gather(0, prev.clamp(min=0)[..., None].expand(T, M, 3))
    at_next = offset.gather(0, nxt.clamp(max=T - 1)[..., None].expand(T, M, 3))
    span = (nxt - prev).clamp(min=1)
    bridged = has_prev & has_next & (span <= L + 1)
    w_next = torch.where(bridged, (t - prev) / span, (1 - (nxt - t) / L).clamp(min=0) * has_next)
    w_prev = torch.where(bridged, 1 - w_next, (1 - (t - prev) / L).clamp(min=0) * has_prev)
    carried = w_prev[..., None] * at_prev + w_next[..., None] * at_next
    out = body + torch.where(ok[..., None], offset, carried)
    source = torch.full((T, M), BODY, dtype=torch.uint8, device=body.device)
    source[(w_prev + w_next) > 0] = FILLED
    source[ok] = MEASURED
    source[~tracked] = NONE
    return out, source
