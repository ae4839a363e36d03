"""Marker-based capture (Canton-Ferrer et al. 2010): the detection simulator, the colour marker detector, the
subject's marker set, robust triangulation and the tracking driver (the annealed particle filter itself is
:mod:`torchtrack.tracking.particles`; formats: docs/formats.md, ``markers2d.npz``)."""

from torchtrack.markers.simulate import DetectorModel, Detections, marker_visibility, simulate_detections

__all__ = ["DetectorModel", "Detections", "marker_visibility", "simulate_detections"]
