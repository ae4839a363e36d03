"""2D body keypoints for the start of a markerless track: detection, multi-view triangulation, the fitted start."""
