"""Pictures of a tracked pose: skeleton and blob outlines over camera images, skeleton points for 3D views.

Geometry (projection with lens distortion, ellipsoid rims) is batched torch on the inputs' device; rasterising
is OpenCV's (imported when drawing, never at import time) on CPU float32 copies of the images. Pixel centres are
at integer coordinates, as in :class:`~torchtrack.cameras.CameraRig` and in OpenCV's drawing functions.

Blob outlines are exact silhouettes. The outline of an ellipsoid seen from a camera centre is the image of its
occluding contour (rim): the surface points whose viewing ray is tangent to the surface. In the ellipsoid's
unit-sphere frame ``q = diag(1 / a) R^T (x - c)`` (an affine map, which keeps tangency) the rim seen from the
eye ``e`` (``|e| > 1``) is the circle ``{q : |q| = 1, q . e = 1}``: centre ``e / |e|^2``, radius
``sqrt(1 - 1 / |e|^2)``, in the plane orthogonal to ``e``. Its samples are projected with
:meth:`CameraRig.project`, so the outline includes lens distortion (a pinhole conic bent by the lens).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from torchtrack.cameras import CameraRig
from torchtrack.checks import InputError, check_shape
from torchtrack.conventions import LANDMARK_EDGES, LANDMARKS

__all__ = ["LEFT_RGB", "RIGHT_RGB", "CENTRE_RGB", "BLOB_RGB", "VOXEL_RGB", "MARKER_RGB", "DETECTION_RGB",
           "landmark_colours", "ellipsoid_rim_points", "draw_marker_overlays", "draw_pose_overlays", "skeleton_cloud"]

LEFT_RGB: tuple[float, float, float] = (0.1, 0.6, 1.0)  #: left-side bones and joints (blue)
RIGHT_RGB: tuple[float, float, float] = (1.0, 0.3, 0.1)  #: right-side bones and joints (orange-red)
CENTRE_RGB: tuple[float, float, float] = (1.0, 0.9, 0.1)  #: pelvis, spine, neck, head (yellow)
BLOB_RGB: tuple[float, float, float] = (0.9, 0.9, 0.9)  #: blob outlines when no blob colours are given
VOXEL_RGB: tuple[float, float, float] = (0.55, 0.55, 0.55)  #: voxels under a skeleton cloud (grey)
MARKER_RGB: tuple[float, float, float] = (0.2, 1.0, 0.3)  #: the model's markers, projected (green rings)
DETECTION_RGB: tuple[float, float, float] = (1.0, 1.0, 1.0)  #: marker detections (white dots)

_SHIFT = 4  # fractional bits of OpenCV's fixed-point drawing coordinates (1/16 px)


def _side_rgb(names: tuple[str, ...]) -> tuple[float, float, float]:
    """Left if any name starts with ``l_``, right if any with ``r_``, else centre."""
    if any(n.startswith("l_") for n in names):
        return LEFT_RGB
    return RIGHT_RGB if any(n.startswith("r_") for n in names) else CENTRE_RGB


def landmark_colours() -> tuple[list[tuple[float, float, float]], list[tuple[float, float, float]]]:
    """RGB colours by body side: (J,) per landmark of LANDMARKS and (E,) per bone of LANDMARK_EDGES.

    A bone is left (right) when one of its ends is a left (right) landmark, so ``neck - l_shoulder`` is left.
    """
    joints = [_side_rgb((n,)) for n in LANDMARKS]
    bones = [_side_rgb((LANDMARKS[i], LANDMARKS[j])) for i, j in LANDMARK_EDGES]
    return joints, bones


def ellipsoid_rim_points(eyes_world: Tensor, centres: Tensor, R_world_blob: Tensor, semi_axes: Tensor,
                         num_samples: int = 64) -> tuple[Tensor, Tensor]:
    """Occluding contours (rims) of K ellipsoids seen from C eye points (camera centres).

    Args:
        eyes_world: (C, 3) viewpoints, world.
        centres: (K, 3) ellipsoid centres, world.
        R_world_blob: (K, 3, 3) rotations whose columns are the ellipsoid axes in the world.
        semi_axes: (K, 3) positive semi-axes along those columns.
        num_samples: S >= 3 rim points, evenly spaced in angle around the unit-sphere circle.

    Returns:
        rim: (C, K, S, 3) world points on the ellipsoid whose viewing ray from the eye is tangent to it,
            consecutive around the rim (finite but meaningless where ``outside`` is False).
        outside: (C, K) bool: the eye is outside the ellipsoid; else there is no rim (the ellipsoid fills
            every direction of view).
    """
    check_shape(eyes_world, ("C", 3), "eyes_world")
    check_shape(centres, ("K", 3), "centres")
    K = centres.shape[0]
    check_shape(R_world_blob, (K, 3, 3), "R_world_blob")
    check_shape(semi_axes, (K, 3), "semi_axes")
    if num_samples < 3:
        raise InputError(f"num_samples must be >= 3, got {num_samples}")
    if bool((semi_axes <= 0).any()):
        raise InputError("semi_axes must be positive")
    dtype = torch.promote_types(eyes_world.dtype, centres.dtype)
    o, c = eyes_world.to(dtype), centres.to(dtype)
    R, a = R_world_blob.to(dtype), semi_axes.to(dtype)
    e = torch.einsum("kji,ckj->cki", R, o[:, None] - c[None]) / a  # (C, K, 3) eye in the unit frame
    n2 = (e * e).sum(-1)  # (C, K)
    outside = n2 > 1
    n2 = torch.where(outside, n2, torch.full_like(n2, 2.0))  # any |e| > 1 where there is no rim
    e_hat = e / n2.sqrt()[..., None]  # (C, K, 3)
    helper = torch.eye(3, dtype=dtype, device=e.device)[e_hat.abs().argmin(-1)]  # (C, K, 3) least-parallel axis
    u = torch.linalg.cross(e_hat, helper)
    u = u / u.norm(dim=-1, keepdim=True)  # (C, K, 3)
    v = torch.linalg.cross(e_hat, u)  # (C, K, 3)
    theta = torch.arange(num_samples, dtype=dtype, device=e.device) * (2 * math.pi / num_samples)  # (S,)
    ring = theta.cos()[:, None] * u[..., None, :] + theta.sin()[:, None] * v[..., None, :]  # (C, K, S, 3)
    radius = (1 - 1 / n2).sqrt()  # (C, K)
    q = (e / n2[..., None])[..., None, :] + radius[..., None, None] * ring  # (C, K, S, 3) on the unit sphere
    rim = c[:, None] + torch.einsum("kij,cksj->cksi", R, q * a[:, None])  # (C, K, S, 3)
    return rim, outside


def _pixels(rig: CameraRig, points_world: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Project world points into every camera for drawing.

    Args:
        points_world: (..., N, 3).

    Returns:
        uv_px: (C, ..., N, 2) distorted pixels.
        drawable: (C, ..., N) finite, in front of the camera, within the distortion model's monotonic radius and
            within one image size of the image: line ends OpenCV can clip at the image edge.
        inside: (C, ..., N) drawable and inside the image (:meth:`CameraRig.project`'s ``valid``).
    """
    # The same cameras seeing an image padded by `margin` on every side: its `valid` is `drawable`.
    size = rig.image_size_wh  # (C, 2)
    margin = size.amax(-1, keepdim=True)  # (C, 1)
    K = rig.K.clone()
    K[:, :2, 2] += margin.to(K.dtype)
    padded = CameraRig(rig.names, K, rig.R_cam_world, rig.t_cam_world, size + 2 * margin, rig.dist, rig.fisheye)
    uv, drawable = padded.project(points_world)  # (C, ..., N, 2), (C, ..., N)
    lead = (len(rig),) + (1,) * (uv.dim() - 2)  # broadcast (C, 1 or 2) over (C, ..., N, 2)
    uv = uv - margin.to(uv.dtype).view(*lead, 1)
    drawable = drawable & torch.isfinite(uv).all(-1)
    inside = drawable & ((uv >= -0.5) & (uv < size.to(uv.dtype).view(*lead, 2) - 0.5)).all(-1)
    return uv, drawable, inside


def _fixed(uv: np.ndarray) -> np.ndarray:
    """(..., 2) float pixels -> int32 fixed point with ``_SHIFT`` fractional bits (OpenCV's ``shift``)."""
    return np.round(uv * (1 << _SHIFT)).astype(np.int32)


def _draw_segments(canvas: np.ndarray, uv: np.ndarray, starts: np.ndarray, ends: np.ndarray, ok: np.ndarray,
                   rgb: tuple[float, float, float], width_px: int) -> None:
    """Lines ``uv[starts[i]] -> uv[ends[i]]`` where ``ok[i]``, on ``canvas (H, W, 3)`` float32 RGB, in place.

    OpenCV anti-aliases only 8-bit images: on the float canvas (kept to preserve the input's values) ``LINE_AA``
    draws plain 8-connected lines.
    """
    import cv2  # lazy: no OpenCV at package import (DESIGN.md)

    segments = _fixed(np.stack([uv[starts[ok]], uv[ends[ok]]], 1))  # (n, 2, 2)
    if len(segments):
        cv2.polylines(canvas, list(segments), False, rgb, width_px, cv2.LINE_AA, _SHIFT)


def _draw_blobs(canvas: np.ndarray, rig: CameraRig, centres: Tensor, R_world_blob: Tensor, semi_axes: Tensor,
                colours: list, width_px: int, rim_samples: int) -> None:
    """Blob outlines on ``canvas (C, H, W, 3)``, in place; arguments as in :func:`draw_pose_overlays`."""
    rim, outside = ellipsoid_rim_points(rig.centers(), centres, R_world_blob, semi_axes, rim_samples)  # (C, K, S, 3)
    uv, drawable, _ = _pixels(rig, rim)  # (C, C, K, S, 2), (C, C, K, S): every rim in every camera
    cams = torch.arange(rig.num_cameras, device=uv.device)
    uv = uv[cams, cams].cpu().numpy()  # (C, K, S, 2) each camera's own rims
    drawable = (drawable[cams, cams] & outside[..., None]).cpu().numpy()  # (C, K, S)
    starts, ends = np.arange(rim_samples), (np.arange(rim_samples) + 1) % rim_samples  # the closed rim
    for c, k in np.ndindex(*outside.shape):
        ok = drawable[c, k, starts] & drawable[c, k, ends]
        _draw_segments(canvas[c], uv[c, k], starts, ends, ok, tuple(map(float, colours[k])), width_px)


def _draw_skeleton(canvas: np.ndarray, rig: CameraRig, landmarks: Tensor, bone_width_px: int,
                   joint_radius_px: int) -> None:
    """Bones, then joints, on ``canvas (C, H, W, 3)``, in place; arguments as in :func:`draw_pose_overlays`."""
    import cv2

    uv, drawable, inside = (x.cpu().numpy() for x in _pixels(rig, landmarks))  # (C, J, 2), (C, J), (C, J)
    joint_rgb, bone_rgb = landmark_colours()
    edges = np.asarray(LANDMARK_EDGES)  # (E, 2)
    for c in range(rig.num_cameras):
        ok = drawable[c, edges[:, 0]] & drawable[c, edges[:, 1]]  # (E,)
        for rgb in dict.fromkeys(bone_rgb) if bone_width_px > 0 else ():
            side = np.array([b == rgb for b in bone_rgb])  # (E,) bones of this colour
            _draw_segments(canvas[c], uv[c], edges[side, 0], edges[side, 1], ok[side], rgb, bone_width_px)
        for j in np.flatnonzero(inside[c]) if joint_radius_px > 0 else ():
            centre = tuple(int(x) for x in _fixed(uv[c, j]))
            cv2.circle(canvas[c], centre, joint_radius_px << _SHIFT, joint_rgb[j], -1, cv2.LINE_AA, _SHIFT)


def draw_pose_overlays(images: Tensor, rig: CameraRig, landmarks: Tensor | None = None,
                       blob_centres: Tensor | None = None, blob_R_world_blob: Tensor | None = None,
                       blob_semi_axes: Tensor | None = None, blob_colours: Tensor | None = None, *,
                       bone_width_px: int = 2, joint_radius_px: int = 3, outline_width_px: int = 1,
                       rim_samples: int = 64) -> Tensor:
    """Draw a pose over every camera's image: blob outlines, then bones, then joints on top.

    Bones are lines between projected landmarks coloured by side (:data:`LEFT_RGB`, :data:`RIGHT_RGB`,
    :data:`CENTRE_RGB`); joints are filled dots; each blob's exact silhouette outline (module docstring) is drawn
    in its colour. What cannot be drawn is left out without error: non-finite landmarks, points behind a camera
    or beyond its distortion model's range, and blobs that contain the camera. Lines are clipped at the image
    edge; joints outside the image are not drawn.

    Args:
        images: (C, 3, H, W) float RGB in [0, 1], at every camera's calibrated size (else use ``rig.resized``).
        rig: the C cameras.
        landmarks: (J, 3) world positions of LANDMARKS (J = 16), or None for no skeleton.
        blob_centres: (K, 3) blob centres, world, or None for no blobs.
        blob_R_world_blob: (K, 3, 3) blob axes as columns (:meth:`BlobModel.ellipsoids`); with ``blob_centres``.
        blob_semi_axes: (K, 3) semi-axes along those axes (``BlobModel.semi_axes``); with ``blob_centres``.
        blob_colours: (K, 3) RGB in [0, 1], or None for :data:`BLOB_RGB`.
        bone_width_px, joint_radius_px, outline_width_px: sizes in pixels (0 leaves that element out).
        rim_samples: points per blob outline.

    Returns:
        (C, 3, H, W) a copy of ``images`` with the overlays, on its device and in its dtype.
    """
    C = rig.num_cameras
    check_shape(images, (C, 3, "H", "W"), "images")
    if not images.is_floating_point():
        raise InputError(f"images: expected a float tensor in [0, 1], got {images.dtype}")
    H, W = images.shape[-2:]
    for name, (w, h) in zip(rig.names, rig.image_size_wh.tolist()):
        if (w, h) != (W, H):
            raise InputError(f"images are {W}x{H} but camera {name!r} is calibrated at {w}x{h}: "
                             "draw with rig.resized(W, H)")
    if landmarks is not None:
        check_shape(landmarks, (len(LANDMARKS), 3), "landmarks")
    blobs = (blob_centres, blob_R_world_blob, blob_semi_axes)
    if any(b is None for b in blobs) and any(b is not None for b in blobs):
        raise InputError("blob_centres, blob_R_world_blob and blob_semi_axes go together: give all or none")
    if blob_centres is not None and blob_colours is not None:
        check_shape(blob_colours, (blob_centres.shape[0], 3), "blob_colours")
    canvas = images.detach().permute(0, 2, 3, 1).to("cpu", torch.float32).numpy().copy()  # (C, H, W, 3)
    device = rig.K.device  # geometry runs where the rig lives
    if blob_centres is not None and outline_width_px > 0:
        colours = [BLOB_RGB] * blob_centres.shape[0] if blob_colours is None else blob_colours.tolist()
        _draw_blobs(canvas, rig, blob_centres.to(device), blob_R_world_blob.to(device), blob_semi_axes.to(device),
                    colours, outline_width_px, rim_samples)
    if landmarks is not None:
        _draw_skeleton(canvas, rig, landmarks.to(device), bone_width_px, joint_radius_px)
    return torch.from_numpy(canvas).permute(0, 3, 1, 2).to(device=images.device, dtype=images.dtype)


def skeleton_cloud(landmarks: Tensor, points_per_bone: int = 20) -> tuple[Tensor, Tensor]:
    """Points along the bones of a pose, coloured by side, for 3D point-cloud views (TensorBoard's mesh plugin).

    Args:
        landmarks: (J, 3) world positions of LANDMARKS (J = 16).
        points_per_bone: n >= 2 evenly spaced points per bone, both ends included.

    Returns:
        points: (P, 3) with P = E * n for the E bones of LANDMARK_EDGES, bone by bone; dtype and device of
            ``landmarks``.
        colours: (P, 3) RGB in [0, 1] (:func:`landmark_colours` of the bones).
    """
    check_shape(landmarks, (len(LANDMARKS), 3), "landmarks")
    if points_per_bone < 2:
        raise InputError(f"points_per_bone must be >= 2, got {points_per_bone}")
    dtype = landmarks.dtype if landmarks.is_floating_point() else torch.float32
    x = landmarks.to(dtype)
    edges = torch.tensor(LANDMARK_EDGES, device=x.device)  # (E, 2)
    t = torch.linspace(0.0, 1.0, points_per_bone, dtype=dtype, device=x.device)[None, :, None]  # (1, n, 1)
    a, b = x[edges[:, 0]][:, None], x[edges[:, 1]][:, None]  # (E, 1, 3)
    points = (a + t * (b - a)).reshape(-1, 3)  # (E * n, 3)
    _, bone_rgb = landmark_colours()
    colours = torch.tensor(bone_rgb, dtype=dtype, device=x.device).repeat_interleave(points_per_bone, 0)
    return points, colours


def draw_marker_overlays(images: Tensor, rig: CameraRig, markers: Tensor | None = None,
                         detections: Tensor | None = None, landmarks: Tensor | None = None, *,
                         ring_radius_px: int = 5, dot_radius_px: int = 2) -> Tensor:
    """The marker tracker's view of one frame: the skeleton (:func:`draw_pose_overlays`), every detection as a
    white dot and the model's markers projected as green rings, so that a ring without its dot is a marker the
    detector missed and a dot without a ring a false detection or another marker's.

    Args:
        images: (C, 3, H, W) float RGB in [0, 1] at the calibrated size (video frames, or a blank canvas).
        rig: the C cameras. markers: (M, 3) world points, NaN where not tracked.
        detections: (C, N, 2) distorted pixels, NaN where none (e.g. ``markers2d.npz``'s ``uv`` of one frame,
            markers and candidates flattened).
        landmarks: (16, 3) or None.

    Returns:
        (C, 3, H, W) a copy of ``images`` with the overlays.
    """
    import cv2

    out = draw_pose_overlays(images, rig, landmarks)
    canvas = out.detach().permute(0, 2, 3, 1).to("cpu", torch.float32).numpy().copy()  # (C, H, W, 3)
    if detections is not None:
        check_shape(detections, (rig.num_cameras, "N", 2), "detections")
        det = detections.detach().cpu().double().numpy()
        for c in range(rig.num_cameras):
            for uv in det[c][np.isfinite(det[c]).all(-1)]:
                cv2.circle(canvas[c], tuple(int(x) for x in _fixed(uv)), dot_radius_px << _SHIFT, DETECTION_RGB,
                           -1, cv2.LINE_AA, _SHIFT)
    if markers is not None:
        check_shape(markers, ("M", 3), "markers")
        uv, _, inside = _pixels(rig, markers.to(rig.K.device, rig.K.dtype))
        uv, inside = uv.cpu().numpy(), inside.cpu().numpy()
        for c in range(rig.num_cameras):
            for m in np.flatnonzero(inside[c]):
                cv2.circle(canvas[c], tuple(int(x) for x in _fixed(uv[c, m])), ring_radius_px << _SHIFT, MARKER_RGB,
                           1, cv2.LINE_AA, _SHIFT)
    return torch.from_numpy(canvas).permute(0, 3, 1, 2).to(device=images.device, dtype=images.dtype)
