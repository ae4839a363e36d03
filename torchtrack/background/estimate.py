"""Pure functions behind :class:`~torchtrack.background.BackgroundModel`: colour conversion, global gain,
dead-frame detection and the chunked per-pixel statistics (mean/std of empty frames; median/MAD of a moving
sequence with a ghost-reducing second pass).

Memory: frames arrive as one ``(N, C, 3, H, W)`` tensor (any float dtype; the caller may store them as
float16). Every temporary is bounded by :data:`CHUNK_ELEMENTS`: means and gains loop over chunks of frames,
medians loop over chunks of pixel rows (a median needs all frames of a pixel at once).
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Iterator, Sequence

import kornia
import torch

from torchtrack.checks import InputError

#: Images whose every value is below this (or NaN) are "black/dead" frames: no signal from that camera.
BLACK_MAX = 1.0 / 255.0
#: Background pixels whose mean luminance Y is below this are ignored by the gain estimate (ratio unstable).
DARK_Y = 0.04
#: Global gains outside this range are clamped to it, with a warning naming the camera.
GAIN_RANGE = (0.5, 2.0)
#: Scale from the median absolute deviation to the standard deviation of a Gaussian: 1 / Phi^-1(3/4).
MAD_TO_STD = 1.4826
#: Largest number of elements a temporary may hold (about 64 MB in float32).
CHUNK_ELEMENTS = 1 << 24
#: About this many pixels per camera are enough for the gain reference of a moving sequence (a median of ratios).
GAIN_PIXELS = 1 << 15
#: The per-frame gain reads every this-many-th row and column (a median of tens of thousands of ratios is as
#: good as one of all of them, at 1/stride^2 of the cost).
GAIN_STRIDE = 4
#: A pixel's second-pass (ghost-reduced) median needs at least this many frames where it is not foreground.
MIN_CLEAN_FRAMES = 5


# ----------------------------------------------------------------------------------------------- colour


def rgb_to_yuv(images: torch.Tensor, scale: torch.Tensor | None = None) -> torch.Tensor:
    """(..., 3, H, W) RGB -> YUV in :func:`kornia.color.rgb_to_yuv`'s colour space (BT.470 M/PAL; NaN passes
    through), optionally divided by a per-image ``scale``.

    Computed as one 3 x 3 matrix product with kornia's matrix (:func:`rgb_to_yuv_matrix`): kornia converts
    channel by channel, which is several times slower; the values agree to float rounding
    (tests/test_background.py).

    Args:
        images: (..., 3, H, W) RGB.
        scale: (...) per-image divisor (a global gain), folded into the matrix; None: 1.

    Returns:
        (..., 3, H, W) YUV, the dtype and device of ``images``.
    """
    M = torch.tensor(rgb_to_yuv_matrix(), dtype=images.dtype, device=images.device)  # (3, 3)
    if scale is not None:
        M = M / scale.to(images.dtype)[..., None, None]  # (..., 3, 3)
    return (M @ images.flatten(-2)).unflatten(-1, images.shape[-2:])


@functools.cache
def rgb_to_yuv_matrix() -> tuple[tuple[float, ...], ...]:
    """kornia's RGB -> YUV matrix M (``yuv = M @ rgb``), read from kornia by converting the unit vectors."""
    eye = torch.eye(3, dtype=torch.float64).reshape(3, 3, 1, 1)  # (3 images, RGB, 1, 1): image i = e_i
    columns = kornia.color.rgb_to_yuv(eye)[..., 0, 0]  # (3, 3): row i = M e_i
    return tuple(tuple(float(v) for v in row) for row in columns.T)


@functools.cache
def log_uniform_density() -> float:
    """log of the uniform density over the YUV image of the RGB unit cube: ``-log |det M|``."""
    det = torch.linalg.det(torch.tensor(rgb_to_yuv_matrix(), dtype=torch.float64))
    return -math.log(abs(float(det)))


# ----------------------------------------------------------------------------------------------- helpers


def frame_chunks(num_frames: int, elements_per_frame: int) -> Iterator[slice]:
    """Slices of at most ``CHUNK_ELEMENTS // elements_per_frame`` (>= 1) frames covering ``range(num_frames)``."""
    step = max(1, CHUNK_ELEMENTS // max(1, elements_per_frame))
    for s in range(0, num_frames, step):
        yield slice(s, min(s + step, num_frames))


def compute_dtype(x: torch.Tensor) -> torch.dtype:
    """float64 stays float64; every other (half, bfloat16, float32) input is computed in float32."""
    return torch.float64 if x.dtype == torch.float64 else torch.float32


def dead_frames(images: torch.Tensor) -> torch.Tensor:
    """(B, C, 3, H, W) RGB -> (B, C) bool: the frame is all NaN or all black (every value < ``BLACK_MAX``)."""
    out = torch.empty(images.shape[:2], dtype=torch.bool, device=images.device)
    per_frame = images[0, 0].numel() * images.shape[1]
    for s in frame_chunks(images.shape[0], per_frame):
        peak = images[s].nan_to_num(nan=-1.0).amax(dim=(2, 3, 4))  # (b, C)
        out[s] = peak < BLACK_MAX
    return out


def subsample(frames: torch.Tensor, max_frames: int) -> torch.Tensor:
    """At most ``max_frames`` frames of (N, ...), evenly spaced, first and last included (a view when N fits);
    the frames :meth:`~torchtrack.io.sequence.SequenceFolder.sample_frames` reads."""
    from torchtrack.io.sequence import evenly_spaced

    n = frames.shape[0]
    if max_frames < 1:
        raise InputError(f"max_frames must be >= 1, got {max_frames}")
    if n <= max_frames:
        return frames
    return frames[torch.tensor(evenly_spaced(n, max_frames), device=frames.device)]


def check_cameras(dead: torch.Tensor, names: Sequence[str], min_frames: int, what: str) -> None:
    """Raise ``InputError`` naming every camera of ``dead (N, C)`` with fewer than ``min_frames`` usable frames."""
    usable = (~dead).sum(0).tolist()  # (C,)
    bad = [f"'{n}' ({u} of {dead.shape[0]})" for n, u in zip(names, usable) if u < min_frames]
    if bad:
        raise InputError(f"{what}: camera(s) {', '.join(bad)} have fewer than {min_frames} usable frames; the "
                         f"others are all NaN (not decoded) or all black (max < 1/255)")


def floor_and_relax(std: torch.Tensor, min_std: float, luminance_relax: float) -> torch.Tensor:
    """(..., 3, H, W) raw YUV std -> model std: every channel floored at ``min_std``, then Y multiplied by
    ``luminance_relax`` (floor first, so the relaxation is never swallowed by the floor). A NaN std (a pixel
    without data; its mean is NaN too, so its outputs are NaN) gets the floor."""
    std = std.nan_to_num(nan=0.0).clamp_min(min_std)
    scale = torch.tensor([luminance_relax, 1.0, 1.0], dtype=std.dtype, device=std.device)
    return std * scale[:, None, None]


# ----------------------------------------------------------------------------------------------- gain


def robust_gain(y: torch.Tensor, y_ref: torch.Tensor, stride: int = GAIN_STRIDE) -> torch.Tensor:
    """Global gain of each image against a reference: the median over pixels of ``y / y_ref`` (the lower middle
    value for an even count, as :func:`torch.nanmedian`), over every ``stride``-th row and column (a median of
    tens of thousands of ratios is as good as one of all of them, at 1/stride^2 of the cost).

    Pixels where ``y_ref <= DARK_Y`` or either value is NaN are ignored; the body covering a minority of the
    pixels does not move the median.

    Args:
        y: (B, C, H, W) luminance of the images.
        y_ref: (C, H, W) reference (background) luminance.

    Returns:
        (B, C) gain, NaN where no pixel qualifies.
    """
    y, y_ref = y[..., ::stride, ::stride], y_ref[..., ::stride, ::stride]
    ok = y_ref > DARK_Y  # (C, H, W); False for NaN
    ratio = torch.where(ok, y / torch.where(ok, y_ref, 1.0), float("nan"))  # (B, C, H, W)
    return ratio.flatten(2).nanmedian(dim=2).values


def clamp_gain(gain: torch.Tensor, names: Sequence[str], what: str) -> torch.Tensor:
    """Clamp (B, C) gains to ``GAIN_RANGE``, warning once per call with the cameras concerned; NaN stays NaN."""
    lo, hi = GAIN_RANGE
    far = (gain < lo) | (gain > hi)  # (B, C)
    if bool(far.any()):
        cams = [names[c] for c in far.any(0).nonzero()[:, 0].tolist()]
        worst = gain[far]
        warnings.warn(f"{what}: global gain vs the background outside [{lo}, {hi}] (from {float(worst.min()):.3g} "
                      f"to {float(worst.max()):.3g}) for camera(s) {cams}; clamped. Lighting change, camera "
                      "moved, or most of the view covered?", RuntimeWarning, stacklevel=3)
    return gain.clamp(lo, hi)


def sequence_gains(frames: torch.Tensor, dead: torch.Tensor, y_ref: torch.Tensor, names: Sequence[str],
                   what: str) -> torch.Tensor:
    """(N, C, 3, H, W) RGB frames -> (N, C) clamped gains against ``y_ref (C, H, W)``; 1 for dead frames."""
    out = torch.ones(dead.shape, dtype=y_ref.dtype, device=y_ref.device)
    for s in frame_chunks(frames.shape[0], frames[0].numel()):
        y = rgb_to_yuv(frames[s].to(y_ref.dtype))[:, :, 0]  # (n, C, H, W)
        out[s] = robust_gain(y, y_ref)
    out = torch.where(dead, 1.0, out)
    return clamp_gain(out.nan_to_num(nan=1.0), names, what)


# ----------------------------------------------------------------------------------------------- statistics


def _yuv(frames: torch.Tensor, dead: torch.Tensor, gains: torch.Tensor | None, dtype: torch.dtype) -> torch.Tensor:
    """(n, C, 3, h, W) RGB -> YUV in ``dtype``, divided by ``gains (n, C)``, NaN for ``dead (n, C)`` frames."""
    x = rgb_to_yuv(frames.to(dtype))
    if gains is not None:
        x.div_(gains[:, :, None, None, None])
    if bool(dead.any()):
        x.masked_fill_(dead[:, :, None, None, None], float("nan"))
    return x


def nan_mean_std(frames: torch.Tensor, dead: torch.Tensor, gains: torch.Tensor | None,
                 dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel YUV mean and unbiased std over frames, NaN ignored (two passes over chunks of frames).

    Args:
        frames: (N, C, 3, H, W) RGB. dead: (N, C) frames to skip. gains: (N, C) divisors or None.

    Returns:
        mean, std: (C, 3, H, W) in ``dtype``; NaN mean where a pixel has no finite value, std 0 where it has one.
    """
    N = frames.shape[0]
    total = torch.zeros(frames.shape[1:], dtype=dtype, device=frames.device)  # (C, 3, H, W)
    count = torch.zeros_like(total)
    chunks = list(frame_chunks(N, frames[0].numel()))
    for s in chunks:
        x = _yuv(frames[s], dead[s], None if gains is None else gains[s], dtype)  # (n, C, 3, H, W)
        finite = torch.isfinite(x)
        total += x.nan_to_num(nan=0.0).sum(0)
        count += finite.sum(0)
    mean = total / count  # NaN where count == 0
    sq = torch.zeros_like(total)
    for s in chunks:
        x = _yuv(frames[s], dead[s], None if gains is None else gains[s], dtype)
        sq += (x - mean).square().nan_to_num(nan=0.0).sum(0)
    std = (sq / (count - 1).clamp_min(1)).sqrt()
    return mean, std


def _row_chunks(frames: torch.Tensor) -> Iterator[slice]:
    N, C, _, H, W = frames.shape
    step = max(1, CHUNK_ELEMENTS // (N * C * 3 * W))
    for r in range(0, H, step):
        yield slice(r, min(r + step, H))


def median_mad(frames: torch.Tensor, dead: torch.Tensor, gains: torch.Tensor | None, dtype: torch.dtype,
               foreground: torch.Tensor | None = None, pixels: torch.Tensor | None = None,
               spread: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-pixel temporal median and robust std (``MAD_TO_STD * MAD``) of YUV, chunked over pixel rows.

    NaN values are ignored; for an even count the lower median is taken (as :func:`torch.nanmedian`).

    Args:
        frames: (N, C, 3, H, W) RGB. dead: (N, C) frames to skip. gains: (N, C) divisors or None.
        foreground: (N, C, H, W) bool, pixels to leave out (treated like NaN), or None.
        pixels: (C, H, W) bool, the only pixels to compute (the others get NaN and count 0), or None for all.
        spread: False skips the MAD (the robust std is then NaN).

    Returns:
        median, robust_std: (C, 3, H, W) in ``dtype`` (NaN where no frame is left); count: (C, H, W) frames used.
    """
    N, C, _, H, W = frames.shape
    med = torch.full((C, H, W, 3), float("nan"), dtype=dtype, device=frames.device)  # channels last while filling
    std = torch.full_like(med, float("nan"))
    count = torch.zeros((C, H, W), dtype=torch.long, device=frames.device)
    for r in _row_chunks(frames):
        x = _yuv(frames[:, :, :, r], dead, gains, dtype)  # (N, C, 3, h, W)
        if foreground is not None:
            x.masked_fill_(foreground[:, :, None, r], float("nan"))
        x = x.permute(1, 3, 4, 2, 0)  # (C, h, W, 3, N)
        if pixels is None:
            v = x.reshape(-1, 3, N)  # (P, 3, N) copy with frames last: the fast layout for nanmedian
            put = med[:, r], std[:, r], count[:, r]  # basic-slice views, filled through .view_as below
        else:
            sel = pixels[:, r]  # (C, h, W)
            if not bool(sel.any()):
                continue
            v = x[sel]  # (P, 3, N)
        m, s, n = nan_median_mad(v, spread)
        if pixels is None:
            put[0].copy_(m.view_as(put[0]))
            if spread:
                put[1].copy_(s.view_as(put[1]))
            put[2].copy_(n.view_as(put[2]))
        else:
            med[:, r][sel] = m
            if spread:
                std[:, r][sel] = s
            count[:, r][sel] = n
    return med.permute(0, 3, 1, 2).contiguous(), std.permute(0, 3, 1, 2).contiguous(), count


def nan_median_mad(values: torch.Tensor, spread: bool = True
                   ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """(P, 3, N) YUV values, frames last (NaN: left out) -> median (P, 3), robust std ``MAD_TO_STD * MAD`` (P, 3)
    or None without ``spread``, and the frames used (P,) (a pixel's frames are left out in all channels at once).
    With ``spread`` the values are overwritten by their distances to the median (no second array that size)."""
    n = values.shape[-1] - values[:, 0].isnan().sum(-1)
    m = values.nanmedian(dim=-1).values
    s = MAD_TO_STD * values.sub_(m[..., None]).abs_().nanmedian(dim=-1).values if spread else None
    return m, s, n


def frames_last_yuv(frames: torch.Tensor, dead: torch.Tensor, gains: torch.Tensor | None,
                    dtype: torch.dtype) -> torch.Tensor:
    """(N, C, 3, H, W) RGB -> (C, H, W, 3, N) YUV in ``dtype`` (as :func:`median_mad` reads it: gains divided out,
    NaN for dead frames), frames last: the layout :func:`nan_median_mad` is fast on, to index pixels from."""
    N, C, _, H, W = frames.shape
    out = torch.empty((C, H, W, 3, N), dtype=dtype, device=frames.device)
    for r in _row_chunks(frames):
        out[:, r] = _yuv(frames[:, :, :, r], dead, gains, dtype).permute(1, 3, 4, 2, 0)
    return out


def dilate(mask: torch.Tensor, radius_px: int) -> torch.Tensor:
    """Binary dilation of ``mask (..., H, W)`` bool by a square of half side ``radius_px`` (separable ORs of
    shifted copies: several times faster than ``max_pool2d`` on CPU, and exact)."""
    out = mask
    for dim in (-1, -2):
        src, out = out, out.clone()
        n = src.shape[dim]
        for s in range(1, min(radius_px, n - 1) + 1):
            out.narrow(dim, s, n - s).logical_or_(src.narrow(dim, 0, n - s))
            out.narrow(dim, 0, n - s).logical_or_(src.narrow(dim, s, n - s))
    return out


def foreground_masks(frames: torch.Tensor, dead: torch.Tensor, gains: torch.Tensor | None, mean: torch.Tensor,
                     std: torch.Tensor, threshold: float, dilate_px: int) -> torch.Tensor:
    """(N, C, 3, H, W) RGB -> (N, C, H, W) bool: squared Mahalanobis distance to (mean, std) (C, 3, H, W) above
    ``threshold``, dilated by a square of half side ``dilate_px``; False for dead frames."""
    N, C, _, H, W = frames.shape
    out = torch.empty((N, C, H, W), dtype=torch.bool, device=frames.device)
    for s in frame_chunks(N, frames[0].numel()):
        x = _yuv(frames[s], dead[s], None if gains is None else gains[s], mean.dtype)  # (n, C, 3, H, W)
        out[s] = dilate(((x - mean) / std).square().sum(2) > threshold, dilate_px)  # NaN -> False
    return out
