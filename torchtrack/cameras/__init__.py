"""Calibrated cameras: :class:`CameraRig` (projection, rays) and calibration files (load, save, convert).

OpenCV is imported lazily inside the file readers, never at package import.
"""

from torchtrack.cameras.calib_io import load_calibration, save_calibration
from torchtrack.cameras.rig import CameraRig

__all__ = ["CameraRig", "load_calibration", "save_calibration"]
