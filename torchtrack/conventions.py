"""The one place that states torchtrack's conventions.

World frame
    Right-handed, **Z up**, lengths in **metres**, angles in **radians**, quaternions **wxyz**.
Body frame (skeleton rest pose, all angles zero)
    The subject stands upright at the root, facing **+X**, its left side towards **+Y**, head towards **+Z**,
    arms hanging down. Joint rotation axes are expressed in this frame: X = forward (ab-/adduction),
    Y = left (flexion/extension), Z = up (twist).
Cameras
    OpenCV pinhole: camera x right, y down, z forward. Extrinsics map world to camera,
    ``x_cam = R_cam_world @ x_world + t_cam_world``. Intrinsics ``K`` in pixels, pixel centres at integer
    coordinates (OpenCV). Distortion: OpenCV (k1, k2, p1, p2[, k3]) or fisheye (k1..k4).
Images
    Inside the library: float tensors ``(C, 3, H, W)``, RGB, values in [0, 1]. BGR exists only at the IO edge.
Shape letters
    B batch, C cameras, H/W image, V voxels, N points, J landmarks, D degrees of freedom, K blobs,
    P particles, M markers, L annealing layers.
"""

from __future__ import annotations

#: The 16 landmarks every pose output carries, in this order (joint centres; ``head`` is the head centre,
#: ``spine`` the thorax).
LANDMARKS: tuple[str, ...] = (
    "pelvis", "spine", "neck", "head",
    "l_shoulder", "l_elbow", "l_wrist",
    "r_shoulder", "r_elbow", "r_wrist",
    "l_hip", "l_knee", "l_ankle",
    "r_hip", "r_knee", "r_ankle",
)

#: Index pairs of LANDMARKS drawn as bones in pictures.
LANDMARK_EDGES: tuple[tuple[int, int], ...] = (
    (0, 1), (1, 2), (2, 3),
    (2, 4), (4, 5), (5, 6),
    (2, 7), (7, 8), (8, 9),
    (0, 10), (10, 11), (11, 12),
    (0, 13), (13, 14), (14, 15),
)

UP_AXIS = 2  #: index of the world up axis (Z)
