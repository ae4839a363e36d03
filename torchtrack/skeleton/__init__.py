"""Skeleton: the URDF body chain (pytorch-kinematics), landmarks, subject scaling."""

from torchtrack.skeleton.model import FKResult, Skeleton, root_rotation_angles, root_rotation_matrix

__all__ = ["FKResult", "Skeleton", "root_rotation_angles", "root_rotation_matrix"]
