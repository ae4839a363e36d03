"""CameraRig: C calibrated cameras as one ``nn.Module`` with buffers, projecting batched over cameras.

Conventions (see :mod:`torchtrack.conventions`): OpenCV cameras (x right, y down, z forward), extrinsics map
world to camera ``x_cam = R_cam_world @ x_world + t_cam_world``, intrinsics ``K`` in pixels with pixel
centres at integer coordinates, so the image covers ``-0.5 <= u < W - 0.5`` and ``-0.5 <= v < H - 0.5``.
Distortion is OpenCV's, pinhole ``(k1, k2, p1, p2, k3)`` or fisheye ``(k1, k2, k3, k4)``
(:mod:`torchtrack.cameras.distortion`). Lengths are in the unit of ``t_cam_world`` (metres for torchtrack
rigs; importers keep other units as they are).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from kornia.geometry.camera import PinholeCamera
from torch import Tensor

from torchtrack.cameras import distortion
from torchtrack.checks import InputError, ShapeError, check_finite, check_shape

#: Largest accepted ``max |R R^T - I|`` for a rotation matrix (float32 storage leaves about 1e-7).
ROTATION_TOL = 1e-5
#: Smallest camera-frame depth of a point that counts as in front of the camera (rig length unit).
MIN_DEPTH = 1e-6


def rotation_error(R: Tensor) -> Tensor:
    """``max |R R^T - I|`` per matrix, ``(..., 3, 3) -> (...)``, with ``inf`` where ``det(R) <= 0``."""
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    err = (R @ R.transpose(-1, -2) - eye).abs().amax(dim=(-1, -2))
    return torch.where(torch.linalg.det(R) > 0, err, torch.full_like(err, float("inf")))


class CameraRig(torch.nn.Module):
    """C calibrated cameras (pinhole or fisheye, OpenCV models).

    Buffers (move with ``.to()``): ``K (C, 3, 3)``, ``R_cam_world (C, 3, 3)``, ``t_cam_world (C, 3)``,
    ``image_size_wh (C, 2) int64``, ``dist (C, 5)``, ``fisheye_mask (C,) bool``. The float dtype is the one of
    ``K``; the other float inputs are converted to it.

    Args:
        names: C unique camera names.
        K: ``(C, 3, 3)`` intrinsics in pixels; positive focal lengths, no skew, last row ``(0, 0, 1)``.
        R_cam_world: ``(C, 3, 3)`` rotations world -> camera.
        t_cam_world: ``(C, 3)`` translations world -> camera.
        image_size_wh: ``(C, 2)`` integer image sizes (width, height) in pixels, positive.
        dist: ``(C, 5)`` (or ``(C, 4)``, padded with 0) distortion coefficients; pinhole cameras
            ``(k1, k2, p1, p2, k3)``, fisheye cameras ``(k1, k2, k3, k4, unused)``. None: no distortion.
        fisheye: C flags, True for the OpenCV fisheye model. None: all pinhole.

    Raises:
        ShapeError: a tensor has the wrong shape.
        InputError: bad values, naming the camera (non-finite, not a rotation, focal length or size <= 0,
            skew, duplicate names).
    """

    K: Tensor
    R_cam_world: Tensor
    t_cam_world: Tensor
    image_size_wh: Tensor
    dist: Tensor
    fisheye_mask: Tensor

    def __init__(self, names: Sequence[str], K: Tensor, R_cam_world: Tensor, t_cam_world: Tensor,
                 image_size_wh: Tensor, dist: Tensor | None = None,
                 fisheye: Sequence[bool] | None = None) -> None:
        super().__init__()
        names = list(names)
        if not all(isinstance(n, str) and n for n in names):
            raise InputError(f"camera names must be non-empty strings, got {names!r}")
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise InputError(f"camera names must be unique, repeated: {dupes}")
        C = len(names)
        if C == 0:
            raise InputError("a CameraRig needs at least one camera")
        check_shape(K, (C, 3, 3), "K")
        if not K.is_floating_point():
            raise TypeError(f"K: expected a floating point tensor, got {K.dtype}")
        dtype, device = K.dtype, K.device
        check_shape(R_cam_world, (C, 3, 3), "R_cam_world")
        check_shape(t_cam_world, (C, 3), "t_cam_world")
        check_shape(image_size_wh, (C, 2), "image_size_wh")
        if dist is None:
            dist = torch.zeros(C, 5, dtype=dtype, device=device)
        check_shape(dist, (C, None), "dist")
        if dist.shape[1] not in (4, 5):
            raise ShapeError(f"dist: expected shape (C, 5) or (C, 4), got {tuple(dist.shape)}")
        dist = torch.nn.functional.pad(dist.to(dtype), (0, 5 - dist.shape[1]))
        fisheye = [False] * C if fisheye is None else [bool(f) for f in fisheye]
        if len(fisheye) != C:
            raise ShapeError(f"fisheye: expected {C} flags, got {len(fisheye)}")
        self._names = names
        tensors = {"K": K, "R_cam_world": R_cam_world.to(dtype), "t_cam_world": t_cam_world.to(dtype),
                   "dist": dist}
        for key, value in tensors.items():
            if value.device != device:
                raise InputError(f"{key} is on {value.device}, K on {device}: put all tensors on one device")
            check_finite(value, key)
        size = self._check_size(image_size_wh)
        self._check_values(tensors["K"], tensors["R_cam_world"])
        for key, value in tensors.items():
            self.register_buffer(key, value.clone())
        self.register_buffer("image_size_wh", size.to(device))
        self.register_buffer("fisheye_mask", torch.tensor(fisheye, dtype=torch.bool, device=device))

    # ----------------------------------------------------------------------------------------- validation
    def _check_size(self, size: Tensor) -> Tensor:
        if size.is_floating_point():
            check_finite(size, "image_size_wh")
            if bool((size != size.round()).any()):
                raise InputError(f"image_size_wh: sizes must be whole pixels, got {size.tolist()}")
        elif size.dtype == torch.bool or size.is_complex():
            raise TypeError(f"image_size_wh: expected integers, got {size.dtype}")
        size = size.to(torch.int64)
        for name, (w, h) in zip(self._names, size.tolist()):
            if w <= 0 or h <= 0:
                raise InputError(f"camera {name!r}: image size must be positive, got {w}x{h}")
        return size

    def _check_values(self, K: Tensor, R: Tensor) -> None:
        err = rotation_error(R.to(torch.float64) if R.device.type != "mps" else R)
        for name, k, e in zip(self._names, K.tolist(), err.tolist()):
            if k[0][0] <= 0 or k[1][1] <= 0:
                raise InputError(f"camera {name!r}: focal lengths must be positive, got fx={k[0][0]}, fy={k[1][1]}")
            if k[0][1] != 0 or k[1][0] != 0 or k[2] != [0.0, 0.0, 1.0]:
                raise InputError(f"camera {name!r}: K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] "
                                 f"(skew is not supported by the OpenCV distortion models), got {k}")
            if not e <= ROTATION_TOL:
                raise InputError(f"camera {name!r}: R_cam_world is not a rotation (max |R R^T - I| = {e:.3g}"
                                 f"{', det <= 0' if e == float('inf') else ''}; tolerance {ROTATION_TOL:g})")

    # ----------------------------------------------------------------------------------------- properties
    @property
    def names(self) -> list[str]:
        """Camera names, in order."""
        return list(self._names)

    @property
    def num_cameras(self) -> int:
        return len(self._names)

    def __len__(self) -> int:
        return len(self._names)

    @property
    def fisheye(self) -> list[bool]:
        """Per camera: True for the OpenCV fisheye model."""
        return [bool(f) for f in self.fisheye_mask.tolist()]

    def extra_repr(self) -> str:
        sizes = [f"{w}x{h}" for w, h in self.image_size_wh.tolist()]
        return f"names={self._names}, sizes={sizes}, fisheye={self.fisheye}, dtype={self.K.dtype}"

    def _index(self, key: str | int) -> int:
        if isinstance(key, str):
            if key not in self._names:
                raise InputError(f"no camera named {key!r}; cameras: {self._names}")
            return self._names.index(key)
        if isinstance(key, bool) or not isinstance(key, int) or not -len(self) <= key < len(self):
            raise InputError(f"camera index {key!r} out of range for {len(self)} cameras")
        return key % len(self)

    # ---------------------------------------------------------------------------------------- derived rigs
    def subset(self, names_or_indices: Sequence[str | int]) -> CameraRig:
        """The rig of the given cameras (names or indices, in the given order)."""
        if isinstance(names_or_indices, (str, int)):
            names_or_indices = [names_or_indices]
        idx = [self._index(k) for k in names_or_indices]
        sel = torch.tensor(idx, dtype=torch.long, device=self.K.device)
        return CameraRig([self._names[i] for i in idx], self.K[sel], self.R_cam_world[sel],
                         self.t_cam_world[sel], self.image_size_wh[sel], self.dist[sel],
                         [self.fisheye[i] for i in idx])

    def resized(self, width: int, height: int) -> CameraRig:
        """The same cameras seeing the images resized to ``width x height`` (every camera).

        With pixel centres at integer coordinates, ``u' = (u + 0.5) * width / W - 0.5``: focal lengths scale
        by ``width / W`` (``height / H``) and ``c' = (c + 0.5) * s - 0.5``. Distortion is unchanged (it acts
        on normalized coordinates).
        """
        if int(width) != width or int(height) != height or width <= 0 or height <= 0:
            raise InputError(f"resized: width and height must be positive integers, got {width}x{height}")
        new_size = torch.tensor([width, height], dtype=self.K.dtype, device=self.K.device)
        scale = new_size / self.image_size_wh.to(self.K.dtype)  # (C, 2)
        K = self.K.clone()
        K[:, 0, 0] = K[:, 0, 0] * scale[:, 0]
        K[:, 1, 1] = K[:, 1, 1] * scale[:, 1]
        K[:, :2, 2] = (K[:, :2, 2] + 0.5) * scale - 0.5
        size = new_size.to(torch.int64).expand(len(self), 2)
        return CameraRig(self._names, K, self.R_cam_world, self.t_cam_world, size, self.dist, self.fisheye)

    def pinhole(self) -> PinholeCamera:
        """kornia's ``PinholeCamera`` of this rig: 4x4 intrinsics and extrinsics ``(C, 4, 4)``, heights and
        widths ``(C,)``. It has no lens distortion: use :meth:`project` for distorted pixels."""
        C, dtype, device = len(self), self.K.dtype, self.K.device
        intrinsics = torch.eye(4, dtype=dtype, device=device).repeat(C, 1, 1)
        intrinsics[:, :3, :3] = self.K
        extrinsics = torch.eye(4, dtype=dtype, device=device).repeat(C, 1, 1)
        extrinsics[:, :3, :3] = self.R_cam_world
        extrinsics[:, :3, 3] = self.t_cam_world
        size = self.image_size_wh.to(dtype)
        return PinholeCamera(intrinsics, extrinsics, size[:, 1].clone(), size[:, 0].clone())

    # ----------------------------------------------------------------------------------------- geometry
    def _params(self, dtype: torch.dtype) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        return (self.K.to(dtype), self.R_cam_world.to(dtype), self.t_cam_world.to(dtype), self.dist.to(dtype))

    def centers(self) -> Tensor:
        """Camera centres in the world frame, ``(C, 3)``: ``-R^T t``."""
        return -(self.R_cam_world.transpose(-1, -2) @ self.t_cam_world[..., None])[..., 0]

    def world_to_camera(self, points: Tensor) -> Tensor:
        """World points into every camera frame.

        Args:
            points: ``(..., N, 3)`` world points (any leading dims).

        Returns:
            ``(C, ..., N, 3)`` camera-frame points, in the promoted dtype of ``points`` and the rig.
        """
        check_shape(points, ("...", "N", 3), "points")
        dtype = torch.promote_types(points.dtype, self.K.dtype)
        _, R, t, _ = self._params(dtype)
        flat = points.to(dtype).reshape(-1, 3)  # (M, 3)
        cam = torch.einsum("cij,mj->cmi", R, flat) + t[:, None, :]  # (C, M, 3)
        return cam.reshape(len(self), *points.shape)

    def project(self, points_world: Tensor) -> tuple[Tensor, Tensor]:
        """Project world points into every camera, with lens distortion.

        Args:
            points_world: ``(..., N, 3)`` world points.

        Returns:
            uv_px: ``(C, ..., N, 2)`` distorted pixel coordinates (OpenCV ``projectPoints`` values wherever
                ``|z| > MIN_DEPTH``; finite but meaningless where ``valid`` is False).
            valid: ``(C, ..., N)`` bool: in front of the camera (``z > MIN_DEPTH``), inside the image
                (``-0.5 <= u < W - 0.5``, same for v) and within the radius where the distortion model is
                monotonic (:func:`~torchtrack.cameras.distortion.fold_radius_sq`; beyond it OpenCV folds points
                from far outside the field of view back into the image).
        """
        xy, in_model, lead = self._normalized(points_world)  # (C, M, 2) undistorted normalized, (C, M)
        C = len(self)
        K, _, _, dist = self._params(xy.dtype)
        xy_d = distortion.distort(xy, dist, self.fisheye_mask)  # (C, M, 2) distorted normalized
        f = torch.stack([K[:, 0, 0], K[:, 1, 1]], -1)[:, None, :]  # (C, 1, 2)
        c = K[:, :2, 2][:, None, :]  # (C, 1, 2)
        uv = xy_d * f + c  # (C, M, 2)
        size = self.image_size_wh.to(uv.dtype)[:, None, :]  # (C, 1, 2)
        inside = ((uv >= -0.5) & (uv < size - 0.5)).all(-1)  # (C, M)
        return uv.reshape(C, *lead, 2), (inside & in_model).reshape(C, *lead)

    def _normalized(self, points_world: Tensor) -> tuple[Tensor, Tensor, tuple[int, ...]]:
        """``(..., N, 3)`` world points -> undistorted normalized coordinates ``(C, M, 2)`` (M = ...*N), whether
        each is in front of its camera and within the radius where the distortion model is monotonic ``(C, M)``,
        and the leading shape ``(..., N)``."""
        cam = self.world_to_camera(points_world)  # (C, ..., N, 3)
        C, lead = len(self), tuple(cam.shape[1:-1])
        _, _, _, dist = self._params(cam.dtype)
        cam = cam.reshape(C, -1, 3)
        z = cam[..., 2]
        xy = cam[..., :2] / torch.where(z.abs() > MIN_DEPTH, z, torch.full_like(z, MIN_DEPTH))[..., None]
        in_model = (xy * xy).sum(-1) < distortion.fold_radius_sq(dist, self.fisheye_mask)[:, None]
        return xy, (z > MIN_DEPTH) & in_model, lead

    def in_lens_model(self, points_world: Tensor) -> Tensor:
        """``(..., N, 3)`` world points -> ``(C, ..., N)`` bool: in front of each camera and within the radius where
        its distortion model is monotonic (:meth:`project`'s ``valid`` without the image bounds)."""
        _, ok, lead = self._normalized(points_world)
        return ok.reshape(len(self), *lead)

    def pixel_rays(self, uv_px: Tensor) -> tuple[Tensor, Tensor]:
        """World rays through (distorted) pixels, one camera per leading index.

        Args:
            uv_px: ``(C, ..., N, 2)`` pixel coordinates in each camera's (distorted) image.

        Returns:
            origins: ``(C, ..., N, 3)`` the camera centres.
            directions: ``(C, ..., N, 3)`` unit world-frame directions (towards ``z > 0`` in the camera).
        """
        check_shape(uv_px, ("...", "N", 2), "uv_px")
        if uv_px.dim() < 3 or uv_px.shape[0] != len(self):
            raise ShapeError(f"uv_px: expected shape (C, ..., N, 2), got {tuple(uv_px.shape)}")
        dtype = torch.promote_types(uv_px.dtype, self.K.dtype)
        K, R, _, dist = self._params(dtype)
        C, lead = len(self), uv_px.shape[1:-1]
        uv = uv_px.to(dtype).reshape(C, -1, 2)  # (C, M, 2)
        f = torch.stack([K[:, 0, 0], K[:, 1, 1]], -1)[:, None, :]  # (C, 1, 2)
        xy_d = (uv - K[:, :2, 2][:, None, :]) / f  # (C, M, 2) distorted normalized
        xy = distortion.undistort(xy_d, dist, self.fisheye_mask)  # (C, M, 2)
        d_cam = torch.cat([xy, torch.ones_like(xy[..., :1])], -1)  # (C, M, 3)
        d_world = torch.einsum("cji,cmj->cmi", R, d_cam)  # R^T d, (C, M, 3)
        d_world = d_world / d_world.norm(dim=-1, keepdim=True)
        origins = self.centers().to(dtype)[:, None, :].expand_as(d_world)
        return origins.reshape(C, *lead, 3), d_world.reshape(C, *lead, 3)
