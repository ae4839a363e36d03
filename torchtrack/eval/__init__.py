"""Pose accuracy: frame matching, MPJPE (plain and root-aligned), PCK and an evaluation report."""

from torchtrack.eval.metrics import (DEFAULT_PCK_THRESHOLDS_M, MPJPE, EvalReport, evaluate, joint_errors,
                                     match_frames, mpjpe, pck, root_relative)

__all__ = ["DEFAULT_PCK_THRESHOLDS_M", "MPJPE", "EvalReport", "evaluate", "joint_errors", "match_frames", "mpjpe",
           "pck", "root_relative"]
