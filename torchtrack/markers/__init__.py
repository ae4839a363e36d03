"""Marker-based capture (Canton-Ferrer et al. 2010): the detection simulator so far; the marker set model, the
colour detector and the annealed particle filter follow (docs/formats.md, ``markers2d.npz``)."""

from torchtrack.markers.simulate import DetectorModel, Detections, marker_visibility, simulate_detections

__all__ = ["DetectorModel", "Detections", "marker_visibility", "simulate_detections"]
