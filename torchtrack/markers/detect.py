"""Colour marker detection in video (Canton-Ferrer et al. 2010, §4.2) and labelling from one labelled frame.

Detection: the balls' chrominance (Cr, Cb of YCrCb, kornia's conversion, taken per unit luma: ``MIN_LUMA``) is a
Gaussian learned from the pixels around points a person labelled in one frame; a pixel is a marker pixel where its
squared Mahalanobis distance is within ``threshold**2``, and each connected component (OpenCV) of a plausible area
is one detection, at its pixels' mean.

Labelling: the balls look alike, so each view's detections are linked to the labelled markers frame by frame from
the labelled frame (forwards, and backwards to the first frame). One detection per marker and view is kept by an
optimal assignment within gates round the predicted positions; the kept detections of two or more views are
triangulated (robustly, as the marker tracker's start is) and reprojected: a view whose kept detection disagrees
with the others drops it, and where a view kept none the reprojection is where the marker is looked for next. A
marker's candidates are its kept detection, then the nearest within its gate that no other marker kept (at most
K): a hidden marker does not take its neighbour's ball. The result is a ``markers2d.npz`` for the marker tracker.
"""

from __future__ import annotations

import csv
import logging
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from kornia.color import rgb_to_ycbcr
from scipy.optimize import linear_sum_assignment

from torchtrack.checks import InputError, check_shape
from torchtrack.io.markers2d import Markers2D
from torchtrack.io.video import DataWarning

__all__ = ["ChromaModel", "MarkerLabels", "detect_blobs", "detect_sequence", "link_detections", "read_marker_labels"]

log = logging.getLogger(__name__)

#: The chrominance is taken per unit luma: Cr - 0.5 and Cb - 0.5 scale with the light as Y does, so a ball's lit and
#: shaded sides share one value, where the plain (Cr, Cb) of its shaded side nears the grey of the room (the paper
#: takes YCrCb for its robustness to intensity; this makes it whole). Darker pixels than MIN_LUMA have no usable
#: chrominance and are never markers.
MIN_LUMA = 0.06
#: The chrominance covariance's smallest variance per axis: a few labelled pixels of a flat colour would otherwise
#: give a degenerate Gaussian that no other pixel of the same balls fits.
MIN_CHROMA_STD = 0.02
#: The robust chrominance fit: rounds of refitting to the pixels within the 90 % ellipse (chi-square, 2 dof), whose
#: covariance is that share of the whole Gaussian's (a 2D Gaussian truncated at r^2 = q keeps a variance of
#: 1 - (q/2) e^{-q/2} / (1 - e^{-q/2}) per axis; q = 4.605).
ROBUST_ROUNDS, CHI2_2DOF_90, CHI2_90_SHRINK = 5, 4.605, 0.744
#: A marker's gate in a view is one gate width where the view kept it the frame before, two where the others'
#: reprojection predicts it, and grows by one each frame it is neither, up to this many.
MAX_GATE_GROWTH = 4


@dataclass(frozen=True)
class MarkerLabels:
    """One frame's labelled markers: ``frame``; ``points``: ``{(camera, marker): (u, v)}`` in pixels."""

    frame: int
    points: dict[tuple[str, str], tuple[float, float]]

    @property
    def markers(self) -> list[str]:
        """The labelled markers, in the order of their first row."""
        return list(dict.fromkeys(m for _, m in self.points))

    def pixels(self, cameras: Sequence[str]) -> np.ndarray:
        """(C, M, 2) each labelled marker's pixel in each of ``cameras`` (M: :attr:`markers`), NaN where not
        labelled."""
        names = self.markers
        out = np.full((len(cameras), len(names), 2), np.nan)
        for (cam, m), uv in self.points.items():
            if cam in cameras:
                out[list(cameras).index(cam), names.index(m)] = uv
        return out

    def colour_model(self, images: torch.Tensor, cameras: Sequence[str]) -> ChromaModel:
        """The balls' colour from the labelled frame's ``images (C, 3, H, W)`` of ``cameras``
        (:meth:`ChromaModel.fit`)."""
        lab = self.pixels(cameras)
        return ChromaModel.fit(images, [torch.from_numpy(x[np.isfinite(x).all(-1)]) for x in lab])


def read_marker_labels(path: str | Path) -> MarkerLabels:
    """Read a labels CSV: a header ``frame,camera,marker,u,v`` and one row per labelled marker and view, all of one
    frame (pixel coordinates as the image shows them, the top-left pixel's centre at (0, 0)).

    Raises:
        InputError: a missing file or column, a malformed row or several frames, naming the file and line.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such marker labels file")
    points: dict[tuple[str, str], tuple[float, float]] = {}
    frames: set[int] = set()
    with open(path, newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        missing = [k for k in ("frame", "camera", "marker", "u", "v") if k not in (reader.fieldnames or [])]
        if missing:
            raise InputError(f"{path}: the header lacks {missing} (expected frame,camera,marker,u,v)")
        for row in reader:
            line = reader.line_num
            try:
                frame, u, v = int(row["frame"]), float(row["u"]), float(row["v"])
            except (TypeError, ValueError):
                raise InputError(f"{path}, line {line}: frame must be an integer and u, v numbers, got {row}") from None
            if not (math.isfinite(u) and math.isfinite(v)):
                raise InputError(f"{path}, line {line}: u, v must be finite, got {u}, {v}")
            key = (row["camera"].strip(), row["marker"].strip())
            if key in points:
                raise InputError(f"{path}, line {line}: marker {key[1]!r} labelled twice in camera {key[0]!r}")
            points[key] = (u, v)
            frames.add(frame)
    if not points:
        raise InputError(f"{path}: no labelled markers")
    if len(frames) > 1:
        raise InputError(f"{path}: labels of one frame are expected, got frames {sorted(frames)}")
    return MarkerLabels(frames.pop(), points)


def _chroma(images: torch.Tensor) -> torch.Tensor:
    """(..., 3, H, W) RGB in [0, 1] -> (..., H, W, 2) chrominance per unit luma ``((Cr - 0.5) / Y, (Cb - 0.5) / Y)``;
    NaN where ``Y < MIN_LUMA``."""
    ycbcr = rgb_to_ycbcr(images)
    y = ycbcr[..., 0, :, :]
    c = torch.stack([ycbcr[..., 2, :, :], ycbcr[..., 1, :, :]], -1) - 0.5
    return torch.where((y >= MIN_LUMA)[..., None], c / y.clamp(min=MIN_LUMA)[..., None], math.nan)


@dataclass(frozen=True)
class ChromaModel:
    """A Gaussian over the markers' (Cr, Cb): ``mean (2,)``, ``cov (2, 2)``, from ``num_pixels`` labelled pixels."""

    mean: torch.Tensor
    cov: torch.Tensor
    num_pixels: int

    @classmethod
    def fit(cls, images: torch.Tensor, points: Sequence[torch.Tensor], radius_px: float = 0.5) -> ChromaModel:
        """Learn from the pixels within ``radius_px`` of labelled points.

        Args:
            images: (C, 3, H, W) RGB in [0, 1], one frame of each view.
            points: C tensors (N_c, 2) of labelled (u, v) pixels in each view (N_c may be 0).
            radius_px: the neighbourhood of a point whose pixels are taken: by default the labelled pixel alone
                (1.5: the 3 x 3 pixels round it), as a ball a few pixels wide in a video's subsampled chrominance
                has its own colour only at its centre (docs/results.md, "Marker-based capture").
        """
        check_shape(images, (len(points), 3, "H", "W"), "images")
        H, W = images.shape[-2:]
        r = math.ceil(radius_px)
        dv, du = torch.meshgrid(torch.arange(-r, r + 1), torch.arange(-r, r + 1), indexing="ij")
        disc = (du.square() + dv.square()) <= radius_px ** 2
        du, dv = du[disc], dv[disc]  # (S,)
        chroma = _chroma(images)  # (C, H, W, 2)
        samples = []
        for c, pts in enumerate(points):
            if len(pts) == 0:
                continue
            p = torch.as_tensor(pts, dtype=torch.float64).round().long()  # (N, 2)
            u, v = p[:, None, 0] + du, p[:, None, 1] + dv  # (N, S)
            inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
            x = chroma[c, v[inside], u[inside]]
            samples.append(x[torch.isfinite(x).all(-1)])
        x = torch.cat(samples) if samples else torch.zeros(0, 2)
        if x.shape[0] < 3:
            raise InputError(f"marker colour: {x.shape[0]} labelled pixels inside the images (and lit); the colour "
                             "needs at least 3: label more markers")
        x = x.double()
        # robust: a label may be off the ball's centre, or a neighbourhood hold the ball's edge and what lies behind
        # it, so the Gaussian is refitted to the pixels within its own 90 % ellipse, from the median and its deviation
        floor = MIN_CHROMA_STD ** 2 * torch.eye(2, dtype=x.dtype, device=x.device)
        mean = x.median(0).values
        cov = torch.diag((x - mean).abs().median(0).values.square() * 1.4826 ** 2) + floor
        for _ in range(ROBUST_ROUNDS):
            d2 = ((x - mean) @ torch.linalg.inv(cov) * (x - mean)).sum(-1)
            inner = x[d2 <= CHI2_2DOF_90]
            if inner.shape[0] < 3:
                break
            mean, cov = inner.mean(0), torch.cov(inner.T) / CHI2_90_SHRINK + floor
        return cls(mean, cov, x.shape[0])

    def distance2(self, images: torch.Tensor) -> torch.Tensor:
        """(..., 3, H, W) RGB -> (..., H, W) squared Mahalanobis distance of each pixel's chrominance."""
        d = _chroma(images) - self.mean.to(images)
        return (d @ torch.linalg.inv(self.cov).to(images) * d).sum(-1)


def detect_blobs(images: torch.Tensor, model: ChromaModel, threshold: float = 3.0, min_area: int = 2,
                 max_area: int = 2000) -> list[np.ndarray]:
    """Markers in one frame of each view: connected components of the pixels within ``threshold`` (Mahalanobis)
    of the model, of ``min_area``..``max_area`` pixels, each at its pixels' mean.

    Args:
        images: (C, 3, H, W) RGB in [0, 1] (NaN for a view that did not decode: no detections there).

    Returns:
        C arrays (N_c, 2) of (u, v) pixels.
    """
    import cv2

    mask = (model.distance2(images) <= threshold ** 2).cpu().numpy().astype(np.uint8)  # NaN compares False
    out = []
    for m in mask:
        n, _, stats, centroids = cv2.connectedComponentsWithStats(m, connectivity=8)
        area = stats[1:, cv2.CC_STAT_AREA]
        keep = (area >= min_area) & (area <= max_area)
        out.append(centroids[1:][keep].astype(np.float64))
    return out


def _gated(centre: np.ndarray, blobs: np.ndarray, gate: np.ndarray) -> np.ndarray:
    """(C, M, N) distances from markers' expected positions ``centre (C, M, 2)`` (NaN: unknown) to each view's
    detections ``(C, N, 2)`` (NaN: padding), inf beyond each marker's ``gate (C, M)``."""
    d = np.linalg.norm(centre[:, :, None] - blobs[:, None], axis=-1)
    return np.where(np.isfinite(d) & (d <= gate[..., None]), d, np.inf)


def link_detections(blobs: Sequence[Sequence[np.ndarray]], labels: np.ndarray, rig: torch.nn.Module,
                    gate_px: float = 15.0, candidates: int = 3, inlier_px: float = 6.0) -> np.ndarray:
    """Each view's detections linked to the labelled markers, from the labelled frame on (module docstring).

    Args:
        blobs: T frames of C arrays (N, 2): the detections, the labelled frame first.
        labels: (C, M, 2) the labelled frame's markers in each view, NaN where not labelled.
        rig: the calibrated cameras (``CameraRig``).
        gate_px: a detection is a marker's candidate within this of its prediction.
        candidates: at most this many candidates per marker and view (K).
        inlier_px: a view's kept detection agrees with the triangulated marker within this.

    Returns:
        (T, C, M, K, 2) float32 candidates, NaN where none.
    """
    from torchtrack.markers.triangulate import triangulate_candidates
    from torchtrack.tracking.epipolar import pinhole_pixels, projection_matrices

    C, M, _ = labels.shape
    T = len(blobs)
    P = projection_matrices(rig).double()
    out = np.full((T, C, M, candidates, 2), np.nan, dtype=np.float32)
    pred = labels.astype(np.float64).copy()  # (C, M, 2) where each marker is looked for in each view
    last, vel = pred.copy(), np.zeros_like(pred)  # the last kept detection and the motion from the one before
    age = np.where(np.isfinite(pred).all(-1), 0, MAX_GATE_GROWTH)  # (C, M) frames since a view last kept it
    views = np.arange(C)[:, None]
    for t in range(T):
        n = max(1, max(len(x) for x in blobs[t]))
        b = np.full((C, n, 2), np.nan)  # the views' detections, padded
        for c, x in enumerate(blobs[t]):
            b[c, :len(x)] = np.asarray(x, dtype=np.float64).reshape(-1, 2)
        gate = gate_px * (1 + np.minimum(age, MAX_GATE_GROWTH - 1))  # (C, M)
        d = _gated(pred, b, gate)  # (C, M, N)
        kept_idx = np.full((C, M), -1)
        for c in range(C):  # one detection per marker: the optimal assignment within the gates (scipy, per view)
            rows, cols = linear_sum_assignment(np.where(np.isfinite(d[c]), d[c], 1e9))
            good = np.isfinite(d[c, rows, cols])
            kept_idx[c, rows[good]] = cols[good]
        kept = np.where((kept_idx >= 0)[..., None], b[views, kept_idx.clip(min=0)], np.nan)  # (C, M, 2)
        # the kept detections triangulated; their reprojection checks each view and predicts where one missed
        z = pinhole_pixels(rig, torch.from_numpy(kept)[:, :, None])  # (C, M, 1, 2)
        X, _ = triangulate_candidates(z[None].double(), P, inlier_px)  # (1, M, 3)
        uv, inside = rig.project(torch.nan_to_num(X[0]).to(P))  # (C, M, 2), (C, M)
        uv, has3d = uv.numpy(), (inside & torch.isfinite(X[0]).all(-1)[None]).numpy()
        agree = np.linalg.norm(kept - uv, axis=-1) <= inlier_px
        take = np.isfinite(kept).all(-1) & (agree | ~has3d)
        # candidates: the kept one first, then the nearest that no other marker keeps
        ci, mi = np.nonzero(take)
        owned = np.zeros((C, n), dtype=bool)
        owned[ci, kept_idx[ci, mi]] = True
        centre = np.where(take[..., None], kept, np.where(has3d[..., None], uv, pred))
        d = np.where(owned[:, None], np.inf, _gated(centre, b, gate))
        d[ci, mi, kept_idx[ci, mi]] = 0.0
        order = np.argsort(d, axis=-1)[..., :candidates]  # (C, M, K') nearest first
        near = np.take_along_axis(d, order, -1)
        out[t, :, :, :order.shape[-1]] = np.where(np.isfinite(near)[..., None], b[views[..., None], order], np.nan)
        vel = np.where((take & (age == 0))[..., None], kept - last, 0.0)
        last = np.where(take[..., None], kept, last)
        pred = np.where(take[..., None], kept + vel, np.where(has3d[..., None], uv, pred))
        age = np.where(take, 0, np.where(has3d, 1, age + 1))
    return out


def detect_sequence(folder: str | Path, labels: MarkerLabels, threshold: float = 3.0, gate_px: float = 15.0,
                    candidates: int = 3, min_area: int = 2, max_area: int = 2000, batch: int = 8,
                    progress: bool = True) -> Markers2D:
    """The colour markers of a sequence folder's video, labelled from ``labels``' frame (module docstring).

    Raises:
        InputError: labels of cameras the calibration lacks, of a frame outside the video, or none usable.
    """
    from torchtrack.io.sequence import SequenceFolder

    with SequenceFolder(folder) as seq:
        return _detect(seq, labels, threshold, gate_px, candidates, min_area, max_area, batch, progress)


def _detect(seq, labels: MarkerLabels, threshold: float, gate_px: float, candidates: int, min_area: int,
            max_area: int, batch: int, progress: bool) -> Markers2D:
    """:func:`detect_sequence` on an open :class:`~torchtrack.io.sequence.SequenceFolder`."""
    from tqdm import tqdm

    cams, names = seq.camera_names, labels.markers
    unknown = sorted({c for c, _ in labels.points} - set(cams))
    if unknown:
        raise InputError(f"marker labels: cameras {unknown} are not in {seq.root}'s calibration ({cams})")
    if not 0 <= labels.frame < seq.num_frames:
        raise InputError(f"marker labels: frame {labels.frame} outside {seq.root}'s {seq.num_frames} frames")
    lab = labels.pixels(cams)
    few = [n for m, n in enumerate(names) if np.isfinite(lab[:, m, 0]).sum() < 2]
    if few:
        warnings.warn(f"marker labels: {few} labelled in fewer than two views: they cannot be triangulated and are "
                      "found in other views only once two views see them; label each marker in two or more views",
                      DataWarning, stacklevel=3)
    model = labels.colour_model(seq.read_frame(labels.frame), cams)
    log.info("marker colour from %d labelled pixels: (Cr, Cb) mean %s", model.num_pixels, model.mean.tolist())
    blobs: list[list[np.ndarray]] = []
    with tqdm(total=seq.num_frames, desc="detect markers", unit="frame", disable=not progress) as bar:
        for fb in seq.iter_batches(batch):
            blobs.extend(detect_blobs(im, model, threshold, min_area, max_area) for im in fb.images)
            bar.update(len(fb.images))
    f0 = labels.frame
    uv = link_detections(blobs[f0:], lab, seq.rig, gate_px, candidates)
    if f0 > 0:
        back = link_detections(blobs[f0::-1], lab, seq.rig, gate_px, candidates)[1:][::-1]
        uv = np.concatenate([back, uv])
    return Markers2D(fps=seq.fps, frame_index=np.arange(seq.num_frames), camera_names=list(cams), marker_names=names,
                     uv=uv)
