"""The start of a track from 2D keypoints: detected in every camera, triangulated, the body fitted to them.

A few cameras' voxels leave a start ambiguous (a four-view hull is fat with phantom volume, and a body larger or
turned round explains it as well); a detector's keypoints in each image are evidence the hull lacks. Over the
first frames (:attr:`KeypointStartConfig.frames` within :attr:`~KeypointStartConfig.span_s`): each camera's
image is detected alone, the views that see the same person are found (:func:`~.triangulate.consistent_views`),
each keypoint is triangulated from them, and the skeleton's pose and bone lengths are fitted to all those frames
at once (:func:`~torchtrack.tracking.landmark_fit.fit_to_landmarks`). The first frame's pose is the start.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from torchtrack.checks import InputError, config_section
from torchtrack.keypoints.detector import KEYPOINTS, KeypointDetector
from torchtrack.keypoints.triangulate import consistent_views, triangulate_keypoints

log = logging.getLogger(__name__)

#: Trunk keypoints that place the body: both hips and both shoulders.
TRUNK = ("l_hip", "r_hip", "l_shoulder", "r_shoulder")
#: Largest mean distance (m) of the fitted body's keypoints from the triangulated ones: one person's keypoints
#: fit within a few centimetres (docs/results.md, "The keypoint start"); more means points of several people or a
#: misdetection.
MAX_FIT_RESIDUAL_M = 0.05


@dataclass(frozen=True)
class KeypointStartConfig:
    """How a track starts from detected keypoints (the tracking config's ``keypoint_start`` section).

    Attributes:
        enabled: "auto" (when the detector's package is installed), "on" (an error without it) or "off".
        detector: the detector's name (:data:`~torchtrack.keypoints.detector.DETECTORS`).
        frames: frames detected for the body's proportions, the start frame first.
        span_s: the frames are spread over this much video from the start frame (s).
        max_error: a detection farther than this share of the person's size in that view (the diagonal of
            its keypoints' box) from the triangulated point is dropped.
        min_views: each frame needs this many cameras that see the same person (at least 3: two views'
            detections triangulate whatever they are, only a third one checks them).
        min_keypoints: and this many keypoints triangulated, the four of the trunk among them.
        max_cameras: used on rigs of at most this many cameras. With more, the visual hull is tight and the
            voxel search starts better than keypoints, whose points are not the skeleton's joint centres
            (docs/results.md, "The keypoint start").
    """

    enabled: str = "auto"
    detector: str = "mediapipe"
    frames: int = 6
    span_s: float = 0.5
    max_error: float = 0.05
    min_views: int = 3
    min_keypoints: int = 9
    max_cameras: int = 6

    def __post_init__(self) -> None:
        if self.enabled not in ("auto", "on", "off"):
            raise InputError(f"keypoint_start.enabled must be auto, on or off, got {self.enabled!r}")
        if self.frames < 1 or self.span_s < 0 or not 0 < self.max_error < 1:
            raise InputError("keypoint_start: frames >= 1, span_s >= 0 and 0 < max_error < 1 are needed, got "
                             f"{self.frames}, {self.span_s}, {self.max_error}")
        if self.min_views < 3 or not len(TRUNK) <= self.min_keypoints <= len(KEYPOINTS):
            raise InputError(f"keypoint_start: min_views >= 3 and {len(TRUNK)} <= min_keypoints <= {len(KEYPOINTS)}"
                             f" are needed, got {self.min_views}, {self.min_keypoints}")

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None, source: str = "config") -> KeypointStartConfig:
        """Build from the YAML section (None: the defaults), naming unknown keys; YAML's bare on / off read as
        booleans count as "on" / "off"."""
        d = config_section(cls, d, source, "keypoint_start")
        if isinstance(d.get("enabled"), bool):
            d["enabled"] = "on" if d["enabled"] else "off"
        return cls(**d)


@dataclass
class KeypointStart:
    """A start found from keypoints: ``angles (D,)`` on ``skeleton`` (the fitted body) at frame ``frame``; the
    frames used, the mean distance (m) of the fitted body's keypoints from the triangulated ones, the cameras
    that saw the person in the start frame, and that frame's detections: ``uv_px (C, K, 2)`` at the videos' size
    and ``used (C, K)``, those the points were triangulated from."""

    angles: torch.Tensor
    skeleton: Any
    frame: int
    frames: list[int]
    residual_m: float
    cameras: list[str]
    uv_px: np.ndarray
    used: np.ndarray


def detect_sequence(folder, frames: list[int], detector: KeypointDetector) -> tuple[np.ndarray, np.ndarray]:
    """Detect ``frames`` (sorted) of every camera of ``folder`` (a SequenceFolder), at the calibrated size:
    ``(C, T, K, 2)`` pixels and ``(C, T, K)`` confidences (0 for a frame that did not decode)."""
    C, T, K = folder.num_cameras, len(frames), len(KEYPOINTS)
    uv, conf = np.full((C, T, K, 2), np.nan), np.zeros((C, T, K))
    decoded = [folder.read_camera_frames(c, frames) for c in range(C)]  # all decoded before any detection
    for c, (images, ok) in enumerate(decoded):
        for t in np.flatnonzero(ok):
            uv[c, t], conf[c, t] = detector.detect(images[t])
    return uv, conf


def person_size_px(uv: np.ndarray, conf: np.ndarray, min_confidence: float = 0.5) -> np.ndarray:
    """``(..., K, 2)``, ``(..., K)`` -> ``(...)``: the diagonal of the box of the confident keypoints (0 where
    fewer than two)."""
    ok = (conf >= min_confidence) & np.isfinite(uv).all(-1)
    lo = np.where(ok[..., None], uv, np.inf).min(-2)
    hi = np.where(ok[..., None], uv, -np.inf).max(-2)
    diag = np.linalg.norm(hi - lo, axis=-1)
    return np.where(ok.sum(-1) >= 2, diag, 0.0)


def start_from_keypoints(folder, rig, generic, detector: KeypointDetector, config: KeypointStartConfig,
                         start: int = 0, stop: int | None = None) -> tuple[KeypointStart | None, str]:
    """The start pose and body from keypoints detected in frames ``start ...`` of ``folder``.

    Args:
        folder: the :class:`~torchtrack.io.sequence.SequenceFolder`. rig: its cameras at the videos' size.
        generic: the body model (:class:`~torchtrack.skeleton.Skeleton`) whose proportions the fit starts from.
        detector, config: the detector and :class:`KeypointStartConfig`.
        start, stop: the tracked frames.

    Returns:
        the :class:`KeypointStart`, or None and why not (a sentence naming the frame): no consistent person in
        the start frame, or a fit no human body makes.
    """
    from torchtrack.tracking.landmark_fit import fit_to_landmarks

    stop = folder.num_frames if stop is None else stop
    last = min(stop - 1, start + int(round(config.span_s * folder.fps)))
    frames = sorted({int(round(x)) for x in np.linspace(start, last, config.frames)})
    uv, conf = detect_sequence(folder, frames, detector)
    limit = torch.as_tensor(config.max_error * person_size_px(uv, conf))  # (C, T)
    uv_t, conf_t = torch.as_tensor(uv), torch.as_tensor(conf)
    rig64 = copy.deepcopy(rig).double()  # nn.Module.double() converts in place: the caller's rig stays as it is
    views = consistent_views(rig64, uv_t, conf_t, limit)  # (C, T)
    tri = triangulate_keypoints(rig64, uv_t, conf_t * views[..., None], limit)
    points = tri.points.float().numpy()  # (T, K, 3)
    found = np.isfinite(points).all(-1)  # (T, K)
    trunk = [KEYPOINTS.index(n) for n in TRUNK]
    usable = ((views.sum(0).numpy() >= config.min_views) & found[:, trunk].all(-1)
              & (found.sum(-1) >= config.min_keypoints))
    if not usable[0]:
        seen = int(views[:, 0].sum())
        return None, (f"frame {start}: {seen} camera(s) agree on one person and {int(found[0].sum())} of "
                      f"{len(KEYPOINTS)} keypoints were triangulated (needed: {config.min_views} cameras, "
                      f"{config.min_keypoints} keypoints with the hips and shoulders)")
    keep = np.flatnonzero(usable)
    try:
        with torch.no_grad():
            angles, body = fit_to_landmarks(generic, list(KEYPOINTS), points[keep])
            fitted = body.forward(angles).output_points.cpu().numpy()  # (T', J, 3)
    except InputError as exc:  # keypoints no body can take (e.g. of several people)
        return None, f"frame {start}: the keypoints fit no body ({exc})"
    idx = [list(body.output_names).index(n) for n in KEYPOINTS]
    dist = np.linalg.norm(fitted[:, idx] - points[keep], axis=-1)
    residual = float(np.nanmean(dist))
    height = float(body.height())
    if not 1.0 <= height <= 2.3:
        return None, f"frame {start}: the keypoints make a {height:.2f} m body"
    if residual > MAX_FIT_RESIDUAL_M:
        return None, (f"frame {start}: no body fits the keypoints (the fitted one is {1e3 * residual:.0f} mm from "
                      f"them on average)")
    cams = [n for n, v in zip(rig.names, views[:, 0].tolist()) if v]
    log.info("start from keypoints: frames %s, %d camera(s) in the first (%s), a %.2f m body fitted %.1f mm from "
             "them on average", [frames[k] for k in keep], len(cams), ", ".join(cams), height, 1e3 * residual)
    return KeypointStart(angles[0], body, start, [frames[k] for k in keep], residual, cams, uv[:, 0],
                         tri.views[:, 0].numpy()), ""


def draw_keypoint_start(images: torch.Tensor, rig, found: KeypointStart, full_size_wh: np.ndarray) -> torch.Tensor:
    """The start frame's ``images (C, 3, H, W)`` (at ``rig``'s size) with the fitted body's skeleton and the
    detections over it: white where triangulated, red where dropped. ``full_size_wh (C, 2)``: the size the
    detections are in."""
    import cv2

    from torchtrack.tracking.draw import draw_pose_overlays

    with torch.no_grad():
        landmarks = found.skeleton.forward(found.angles[None]).output_points[0, :16]
    canvas = draw_pose_overlays(images, rig, landmarks.to(images)).permute(0, 2, 3, 1).numpy().copy()
    scale = rig.image_size_wh.cpu().numpy() / np.asarray(full_size_wh)  # (C, 2)
    radius = max(2, round(0.006 * float(rig.image_size_wh.max())))
    for c in range(canvas.shape[0]):
        for (u, v), used in zip(found.uv_px[c] * scale[c], found.used[c]):
            if np.isfinite(u) and np.isfinite(v):
                cv2.circle(canvas[c], (int(round(u)), int(round(v))), radius, (1.0, 1.0, 1.0) if used else
                           (1.0, 0.1, 0.1), 1, cv2.LINE_AA)
    return torch.from_numpy(canvas).permute(0, 3, 1, 2)
