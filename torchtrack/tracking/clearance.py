"""Where the tracked body is seen in each view, and how clear of it each pixel is in each frame: the masks from
which the background refinement (:mod:`torchtrack.tracking.refine`) re-estimates each pixel's background.

:func:`body_masks` renders the blobs' ellipsoids as exact ray hits through the lens model
(:func:`~torchtrack.ellipsoids.rays_meet_ellipsoids`); :func:`clearance_px` measures each pixel's distance to them;
:func:`clear_frame_masks` keeps each pixel its clearest frames.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from torchtrack.blobs import BlobModel
from torchtrack.cameras import CameraRig
from torchtrack.checks import InputError, ShapeError, check_shape
from torchtrack.ellipsoids import rays_meet_ellipsoids
from torchtrack.skeleton import Skeleton

__all__ = ["PixelTiles", "body_masks", "clear_frame_masks", "clearance_px", "stays_near"]


class PixelTiles:
    """A rig's pixel rays (through the lens model, :meth:`CameraRig.pixel_rays`) ordered in 8 x 8 tiles, as
    :func:`body_masks` tests them: made once for the many masks of a background refinement (undistorting every
    pixel costs as much as testing it).

    Attributes:
        origins, dirs: (C, 3) and (C, th * tw * 64, 3); size: (H, W); tiles: (th, tw) the image padded to whole
            tiles (the padding repeats the last column and row: a ray from outside the image may not undistort).
    """

    def __init__(self, rig: CameraRig) -> None:
        if bool((rig.image_size_wh != rig.image_size_wh[0]).any()):
            raise InputError("body_masks: the cameras must share one image size")
        device = rig.K.device
        W, H = (int(v) for v in rig.image_size_wh[0].tolist())
        th, tw = -(-H // 8), -(-W // 8)
        ty, tx, iy, ix = torch.meshgrid(*(torch.arange(n, device=device) for n in (th, tw, 8, 8)), indexing="ij")
        u, v = (tx * 8 + ix).clamp(max=W - 1), (ty * 8 + iy).clamp(max=H - 1)
        uv = torch.stack([u, v], -1).reshape(1, -1, 2).float().expand(len(rig), -1, -1)
        origins, self.dirs = rig.pixel_rays(uv)  # (C, th * tw * 64, 3)
        self.origins, self.size, self.tiles = origins[:, 0], (H, W), (th, tw)


def body_masks(rig: CameraRig, skeleton: Skeleton, angles: torch.Tensor, blob_scale: float = 1.0,
               blobs: BlobModel | None = None, tiles: PixelTiles | None = None,
               bones: Sequence[str] | None = None) -> torch.Tensor:
    """Where the body of the blob model is seen: the union of its ellipsoids in every view.

    A pixel is set when its ray (through the lens model, :meth:`CameraRig.pixel_rays`) meets an ellipsoid in
    front of the camera (:func:`rays_meet_ellipsoids`).

    Args:
        rig: the cameras at the size of the masks (one size for all).
        skeleton: the subject's skeleton.
        blobs: its blob model (the tracker's ``subject.blobs``; default: blobs.yaml on ``skeleton``).
        angles: (T, D) state vectors; a frame with a non-finite value (an untracked frame) gives a mask that is
            set everywhere (the body may be anywhere).
        blob_scale: the ellipsoids' semi-axes are multiplied by this.
        tiles: ``PixelTiles(rig)``, made once for many calls on one rig (default: made here).
        bones: only the blobs of these bones (default: all).

    Returns:
        (T, C, H, W) bool on the rig's device.
    """
    check_shape(angles, ("T", skeleton.num_dofs), "angles")
    tiles = PixelTiles(rig) if tiles is None else tiles  # rays_meet_ellipsoids' bundles of 64 rays are its tiles
    W0, H0 = (int(v) for v in rig.image_size_wh[0].tolist())
    if tiles.size != (H0, W0) or tiles.dirs.shape[0] != len(rig):
        raise InputError(f"body_masks: the pixel tiles are of {tiles.dirs.shape[0]} cameras at {tiles.size[1]}x"
                         f"{tiles.size[0]}, the rig has {len(rig)} at {W0}x{H0}")
    origins, dirs, (H, W), (th, tw) = tiles.origins, tiles.dirs, tiles.size, tiles.tiles
    device = rig.K.device
    skeleton = skeleton.to(device)
    blobs = (BlobModel.from_config(skeleton) if blobs is None else blobs).to(device)
    T, C = angles.shape[0], len(rig)
    angles = angles.to(device, torch.float32)
    out = torch.ones((T, C, th * tw * 64), dtype=torch.bool, device=device)
    ok = torch.isfinite(angles).all(-1)
    if bool(ok.any()):
        centres, R = blobs.ellipsoids(skeleton.forward(angles[ok]).bone_frames)  # (T', K, 3), (T', K, 3, 3)
        axes = (blobs.semi_axes * blob_scale).to(origins.dtype)
        if bones is not None:
            keep = torch.tensor([k for k, b in enumerate(blobs.bone_of_blob.tolist())
                                 if skeleton.bone_names[b] in bones], dtype=torch.long, device=device)
            centres, R, axes = centres[:, keep], R[:, keep], axes[keep]
        out[ok] = rays_meet_ellipsoids(origins, dirs, centres.to(origins.dtype), R.to(origins.dtype), axes,
                                       bundle=64)
    tiles = out.view(T, C, th, tw, 8, 8).permute(0, 1, 2, 4, 3, 5)  # (T, C, th, 8, tw, 8)
    return tiles.reshape(T, C, th * 8, tw * 8)[..., :H, :W].contiguous()


def clearance_px(masks: torch.Tensor, within_px: float = math.inf) -> torch.Tensor:
    """(..., H, W) bool -> (..., H, W) float32 Euclidean distance in pixels from each pixel to the nearest set
    pixel of its own image (0 on the mask; ``inf`` in an image with no set pixel). Only the distances up to
    ``within_px`` are needed: each image's are computed within its mask's bounding box grown by that much, and
    are ``inf`` outside it (where they are over ``within_px``). OpenCV's exact transform (``DIST_MASK_PRECISE``)."""
    import cv2

    check_shape(masks, ("...", "H", "W"), "masks")
    if not within_px > 0:
        raise InputError(f"clearance_px: within_px must be > 0, got {within_px}")
    flat = masks.reshape(-1, *masks.shape[-2:]).cpu().numpy()
    H, W = flat.shape[1:]
    grow = math.ceil(within_px) + 1 if math.isfinite(within_px) else max(H, W)
    out = np.full(flat.shape, np.inf, np.float32)
    for i, m in enumerate(flat):
        rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
        if rows.size:
            y0, y1 = max(rows[0] - grow, 0), min(rows[-1] + 1 + grow, H)
            x0, x1 = max(cols[0] - grow, 0), min(cols[-1] + 1 + grow, W)
            free = (~m[y0:y1, x0:x1]).astype(np.uint8)  # the transform measures to the nearest zero pixel
            out[i, y0:y1, x0:x1] = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return torch.from_numpy(out).reshape(masks.shape).to(masks.device)


def clear_frame_masks(clearance: torch.Tensor, clear_frames: int, clear_px: float, near_px: float = 0.0
                      ) -> torch.Tensor:
    """Subject masks that leave each pixel its clearest frames.

    Args:
        clearance: (N, ..., H, W) each pixel's distance to the body in each of N frames (those over
            ``max(clear_px, near_px)`` may be any larger value: :func:`clearance_px`'s ``within_px``).
        clear_frames: k: each pixel keeps at least its k clearest frames (all of them when N <= k), ties
            included, but never a frame where it is on the body (clearance 0).
        clear_px: frames at least this clear are all kept.
        near_px: a pixel with fewer than k frames (k as above: all N when N <= k) at least this clear of the body
            (its k-th clearest frame nearer) keeps none (0: off), so that the caller's fallback
            (``BackgroundModel.from_sequence``: passes 1-3) decides it.

    Returns:
        (N, ..., H, W) bool, True where a frame is not used for a pixel's background.
    """
    kth = _kth_clearest(clearance, clear_frames)
    threshold = torch.clamp(torch.minimum(kth, torch.tensor(clear_px, dtype=kth.dtype, device=kth.device)),
                            min=torch.finfo(kth.dtype).tiny)
    out = clearance < threshold
    if near_px > 0:
        out |= (kth < near_px)[None]
    return out


def stays_near(clearance: torch.Tensor, clear_frames: int, near_px: float) -> torch.Tensor:
    """(..., H, W) bool: the pixels with fewer than k frames (all N when N <= k) at least ``near_px`` clear of
    the body, ``clearance (N, ..., H, W)`` as for :func:`clear_frame_masks` (its ``near_px`` rule on its own)."""
    return _kth_clearest(clearance, clear_frames) < near_px


def _kth_clearest(clearance: torch.Tensor, clear_frames: int) -> torch.Tensor:
    """(..., H, W) each pixel's k-th largest clearance over the N frames, k = min(clear_frames, N)."""
    if clearance.dim() < 3:
        raise ShapeError(f"clearance: expected shape (N, ..., H, W), got {tuple(clearance.shape)}")
    return clearance.topk(min(clear_frames, clearance.shape[0]), dim=0).values[-1]
