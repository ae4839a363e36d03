"""torchtrack: 3D human motion tracking from several calibrated cameras, as batched PyTorch code.

Conventions (see :mod:`torchtrack.conventions`): world Z up, metres, radians, OpenCV cameras
(``x_cam = R_cam_world @ x_world + t_cam_world``), images as float ``(C, 3, H, W)`` RGB in [0, 1].
"""

__version__ = "0.1.0"


def __getattr__(name: str):
    """``torchtrack.track`` and ``torchtrack.track_many``: :func:`torchtrack.tracking.pipeline.track` and
    :func:`~torchtrack.tracking.pipeline.track_many`, imported on first use (they need torch, which ``import
    torchtrack`` does not load)."""
    if name in ("track", "track_many"):
        from torchtrack.tracking import pipeline

        return getattr(pipeline, name)
    raise AttributeError(f"module 'torchtrack' has no attribute {name!r}")
