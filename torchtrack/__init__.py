"""torchtrack: 3D human motion tracking from several calibrated cameras, as batched PyTorch code.

Conventions (see :mod:`torchtrack.conventions`): world Z up, metres, radians, OpenCV cameras
(``x_cam = R_cam_world @ x_world + t_cam_world``), images as float ``(C, 3, H, W)`` RGB in [0, 1].
"""

__version__ = "0.1.0"


def __getattr__(name: str):
    """``torchtrack.track``: :func:`torchtrack.tracking.pipeline.track`, imported on first use (it needs torch,
    which ``import torchtrack`` does not load)."""
    if name == "track":
        from torchtrack.tracking.pipeline import track

        return track
    raise AttributeError(f"module 'torchtrack' has no attribute {name!r}")
