"""Pose accuracy metrics: frame matching, MPJPE, PCK and an evaluation report of a prediction against a reference.

Everything here works on numpy arrays (what ``torchtrack.io.poses.Poses`` holds): evaluation is an offline,
IO-side step over whole sequences, so there is nothing to batch on a device. Positions are in metres, errors
are Euclidean distances per joint; the report gives them in millimetres.

Missing data
    * A reference joint with a NaN coordinate (a keypoint the reference lacks) is left out of every figure for
      that frame; a reference frame marked invalid counts as having no reference at all.
    * A frame the prediction marks invalid is *lost*: it is left out of MPJPE and PCK and counted separately.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from torchtrack.checks import InputError, ShapeError
from torchtrack.conventions import LANDMARKS
from torchtrack.io.poses import Poses

log = logging.getLogger(__name__)

DEFAULT_PCK_THRESHOLDS_M: tuple[float, ...] = (0.05, 0.10, 0.15)
#: MMTA's threshold (Canton-Ferrer's T): a marker estimate within 5 cm of the truth matches.
DEFAULT_MARKER_THRESHOLD_M = 0.05


class MPJPE(NamedTuple):
    """Mean per-joint position error, in the unit of the inputs.

    ``per_joint`` (J,) mean over frames, ``per_frame`` (T,) mean over joints, ``mean`` over all (frame, joint)
    pairs evaluated. NaN where nothing was evaluated (masked-out frames, joints never in the reference).
    """

    per_joint: np.ndarray
    per_frame: np.ndarray
    mean: float


def match_frames(pred: Poses, truth: Poses, pred_name: str = "prediction",
                 truth_name: str = "ground truth") -> tuple[np.ndarray, np.ndarray]:
    """Indices of the frames both sequences hold, matched by ``frame_index`` (source frame number).

    Returns:
        ``(pred_idx, truth_idx)``, each (N,) int64, in increasing frame number:
        ``pred.frame_index[pred_idx] == truth.frame_index[truth_idx]``.

    Raises:
        InputError: a ``frame_index`` repeats a frame number, or the two have no frame in common (naming both).
    """
    for poses, name in ((pred, pred_name), (truth, truth_name)):
        values, counts = np.unique(poses.frame_index, return_counts=True)
        if (counts > 1).any():
            raise InputError(f"{name}: field 'frame_index' repeats frame {int(values[counts > 1][0])}")
    _, pred_idx, truth_idx = np.intersect1d(pred.frame_index, truth.frame_index, return_indices=True)
    if pred_idx.size == 0:
        raise InputError(f"no frame in common between {pred_name} (frames {_span(pred.frame_index)}) "
                         f"and {truth_name} (frames {_span(truth.frame_index)})")
    return pred_idx.astype(np.int64), truth_idx.astype(np.int64)


def joint_errors(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Euclidean distance per frame and joint.

    Args:
        pred: (T, J, 3) predicted positions; must be finite in the frames of ``mask``.
        truth: (T, J, 3) reference positions; NaN marks a missing keypoint.
        mask: (T,) bool, frames to evaluate (default: all).

    Returns:
        (T, J) float64 errors; NaN where the frame is masked out or the reference joint is missing.
    """
    pred = np.asarray(pred, dtype=np.float64)
    truth = np.asarray(truth, dtype=np.float64)
    if pred.ndim != 3 or pred.shape[-1] != 3 or truth.shape != pred.shape:
        raise ShapeError(f"pred, truth: expected two arrays of shape (T, J, 3), got {pred.shape} and {truth.shape}")
    mask = np.ones(pred.shape[0], dtype=bool) if mask is None else np.asarray(mask)
    if mask.dtype != bool or mask.shape != pred.shape[:1]:
        raise ShapeError(f"mask: expected a bool array of shape ({pred.shape[0]},), got {mask.dtype} {mask.shape}")
    bad = ~np.isfinite(pred[mask])
    if bad.any():
        raise InputError(f"pred: {int(bad.sum())} values are NaN or infinite in frames to evaluate")
    err = np.linalg.norm(pred - truth, axis=-1)  # (T, J), NaN where truth is
    err[~mask] = np.nan
    return err


def mpjpe(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> MPJPE:
    """Mean per-joint position error of ``pred`` (T, J, 3) against ``truth`` (T, J, 3) in the frames of
    ``mask`` (T,) bool (default: all); NaN reference joints are left out. See :class:`MPJPE`."""
    err = joint_errors(pred, truth, mask)  # (T, J)
    return MPJPE(per_joint=_nanmean(err, axis=0), per_frame=_nanmean(err, axis=1), mean=float(_nanmean(err)))


def pck(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None,
        thresholds_m: float | Sequence[float] = 0.1) -> np.ndarray:
    """Percentage of correct keypoints: the fraction of evaluated (frame, joint) pairs whose error is at most
    each threshold.

    Args:
        pred, truth, mask: as in :func:`joint_errors`.
        thresholds_m: one threshold or (N,) thresholds, in the unit of the inputs (metres).

    Returns:
        Fractions in [0, 1], shaped like ``thresholds_m`` (a 0-d array for one threshold); NaN if nothing
        was evaluated.
    """
    thresholds = np.asarray(thresholds_m, dtype=np.float64)
    if thresholds.ndim > 1 or not (np.isfinite(thresholds) & (thresholds > 0)).all():
        raise InputError(f"PCK thresholds must be positive numbers, got {thresholds_m}")
    err = joint_errors(pred, truth, mask)
    err = err[np.isfinite(err)]  # (E,)
    if err.size == 0:
        return np.full(thresholds.shape, np.nan)
    return (err[:, None] <= thresholds.reshape(-1)).mean(axis=0).reshape(thresholds.shape)


def root_relative(points: np.ndarray, root: int) -> np.ndarray:
    """(T, J, 3) ``points`` minus joint ``root`` of the same frame (root-aligned positions)."""
    return points - points[:, root:root + 1]


@dataclass
class EvalReport:
    """Accuracy of a prediction against a reference (errors in millimetres). See :func:`evaluate`."""

    landmark_names: list[str]
    per_landmark_mm: np.ndarray  # (J,) MPJPE of each landmark over the evaluated frames
    mpjpe_mm: float  # mean over all evaluated (frame, landmark) pairs
    median_frame_mm: float  # median of the per-frame mean errors
    max_frame_mm: float  # worst per-frame mean error ...
    max_frame: int | None  # ... and its source frame number
    pck_thresholds_m: tuple[float, ...]
    pck: np.ndarray  # (N,) fraction of (frame, landmark) pairs within each threshold
    frames_evaluated: int  # frames with a reference and a valid prediction
    frames_lost: int  # frames with a reference that the prediction marks invalid
    frames_without_reference: int  # common frames where the reference is invalid or has no landmark
    frames_truth_only: int  # reference frames absent from the prediction
    root: str | None = None
    root_aligned_mpjpe_mm: float | None = None  # MPJPE after subtracting ``root``, over the other landmarks
    frame_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (F,) evaluated frames
    per_frame_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (F,) mean error of each
    lost_frame_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (frames_lost,)
    markers: MarkerAccuracy | None = None  # both files have markers3d

    @property
    def lost_fraction(self) -> float:
        """Lost frames over frames with a reference (0 when there are none)."""
        total = self.frames_evaluated + self.frames_lost
        return self.frames_lost / total if total else 0.0

    def format(self) -> str:
        """A readable table: frame counts, per-landmark MPJPE, summary figures and PCK."""
        width = max([len(n) for n in self.landmark_names] + [16])
        lines = [f"frames: {self.frames_evaluated} evaluated, {self.frames_lost} lost "
                 f"({100 * self.lost_fraction:.1f}%), {self.frames_without_reference} without reference, "
                 f"{self.frames_truth_only} reference frames not in the prediction",
                 "", f"{'landmark':<{width}}  MPJPE mm"]
        lines += [f"{name:<{width}}  {_mm(v)}" for name, v in zip(self.landmark_names, self.per_landmark_mm)]
        lines += ["", f"{'MPJPE':<{width}}  {_mm(self.mpjpe_mm)}"]
        if self.root is not None:
            lines.append(f"{'root-aligned':<{width}}  {_mm(self.root_aligned_mpjpe_mm)}  ({self.root} subtracted)")
        worst = f"  (frame {self.max_frame})" if self.max_frame is not None else ""
        lines += [f"{'median frame':<{width}}  {_mm(self.median_frame_mm)}",
                  f"{'max frame':<{width}}  {_mm(self.max_frame_mm)}{worst}"]
        for thr, frac in zip(self.pck_thresholds_m, self.pck):
            value = "n/a" if np.isnan(frac) else f"{100 * frac:.1f}%"
            lines.append(f"{f'PCK@{1000 * thr:g}mm':<{width}}  {value:>8}")
        if self.markers is not None:
            m = self.markers
            lines += ["", f"markers: {m.markers} in both, {m.frames} frames",
                      f"{f'MMTA@{1000 * m.threshold_m:g}mm':<{width}}  {100 * m.mmta:7.2f}%",
                      f"{'MMTP':<{width}}  {_mm(m.mmtp_mm)}"]
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        """Plain Python values for JSON (NaN becomes None)."""
        return {
            "frames_evaluated": self.frames_evaluated, "frames_lost": self.frames_lost,
            "lost_fraction": self.lost_fraction, "frames_without_reference": self.frames_without_reference,
            "frames_truth_only": self.frames_truth_only,
            "mpjpe_mm": _num(self.mpjpe_mm), "median_frame_mm": _num(self.median_frame_mm),
            "max_frame_mm": _num(self.max_frame_mm), "max_frame": self.max_frame,
            "root": self.root, "root_aligned_mpjpe_mm": _num(self.root_aligned_mpjpe_mm),
            "per_landmark_mm": {n: _num(v) for n, v in zip(self.landmark_names, self.per_landmark_mm)},
            "pck": [{"threshold_m": float(t), "fraction": _num(f)} for t, f in zip(self.pck_thresholds_m, self.pck)],
            "frame_index": [int(i) for i in self.frame_index],
            "per_frame_mm": [_num(v) for v in self.per_frame_mm],
            "lost_frame_index": [int(i) for i in self.lost_frame_index],
            **({} if self.markers is None else {"markers": {
                "threshold_m": self.markers.threshold_m, "mmta": _num(self.markers.mmta),
                "mmtp_mm": _num(self.markers.mmtp_mm), "markers": self.markers.markers,
                "frames": self.markers.frames}}),
        }


@dataclass(frozen=True)
class MarkerAccuracy:
    """Canton-Ferrer's marker figures (§4.1): a marker estimate matches where it lies within ``threshold_m`` of the
    truth; MMTA is the share of matched markers, MMTP their mean error (mm), each per frame and averaged over the
    frames. A marker the prediction names but does not give (NaN) counts as unmatched; one it does not name is left
    out, with a warning that names it."""

    threshold_m: float
    mmta: float
    mmtp_mm: float
    markers: int  # markers named in both files
    frames: int  # frames evaluated


def marker_accuracy(pred: Poses, truth: Poses, pred_idx: np.ndarray, truth_idx: np.ndarray, frames_ok: np.ndarray,
                    threshold_m: float = DEFAULT_MARKER_THRESHOLD_M) -> MarkerAccuracy | None:
    """MMTA and MMTP of the common markers (by name) on the common frames ``pred_idx`` / ``truth_idx`` where
    ``frames_ok``; None where either file has no markers or none in common."""
    if pred.markers3d is None or truth.markers3d is None:
        return None
    names = [n for n in truth.marker_names if n in set(pred.marker_names)]
    missing = [n for n in truth.marker_names if n not in set(pred.marker_names)]
    if names and missing:  # scored on the markers both name; the others are said, not counted
        log.warning("the prediction has no markers %s of the ground truth: MMTA and MMTP over the %d both name",
                    missing, len(names))
    if not names:
        return None
    p = pred.markers3d[pred_idx][:, [pred.marker_names.index(n) for n in names]].astype(np.float64)
    t = truth.markers3d[truth_idx][:, [truth.marker_names.index(n) for n in names]].astype(np.float64)
    p, t = p[frames_ok], t[frames_ok]
    has = np.isfinite(t).all(-1)  # (F, M) the truth has the marker
    err = np.linalg.norm(p - t, axis=-1)  # NaN where the prediction lacks it
    match = has & (err <= threshold_m)
    rows = has.any(1)
    share = match.sum(1)[rows] / has.sum(1)[rows]
    with np.errstate(invalid="ignore"):
        prec = np.where(match, err, 0.0).sum(1)[rows] / match.sum(1)[rows]
    return MarkerAccuracy(float(threshold_m), float(share.mean()) if share.size else float("nan"),
                          1000 * float(np.nanmean(prec)) if np.isfinite(prec).any() else float("nan"),
                          len(names), int(rows.sum()))


def evaluate(pred: Poses, truth: Poses, landmarks: Sequence[str] | None = None,
             pck_thresholds_m: Sequence[float] = DEFAULT_PCK_THRESHOLDS_M, root: str | None = "pelvis",
             pred_name: str = "prediction", truth_name: str = "ground truth",
             marker_threshold_m: float = DEFAULT_MARKER_THRESHOLD_M) -> EvalReport:
    """Compare ``pred`` with ``truth`` on their common frames (matched by frame number).

    Args:
        pred, truth: pose sequences; joints are matched by name.
        landmarks: joint names to evaluate (default: the 16 ``conventions.LANDMARKS``).
        pck_thresholds_m: PCK thresholds in metres.
        root: joint subtracted from both for the root-aligned MPJPE (None: skip that figure).
        pred_name, truth_name: how error messages name the two (file paths in the CLI).
        marker_threshold_m: MMTA's threshold where both have markers (:class:`MarkerAccuracy`).

    Raises:
        InputError: no common frame, a landmark missing from either, bad thresholds.
    """
    if not marker_threshold_m > 0:
        raise InputError(f"the marker threshold must be > 0 m, got {marker_threshold_m}")
    names = list(dict.fromkeys(LANDMARKS if landmarks is None else landmarks))
    thresholds = tuple(float(t) for t in pck_thresholds_m)
    pred_idx, truth_idx = match_frames(pred, truth, pred_name, truth_name)
    with_root = root is not None and root not in names
    cols = names + [root] if with_root else names
    pred_xyz = _select(pred, cols, pred_name)[pred_idx].astype(np.float64)  # (N, J', 3)
    truth_xyz = _select(truth, cols, truth_name)[truth_idx].astype(np.float64)  # (N, J', 3)
    truth_xyz[~truth.valid[truth_idx]] = np.nan  # an invalid reference frame has no keypoints
    frames = truth.frame_index[truth_idx]  # (N,)
    has_ref = np.isfinite(truth_xyz[:, : len(names)]).all(-1).any(-1)  # (N,)
    pred_ok = pred.valid[pred_idx].astype(bool)  # (N,)
    evaluated, lost = has_ref & pred_ok, has_ref & ~pred_ok

    J = len(names)
    res = mpjpe(pred_xyz[:, :J], truth_xyz[:, :J], evaluated)
    per_frame_mm = 1000 * res.per_frame[evaluated]  # (F,)
    worst = int(np.argmax(per_frame_mm)) if per_frame_mm.size else None
    root_mm = None
    if root is not None:
        r = cols.index(root)
        others = [j for j in range(J) if j != r]
        aligned = mpjpe(root_relative(pred_xyz, r)[:, others], root_relative(truth_xyz, r)[:, others], evaluated)
        root_mm = 1000 * aligned.mean
    return EvalReport(
        landmark_names=names, per_landmark_mm=1000 * res.per_joint, mpjpe_mm=1000 * res.mean,
        median_frame_mm=float(np.median(per_frame_mm)) if per_frame_mm.size else float("nan"),
        max_frame_mm=float(per_frame_mm[worst]) if worst is not None else float("nan"),
        max_frame=int(frames[evaluated][worst]) if worst is not None else None,
        pck_thresholds_m=thresholds,
        pck=pck(pred_xyz[:, :J], truth_xyz[:, :J], evaluated, thresholds),
        frames_evaluated=int(evaluated.sum()), frames_lost=int(lost.sum()),
        frames_without_reference=int((~has_ref).sum()), frames_truth_only=truth.num_frames - len(truth_idx),
        root=root, root_aligned_mpjpe_mm=root_mm, frame_index=frames[evaluated].astype(np.int64),
        per_frame_mm=per_frame_mm, lost_frame_index=frames[lost].astype(np.int64),
        markers=marker_accuracy(pred, truth, pred_idx, truth_idx, evaluated, marker_threshold_m))


def _select(poses: Poses, names: list[str], source: str) -> np.ndarray:
    """(T, len(names), 3) the joints ``names`` of ``poses``; InputError naming ``source`` if any is missing."""
    missing = [n for n in names if n not in poses.joint_names]
    if missing:
        raise InputError(f"{source}: joint_names lacks {missing} (has {poses.joint_names})")
    return poses.joints3d[:, [poses.joint_names.index(n) for n in names]]


def _nanmean(x: np.ndarray, axis: int | None = None) -> np.ndarray:
    """Mean of the finite values along ``axis``; NaN where there are none (without numpy's warning)."""
    ok = np.isfinite(x)
    total = np.where(ok, x, 0.0).sum(axis=axis)
    count = ok.sum(axis=axis)
    return np.divide(total, count, out=np.full(np.shape(total), np.nan), where=count > 0)


def _span(frame_index: np.ndarray) -> str:
    return f"{int(frame_index.min())}..{int(frame_index.max())}" if frame_index.size else "none"


def _mm(value: float | None) -> str:
    return f"{'n/a' if value is None or np.isnan(value) else f'{value:.1f}':>8}"


def _num(value: float | None) -> float | None:
    return None if value is None or not np.isfinite(value) else float(value)
