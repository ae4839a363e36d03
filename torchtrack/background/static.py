"""A subject that stays in place: find it in a temporal-median background and paint it out.

A background estimated from a moving sequence (:meth:`BackgroundModel.from_sequence`) keeps whatever did not
move: a subject balancing in place leaves their trunk and stance leg in the median (a *ghost*), and the
ghost is then background in every frame. No per-pixel temporal statistic can tell a ghost from the room,
but its colours can: the parts of the subject that do move (arms, head, swinging leg) show what the subject
looks like, and the pixels that never change show what the room looks like.

Per camera:

1. Colour models: 3D YUV histograms (:data:`COLOUR_BINS` per channel, Gaussian-smoothed) of the moving
   subject (pixels foreground under the median model in some frame) and of the room (the median at pixels
   never foreground).
2. Seeds: within ``near_px`` of where the subject moved, a median pixel whose colour the subject's histogram
   explains better than the room's (log ratio > 0, the Bayes decision) is probably the subject.
3. Segmentation: OpenCV's GrabCut (colour GMMs and a graph cut on the median image; Rother et al. 2004) turns
   the seeds into a coherent region, which is grown by ``grow_px`` so the fill starts from clean room pixels.
4. Fill: the region's background mean is inpainted from the room around it (:func:`cv2.inpaint`, the
   Navier-Stokes method, per YUV channel in float32; OpenCV's Telea method is wrong on float32 images in
   OpenCV 5.0, offset by about -1.2 on a ramp, and quantised on 8- and 16-bit ones); its std is kept.

The fill is a guess of the room behind the subject: good where the room is smooth (walls, floor), rough where
it has structure. Empty-scene frames (``background/``) are always better; this runs only on the estimated
path (``BackgroundConfig.fill_static_subject``).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import torch

from torchtrack.background import estimate as est

logger = logging.getLogger(__name__)

#: Bins per YUV channel of the colour histograms.
COLOUR_BINS = 24
#: Std of the Gaussian smoothing of the histograms, in bins (colours a bin apart are alike).
COLOUR_SMOOTH_BINS = 1.0
#: YUV ranges of the histograms (kornia's YUV of the RGB unit cube; gain-normalised values outside are clamped).
YUV_RANGE = ((0.0, 1.0), (-0.436, 0.436), (-0.615, 0.615))
#: At most this many subject colour samples per camera (evenly strided); the histogram needs far fewer.
MAX_SAMPLES = 1 << 20
#: A camera needs this many subject pixels (over all frames) and seed pixels, or it is left as it is.
MIN_SUBJECT_PIXELS = 200
MIN_SEED_PIXELS = 20
#: GrabCut iterations.
GRABCUT_ITERATIONS = 5


def _bin_index(yuv: torch.Tensor) -> torch.Tensor:
    """(..., 3) YUV -> (...,) flat histogram bin index."""
    lo = torch.tensor([r[0] for r in YUV_RANGE], dtype=yuv.dtype, device=yuv.device)
    hi = torch.tensor([r[1] for r in YUV_RANGE], dtype=yuv.dtype, device=yuv.device)
    idx = ((yuv - lo) / (hi - lo) * COLOUR_BINS).floor().long().clamp(0, COLOUR_BINS - 1)  # (..., 3)
    return (idx[..., 0] * COLOUR_BINS + idx[..., 1]) * COLOUR_BINS + idx[..., 2]


def colour_log_density(yuv: torch.Tensor) -> torch.Tensor:
    """Log of the smoothed, normalised colour histogram of ``yuv (N, 3)`` samples: (COLOUR_BINS,)*3 float64.

    Each bin gets the Gaussian-smoothed share of the samples plus a floor of 1e-7 (no colour is impossible).
    """
    B = COLOUR_BINS
    counts = torch.bincount(_bin_index(yuv).reshape(-1).cpu(), minlength=B ** 3).double().reshape(1, 1, B, B, B)
    r = max(1, int(3 * COLOUR_SMOOTH_BINS))
    x = torch.arange(-r, r + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (x / COLOUR_SMOOTH_BINS) ** 2)
    k = k / k.sum()
    for dim in range(3):  # separable smoothing, zero padded (mass near the gamut's edge leaks out a little)
        shape = [1, 1, 1, 1, 1]
        shape[2 + dim] = k.numel()
        pad = [0, 0, 0, 0, 0, 0]
        pad[2 * (2 - dim)] = pad[2 * (2 - dim) + 1] = r
        counts = torch.nn.functional.conv3d(torch.nn.functional.pad(counts, pad), k.reshape(shape))
    density = counts[0, 0] / counts.sum().clamp_min(1e-300)
    return (density + 1e-7).log()


def subject_log_ratio(median: torch.Tensor, subject: torch.Tensor, room: torch.Tensor) -> torch.Tensor:
    """(3, H, W) median YUV, (N, 3) subject and (M, 3) room colour samples -> (H, W) float64
    ``log p(median | subject) - log p(median | room)`` under the two smoothed histograms."""
    log_s, log_r = colour_log_density(subject).flatten(), colour_log_density(room).flatten()
    idx = _bin_index(median.permute(1, 2, 0)).cpu()  # (H, W)
    return log_s[idx] - log_r[idx]


def _grabcut(median_yuv: torch.Tensor, seeds: torch.Tensor, near: torch.Tensor) -> np.ndarray:
    """GrabCut of the median image: ``seeds`` probably subject, the rest of ``near`` probably room, the rest
    surely room. Returns (H, W) bool."""
    import cv2  # lazy: no OpenCV at package import (DESIGN.md)

    import kornia

    rgb = kornia.color.yuv_to_rgb(median_yuv.float().cpu()).clamp(0, 1)  # (3, H, W)
    bgr = np.ascontiguousarray((rgb.permute(1, 2, 0).numpy()[..., ::-1] * 255).round().astype(np.uint8))
    mask = np.full(seeds.shape, cv2.GC_BGD, np.uint8)
    mask[near.cpu().numpy()] = cv2.GC_PR_BGD
    mask[seeds.cpu().numpy()] = cv2.GC_PR_FGD
    bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
    cv2.setRNGSeed(0)  # GrabCut seeds its GMMs by k-means on OpenCV's global RNG: same input, same result
    cv2.grabCut(bgr, mask, None, bgd, fgd, GRABCUT_ITERATIONS, cv2.GC_INIT_WITH_MASK)
    return (mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)


def inpaint(mean: torch.Tensor, region: torch.Tensor, radius_px: int) -> torch.Tensor:
    """(3, H, W) YUV mean with ``region (H, W)`` painted from around it (:func:`cv2.inpaint`, Navier-Stokes,
    per channel in float32); a copy, in ``mean``'s dtype and device."""
    import cv2

    hole = region.cpu().numpy().astype(np.uint8)
    out = mean.clone()
    for k in range(3):
        channel = np.ascontiguousarray(mean[k].float().cpu().numpy())
        filled = cv2.inpaint(channel, hole, radius_px, cv2.INPAINT_NS)
        out[k] = torch.from_numpy(filled).to(out)
    return torch.where(region.to(out.device), out, mean)


def static_subject(frames: torch.Tensor, dead: torch.Tensor, gains: torch.Tensor | None, mean: torch.Tensor,
                   std: torch.Tensor, threshold: float, names: Sequence[str]) -> torch.Tensor:
    """(C, H, W) bool: where each camera's median background ``mean`` holds the subject (see the module doc).

    Args:
        frames: (N, C, 3, H, W) RGB the model was estimated from. dead: (N, C) frames to skip. gains: (N, C)
            divisors or None. mean, std: (C, 3, H, W) the model (YUV). threshold: squared Mahalanobis distance
            over which a pixel is the (moving) subject. names: (C,) camera names for the log.
    """
    N, C, _, H, W = frames.shape
    near_px, grow_px = max(2, max(H, W) // 48), max(1, max(H, W) // 120)
    moving = torch.zeros((C, H, W), dtype=torch.bool, device=frames.device)
    samples: list[list[torch.Tensor]] = [[] for _ in range(C)]
    stride = max(1, (N * H * W) // MAX_SAMPLES)
    for s in est.frame_chunks(N, frames[0].numel()):
        x = est._yuv(frames[s], dead[s], None if gains is None else gains[s], mean.dtype)  # (n, C, 3, H, W)
        fg = ((x - mean) / std).square().sum(2) > threshold  # (n, C, H, W); NaN -> False
        moving |= fg.any(0)
        for c in range(C):
            samples[c].append(x[:, c].permute(0, 2, 3, 1)[fg[:, c]][::stride])  # (k, 3)
    out = torch.zeros_like(moving)
    for c in range(C):
        subject = torch.cat(samples[c])
        room = mean[c].permute(1, 2, 0)[~moving[c]]  # (M, 3)
        room = room[room.isfinite().all(-1)]
        if len(subject) < MIN_SUBJECT_PIXELS or len(room) < MIN_SUBJECT_PIXELS:
            logger.info("static subject: camera '%s' has %d moving-subject pixels; left as it is", names[c],
                        len(subject))
            continue
        near = est.dilate(moving[c], near_px)
        seeds = near & (subject_log_ratio(mean[c], subject, room) > 0).to(near.device)
        if int(seeds.sum()) < MIN_SEED_PIXELS:
            continue
        region = torch.from_numpy(_grabcut(mean[c], seeds, near)).to(out.device)
        out[c] = est.dilate(region, grow_px)
    logger.info("static subject painted out of the background: %s", ", ".join(
        f"{n} {100 * float(m.float().mean()):.1f}%" for n, m in zip(names, out)))
    return out


def paint_out(mean: torch.Tensor, region: torch.Tensor) -> torch.Tensor:
    """(C, 3, H, W) background mean with each camera's ``region (C, H, W)`` inpainted from the room around it."""
    radius = max(2, max(mean.shape[-2:]) // 64)
    out = mean.clone()
    for c in range(mean.shape[0]):
        if bool(region[c].any()):
            out[c] = inpaint(mean[c], region[c], radius)
    return out
