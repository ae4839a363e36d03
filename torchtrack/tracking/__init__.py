"""Tracking: per-frame loops of the trackers and pictures of their results (no I/O)."""
