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
2. Evidence: within ``near_px`` of where the subject moved, the log ratio of the two histograms at the median
   pixel's colour (> 0: the subject explains it better, the Bayes decision at even prior odds; minus
   ``BackgroundConfig.fill_prior_log_odds`` otherwise); farther away, surely room.
3. Segmentation: a graph cut on the median image (:func:`graph_cut`: that log ratio as the unary term, a
   contrast-sensitive Potts term of weight :data:`SMOOTHNESS`; Boykov & Jolly 2001) turns the evidence into a
   coherent region, which is grown by ``grow_px`` so the fill starts from clean room pixels. GrabCut (Rother
   et al. 2004) solves the same energy but re-learns its colour models as 5-component GMMs from its own noisy
   seeds; on the Pose2Sim demo it dropped the stance lower leg and foot (skin on a dark treadmill, a thin
   region whose colours the room GMM also explains) in three of the four cameras although the histogram
   ratio called them subject (docs/results.md, "Tried and dropped").
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

import kornia
import numpy as np
import torch

from torchtrack.background import estimate as est
from torchtrack.checks import InputError, ShapeError

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
#: Weight of the graph cut's smoothness term (nats per neighbour pair across a uniform colour; see graph_cut).
SMOOTHNESS = 1.0


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


def contrast_weights(image: np.ndarray) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[np.ndarray]]:
    """Contrast-sensitive Potts weights of the 8-neighbour pairs of ``image (h, w, 3)`` float (Boykov & Jolly
    2001, as in GrabCut): ``exp(-beta |I_p - I_q|^2) / dist(p, q)``, ``beta = 1 / (2 mean |I_p - I_q|^2)``.

    Returns:
        pairs: per direction (4 of them) the flat indices (n_d,), (n_d,) of p and q; weights: (n_d,) each.
    """
    h, w = image.shape[:2]
    idx = np.arange(h * w).reshape(h, w)
    flat = image.reshape(-1, image.shape[-1]).astype(np.float64)
    pairs, d2, dist = [], [], []
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        p = idx[:h - dy, max(0, -dx):w - max(0, dx)]  # (h - dy, w - |dx|)
        q = idx[dy:, max(0, dx):w + min(0, dx)]
        pairs.append((p.ravel(), q.ravel()))
        d2.append(np.square(flat[p.ravel()] - flat[q.ravel()]).sum(-1))
        dist.append(float(np.hypot(dy, dx)))
    beta = 1.0 / (2.0 * max(float(np.concatenate(d2).mean()), 1e-12))
    return pairs, [np.exp(-beta * d) / r for d, r in zip(d2, dist)]


def graph_cut(log_ratio: np.ndarray, image: np.ndarray, free: np.ndarray, smoothness: float) -> np.ndarray:
    """Binary MAP segmentation: minimise ``sum_p -log_ratio_p [p in] + smoothness sum_pq w_pq [p, q split]`` over
    the labellings with every pixel outside ``free`` out, by a minimum s-t cut.

    ``w_pq`` are the contrast-sensitive Potts weights of :func:`contrast_weights` over 8 neighbours. GrabCut solves
    the same energy but re-learns the colour models as GMMs from its own labelling, which is only as good as its
    seeds; here the unary is the given log ratio. OpenCV exposes no general graph cut, so the graph is built
    here and solved by :func:`scipy.sparse.csgraph.maximum_flow` (Dinic, integer capacities in 1/100 nat);
    the cut is the set reachable from the source in the residual graph.

    Args:
        log_ratio: (H, W) ``log p(colour | in) - log p(colour | out)`` per pixel (finite where ``free``).
        image: (H, W, K) float colours of the pairwise term. free: (H, W) bool, pixels that may be in.
        smoothness: weight of the pairwise term (nats per neighbour pair across a uniform colour).

    Returns:
        (H, W) bool, the pixels in.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import breadth_first_order, maximum_flow

    if log_ratio.shape != free.shape or image.shape[:2] != free.shape or image.ndim != 3:
        raise ShapeError(f"graph_cut: expected log_ratio (H, W), image (H, W, K), free (H, W); got "
                         f"{log_ratio.shape}, {image.shape}, {free.shape}")
    if not 0 <= smoothness <= 1e6:  # capacities are int32 in 1/100 nat
        raise InputError(f"graph_cut: smoothness must be in [0, 1e6], got {smoothness}")
    out = np.zeros(free.shape, bool)
    if not free.any():
        return out
    rows, cols = np.nonzero(free)
    y0, y1 = max(int(rows.min()) - 1, 0), min(int(rows.max()) + 2, free.shape[0])
    x0, x1 = max(int(cols.min()) - 1, 0), min(int(cols.max()) + 2, free.shape[1])
    unary = np.where(free, log_ratio, 0.0)[y0:y1, x0:x1].ravel()  # (n,)
    fixed_out = ~free[y0:y1, x0:x1].ravel()  # (n,) the crop's one-pixel border is out (or the image's edge)
    n, scale = unary.size, 100.0
    source, sink = n, n + 1
    pairs, weights = contrast_weights(image[y0:y1, x0:x1])
    nodes = np.arange(n)
    # "never cut": a fixed-out node's only inflow is its <= 8 pair edges of <= scale * smoothness each
    hard = np.int64(8 * int(np.ceil(scale * smoothness)) + 1)
    src_cap = np.where(fixed_out, 0, np.round(scale * np.clip(unary, 0, None))).astype(np.int64)
    snk_cap = np.where(fixed_out, hard, np.round(scale * np.clip(-unary, 0, None))).astype(np.int64)
    heads = [np.full(n, source), nodes] + [a for p, q in pairs for a in (p, q)]
    tails = [nodes, np.full(n, sink)] + [a for p, q in pairs for a in (q, p)]
    caps = [src_cap, snk_cap] + [c for w in weights for c in 2 * [np.round(scale * smoothness * w).astype(np.int64)]]
    r, c, k = np.concatenate(heads), np.concatenate(tails), np.concatenate(caps)
    keep = k > 0
    capacity = sp.csr_matrix((k[keep].astype(np.int32), (r[keep], c[keep])), shape=(n + 2, n + 2))
    capacity.sum_duplicates()
    flow = maximum_flow(capacity, source, sink, method="dinic").flow  # skew-symmetric
    residual = (capacity - flow).tocsr()
    residual.data = (residual.data > 0).astype(np.int8)
    residual.eliminate_zeros()
    reach = breadth_first_order(residual, source, directed=True, return_predecessors=False)
    inside = np.zeros(n + 2, bool)
    inside[reach] = True
    out[y0:y1, x0:x1] = inside[:n].reshape(y1 - y0, x1 - x0) & ~fixed_out.reshape(y1 - y0, x1 - x0)
    return out


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
                   std: torch.Tensor, threshold: float, names: Sequence[str], prior_log_odds: float = 0.0
                   ) -> torch.Tensor:
    """(C, H, W) bool: where each camera's median background ``mean`` holds the subject (see the module doc).

    Args:
        frames: (N, C, 3, H, W) RGB the model was estimated from. dead: (N, C) frames to skip. gains: (N, C)
            divisors or None. mean, std: (C, 3, H, W) the model (YUV). threshold: squared Mahalanobis distance
            over which a pixel is the (moving) subject. names: (C,) camera names for the log.
        prior_log_odds: prior log odds of room against subject, subtracted from the colour log ratio (the graph
            cut's unary is the posterior log odds).
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
        log_ratio = (subject_log_ratio(mean[c], subject, room) - prior_log_odds).to(near.device)  # (H, W)
        if int((near & (log_ratio > 0)).sum()) < MIN_SEED_PIXELS:
            continue
        rgb = kornia.color.yuv_to_rgb(mean[c].float()).clamp(0, 1).permute(1, 2, 0).cpu().numpy()  # (H, W, 3)
        region = torch.from_numpy(graph_cut(log_ratio.cpu().numpy(), rgb, near.cpu().numpy(), SMOOTHNESS))
        region = region.to(out.device)
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
