"""Skeleton: the URDF body chain (pytorch-kinematics), landmarks, subject scaling."""

from torchtrack.skeleton.model import FKResult, Skeleton

__all__ = ["FKResult", "Skeleton"]
