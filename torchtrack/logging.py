"""TensorBoard logging of a tracking run: scalars, occupancy point clouds, camera and probability images.

TensorBoard is imported when a :class:`RunLogger` is created, never when this module is imported
(DESIGN.md: no TensorBoard import at package import time). Tags are TensorBoard's: ``/`` groups them in the UI.

Images are written as uint8 PNG (values in [0, 1] scaled by 255 and rounded); NaN pixels (unreadable frames)
are drawn black in camera images and grey in probability images. Point clouds go through the mesh plugin
(vertices and optional per-vertex colours, no faces).
"""

from __future__ import annotations

import math
import operator
from collections.abc import Sequence
from pathlib import Path
from types import TracebackType

import torch

from torchtrack.checks import InputError, check_finite, check_shape

__all__ = ["RunLogger", "apply_colour_map", "VIRIDIS_RGB", "subsample_indices", "tile_images"]

#: Five evenly spaced samples of matplotlib's "viridis" colour map (RGB in [0, 1]), linearly interpolated by
#: :func:`apply_colour_map`. Hand-written because matplotlib is not a dependency.
VIRIDIS_RGB: tuple[tuple[float, float, float], ...] = (
    (0.267, 0.005, 0.329), (0.229, 0.322, 0.546), (0.128, 0.567, 0.551), (0.369, 0.789, 0.383),
    (0.993, 0.906, 0.144),
)

#: Colour of NaN values in colour-mapped images.
NAN_RGB: tuple[float, float, float] = (0.5, 0.5, 0.5)


def apply_colour_map(values: torch.Tensor, anchors_rgb: Sequence[Sequence[float]] = VIRIDIS_RGB,
                     nan_rgb: Sequence[float] = NAN_RGB) -> torch.Tensor:
    """Map values in [0, 1] to RGB by piecewise-linear interpolation between evenly spaced anchor colours.

    Args:
        values: (...) values; clamped to [0, 1], NaN drawn as ``nan_rgb``.
        anchors_rgb: K >= 2 RGB colours for the values 0, 1/(K-1), ..., 1.

    Returns:
        (..., 3) RGB in [0, 1], float, on the device of ``values``.
    """
    dtype = values.dtype if values.is_floating_point() else torch.float32
    anchors = torch.as_tensor(anchors_rgb, dtype=dtype, device=values.device)  # (K, 3)
    if anchors.ndim != 2 or anchors.shape[0] < 2 or anchors.shape[1] != 3:
        raise InputError(f"anchors_rgb: expected K >= 2 RGB colours, got shape {tuple(anchors.shape)}")
    K = anchors.shape[0]
    x = values.to(dtype)
    nan = torch.isnan(x)
    pos = torch.nan_to_num(x, nan=0.0).clamp(0.0, 1.0) * (K - 1)  # (...) position along the anchors
    lo = pos.floor().long().clamp(max=K - 2)  # (...) left anchor of the segment
    frac = (pos - lo.to(dtype)).unsqueeze(-1)  # (..., 1)
    rgb = anchors[lo] * (1 - frac) + anchors[lo + 1] * frac  # (..., 3)
    nan_colour = torch.as_tensor(nan_rgb, dtype=dtype, device=values.device)
    return torch.where(nan.unsqueeze(-1), nan_colour, rgb)


def subsample_indices(n: int, max_points: int) -> torch.Tensor:
    """Deterministic, evenly spread subset of ``range(n)``: all of it when ``n <= max_points``.

    Returns:
        (min(n, max_points),) int64 strictly increasing indices.
    """
    if max_points < 1:
        raise InputError(f"max_points must be >= 1, got {max_points}")
    m = min(n, max_points)
    return torch.arange(m, dtype=torch.int64) * n // m if m else torch.zeros(0, dtype=torch.int64)


def tile_images(images: torch.Tensor, columns: int | None = None) -> torch.Tensor:
    """Tile camera images row-major into one picture (black where the last row is short).

    Args:
        images: (C, 3, H, W).
        columns: images per row (default ``ceil(sqrt(C))``).

    Returns:
        (3, rows * H, columns * W) with ``rows = ceil(C / columns)``.
    """
    check_shape(images, ("C", 3, "H", "W"), "images")
    C, _, H, W = images.shape
    cols = columns or math.ceil(math.sqrt(C))
    if cols < 1:
        raise InputError(f"columns must be >= 1, got {cols}")
    rows = math.ceil(C / cols)
    canvas = images.new_zeros(rows * cols, 3, H, W)
    canvas[:C] = images
    # (rows, cols, 3, H, W) -> (3, rows, H, cols, W)
    return canvas.reshape(rows, cols, 3, H, W).permute(2, 0, 3, 1, 4).reshape(3, rows * H, cols * W)


def _to_uint8(values: torch.Tensor, nan: float) -> torch.Tensor:
    """(...) float in [0, 1] (clamped) -> (...) uint8 0..255 on the CPU; NaN -> ``nan``."""
    x = torch.nan_to_num(values.detach().float(), nan=nan).clamp(0.0, 1.0)
    return (x * 255 + 0.5).to(torch.uint8).cpu()


class RunLogger:
    """Writes a run's diagnostics to a TensorBoard event file under ``log_dir``.

    Use as a context manager (or call :meth:`close`)::

        with RunLogger("runs/walk") as run:
            run.scalars(step, em_iterations=12, ik_residual_m=0.004)
            run.occupancy_cloud(step, "occupancy/bayes", centres_m, None)  # (N, 3) occupied voxel centres
            run.camera_images(step, "frames", images, rig.names)

    Args:
        log_dir: folder of the event files (created if absent).
        flush_secs: how often pending events are written to disk.
    """

    def __init__(self, log_dir: str | Path, flush_secs: int = 10) -> None:
        from torch.utils.tensorboard import SummaryWriter  # lazy: TensorBoard only when logging

        self.log_dir = Path(log_dir)
        self._writer = SummaryWriter(log_dir=str(self.log_dir), flush_secs=flush_secs)

    # ------------------------------------------------------------------------------------------ scalars
    def scalars(self, step: int, **values: float | torch.Tensor) -> None:
        """One scalar per keyword at ``step``; the keyword is the tag, ``__`` in it stands for ``/``.

        ``run.scalars(3, loss__em=0.2)`` writes tag ``loss/em``. Values are numbers or one-element tensors.
        """
        step = _check_step(step)
        for name, value in values.items():
            if isinstance(value, torch.Tensor):
                if value.numel() != 1:
                    raise InputError(f"scalar {name!r}: expected one value, got a tensor of shape "
                                     f"{tuple(value.shape)}")
                value = value.detach().cpu().reshape(()).item()
            self._writer.add_scalar(name.replace("__", "/"), float(value), global_step=step)

    # ------------------------------------------------------------------------------------------ 3D
    def occupancy_cloud(self, step: int, tag: str, centres: torch.Tensor, colours: torch.Tensor | None = None,
                        max_points: int = 50_000) -> None:
        """Occupied voxels as a point cloud (TensorBoard mesh plugin: vertices and colours, no faces).

        Args:
            centres: (N, 3) voxel centres, world metres.
            colours: (N, 3) RGB in [0, 1] (clamped), or None for TensorBoard's default colour.
            max_points: beyond this, an evenly spread deterministic subset (:func:`subsample_indices`) is kept.

        Writes tags ``{tag}_VERTEX`` and (with colours) ``{tag}_COLOR``, shapes (1, n, 3), n <= max_points.
        """
        step = _check_step(step)
        check_shape(centres, ("N", 3), "centres")
        check_finite(centres, "centres")
        N = centres.shape[0]
        if colours is not None:
            check_shape(colours, (N, 3), "colours")
        keep = subsample_indices(N, max_points).to(centres.device)  # (n,)
        vertices = centres.detach()[keep].float().cpu()[None]  # (1, n, 3)
        rgb = None
        if colours is not None:
            # uint8 0..255: the mesh plugin's viewer divides colours by 255.
            rgb = _to_uint8(colours[keep.to(colours.device)], nan=0.0)[None]  # (1, n, 3)
        self._writer.add_mesh(tag, vertices=vertices, colors=rgb, global_step=step)

    def pose_cloud(self, step: int, tag: str, voxel_centres: torch.Tensor, landmarks: torch.Tensor,
                   voxel_colours: torch.Tensor | None = None, points_per_bone: int = 20,
                   max_voxels: int = 50_000) -> None:
        """Voxels and a skeleton as one coloured point cloud (mesh plugin), to see the pose inside the occupancy.

        Args:
            voxel_centres: (V, 3) occupied voxel centres, world metres.
            landmarks: (J, 3) world positions of LANDMARKS (J = 16); non-finite ones (lost) leave their bones out.
            voxel_colours: (V, 3) RGB in [0, 1], or None for grey (:data:`torchtrack.tracking.draw.VOXEL_RGB`).
            points_per_bone: points along each bone (:func:`torchtrack.tracking.draw.skeleton_cloud`), coloured
                by body side.
            max_voxels: beyond this, an evenly spread deterministic subset of the voxels
                (:func:`subsample_indices`); the skeleton is always kept whole.

        Writes tags ``{tag}_VERTEX`` and ``{tag}_COLOR``, shapes (1, v + P, 3): the v kept voxels, then the
        P skeleton points.
        """
        from torchtrack.tracking.draw import VOXEL_RGB, skeleton_cloud  # lazy: it imports the cameras

        check_shape(voxel_centres, ("V", 3), "voxel_centres")
        check_finite(voxel_centres, "voxel_centres")
        V = voxel_centres.shape[0]
        if voxel_colours is None:
            voxel_colours = voxel_centres.new_tensor(VOXEL_RGB).expand(V, 3)
        check_shape(voxel_colours, (V, 3), "voxel_colours")
        bone_points, bone_colours = skeleton_cloud(landmarks.detach(), points_per_bone)  # (P, 3), (P, 3)
        finite = torch.isfinite(bone_points).all(-1)  # (P,)
        keep = subsample_indices(V, max_voxels).to(voxel_centres.device)  # (v,)
        points = torch.cat([voxel_centres.detach()[keep].float().cpu(), bone_points[finite].float().cpu()])
        colours = torch.cat([voxel_colours.detach()[keep.to(voxel_colours.device)].float().cpu(),
                             bone_colours[finite].float().cpu()])
        self.occupancy_cloud(step, tag, points, colours, max_points=max(points.shape[0], 1))

    # ------------------------------------------------------------------------------------------ images
    def camera_images(self, step: int, tag: str, images: torch.Tensor, names: Sequence[str],
                      grid: bool = False) -> None:
        """Camera frames, one image per camera (tags ``{tag}/{name}``) or all tiled into one (tag ``tag``).

        Args:
            images: (C, 3, H, W) RGB in [0, 1] (clamped; NaN drawn black).
            names: C camera names.
            grid: tile the cameras row-major (:func:`tile_images`) into one image.
        """
        step = _check_step(step)
        check_shape(images, (len(names), 3, "H", "W"), "images")
        self._images(step, tag, _to_uint8(images, nan=0.0), names, grid)

    def probability_images(self, step: int, tag: str, prob: torch.Tensor, names: Sequence[str],
                           grid: bool = False) -> None:
        """Per-camera foreground probability, colour-mapped (:data:`VIRIDIS_RGB`: dark blue 0 to yellow 1).

        Args:
            prob: (C, H, W) probabilities in [0, 1] (clamped; NaN drawn grey).
            names: C camera names.
            grid: as in :meth:`camera_images`.
        """
        step = _check_step(step)
        check_shape(prob, (len(names), "H", "W"), "prob")
        rgb = apply_colour_map(prob.detach().float()).permute(0, 3, 1, 2)  # (C, 3, H, W)
        self._images(step, tag, _to_uint8(rgb, nan=0.0), names, grid)

    def _images(self, step: int, tag: str, images_u8: torch.Tensor, names: Sequence[str], grid: bool) -> None:
        """images_u8: (C, 3, H, W) uint8 on the CPU."""
        if len(set(names)) != len(names) or not all(isinstance(n, str) and n for n in names):
            raise InputError(f"names must be unique non-empty strings, got {list(names)!r}")
        if grid:
            self._writer.add_image(tag, tile_images(images_u8), global_step=step, dataformats="CHW")
            return
        for name, image in zip(names, images_u8):
            self._writer.add_image(f"{tag}/{name}", image, global_step=step, dataformats="CHW")

    # ------------------------------------------------------------------------------------------ lifetime
    def flush(self) -> None:
        """Write pending events to disk."""
        self._writer.flush()

    def close(self) -> None:
        """Flush and close the event file (idempotent)."""
        self._writer.close()

    def __enter__(self) -> RunLogger:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def _check_step(step: int) -> int:
    """``step`` as a Python int (numpy and 0-d integer tensors accepted); InputError unless an integer >= 0."""
    try:
        value = operator.index(step) if not isinstance(step, bool) else -1
    except TypeError:
        value = -1
    if value < 0:
        raise InputError(f"step must be a non-negative integer, got {step!r}")
    return value
