"""Skeleton: the URDF body chain (pytorch-kinematics), landmarks, subject scaling."""

from torchtrack.skeleton.model import FKResult, Skeleton, fit_states, root_rotation_angles, root_rotation_matrix

__all__ = ["FKResult", "Skeleton", "fit_states", "root_rotation_angles", "root_rotation_matrix"]
