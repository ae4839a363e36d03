"""Lens distortion on the normalized image plane (``z = 1``), batched over cameras.

Models (OpenCV's, coefficients stored in one ``(C, 5)`` buffer):

* pinhole: ``(k1, k2, p1, p2, k3)``, the OpenCV ``projectPoints`` model;
* fisheye: ``(k1, k2, k3, k4, unused)``, the OpenCV ``cv2.fisheye`` model, which is the Kannala-Brandt
  model ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)`` (no skew).

The forward maps and the first guess of the inverse maps are kornia's
(``kornia.geometry.calibration.distort_points / undistort_points`` for pinhole,
``kornia.geometry.camera.distort_points_kannala_brandt / undistort_points_kannala_brandt`` for fisheye).
Written here, because kornia lacks them:

* a Newton polish of the pinhole inverse: kornia's fixed-point iteration has no convergence test and converges
  slowly for strong barrel distortion (about 2 px off in the corners of a real k1 = -0.34 webcam after its
  default 5 steps, kornia issue #4285);
* :func:`fold_radius_sq`, the radius where the radial polynomial stops growing: beyond it the model folds
  back, and points far outside the field of view land inside the image (OpenCV's projectPoints does this).

All functions take the flattened layout: points ``(C, M, 2)``, coefficients ``(C, 5)``, fisheye mask ``(C,)``.
"""

from __future__ import annotations

import torch
from kornia.geometry.calibration import distort_points, undistort_points
from kornia.geometry.camera import distort_points_kannala_brandt, undistort_points_kannala_brandt

#: Fixed-point steps of kornia's pinhole inverse used as the first guess for Newton's method.
_FIXED_POINT_STEPS = 10
#: Newton steps after it (quadratic convergence: 3 reach float64 rounding for the real rigs).
_NEWTON_STEPS = 3
#: Samples of the radius when searching for the fold of the radial polynomial.
_FOLD_SAMPLES = 4096
#: Largest normalized radius searched for pinhole cameras (about 84 degrees off axis).
_FOLD_MAX_RADIUS = 10.0


def _eye_like(coeffs: torch.Tensor) -> torch.Tensor:
    """Identity intrinsics ``(C, 3, 3)`` for kornia's pixel-based API, so it works on normalized coordinates."""
    eye = torch.eye(3, dtype=coeffs.dtype, device=coeffs.device)
    return eye.expand(coeffs.shape[0], 3, 3)


def _kb_params(coeffs: torch.Tensor) -> torch.Tensor:
    """kornia's Kannala-Brandt parameter vector ``(C, 1, 8)`` = [fx=1, fy=1, cx=0, cy=0, k1..k4]."""
    affine = torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=coeffs.dtype, device=coeffs.device)
    return torch.cat([affine.expand(coeffs.shape[0], 4), coeffs[:, :4]], dim=-1)[:, None, :]


def distort(xy: torch.Tensor, coeffs: torch.Tensor, fisheye: torch.Tensor) -> torch.Tensor:
    """Undistorted -> distorted normalized coordinates.

    Args:
        xy: ``(C, M, 2)`` points on the ``z = 1`` plane (x/z, y/z).
        coeffs: ``(C, 5)`` distortion coefficients (layout in the module docstring).
        fisheye: ``(C,)`` bool, which cameras use the fisheye model.

    Returns:
        ``(C, M, 2)`` distorted normalized coordinates (apply K for pixels).
    """
    any_fisheye, all_fisheye = bool(fisheye.any()), bool(fisheye.all())
    pin = None if all_fisheye else distort_points(xy, _eye_like(coeffs), coeffs)  # (C, M, 2)
    if not any_fisheye:
        return pin
    fish = distort_points_kannala_brandt(xy, _kb_params(coeffs))  # (C, M, 2)
    return fish if pin is None else torch.where(fisheye[:, None, None], fish, pin)


def _pinhole_jacobian(xy: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """Jacobian of the OpenCV pinhole distortion w.r.t. the undistorted point, ``(C, M, 2, 2)``."""
    x, y = xy[..., 0], xy[..., 1]  # (C, M)
    k1, k2, p1, p2, k3 = (coeffs[:, i:i + 1] for i in range(5))  # (C, 1) each
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))  # (C, M)
    dradial_dr2 = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # (C, M)
    dxd_dx = radial + 2 * x * x * dradial_dr2 + 2 * p1 * y + 6 * p2 * x
    dxd_dy = 2 * x * y * dradial_dr2 + 2 * p1 * x + 2 * p2 * y
    dyd_dx = 2 * x * y * dradial_dr2 + 2 * p1 * x + 2 * p2 * y
    dyd_dy = radial + 2 * y * y * dradial_dr2 + 6 * p1 * y + 2 * p2 * x
    return torch.stack([torch.stack([dxd_dx, dxd_dy], -1), torch.stack([dyd_dx, dyd_dy], -1)], -2)


def _undistort_pinhole(xy_d: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """Inverse of the pinhole model: kornia's fixed point as first guess, then Newton. ``(C, M, 2)``."""
    eye = _eye_like(coeffs)
    xy = undistort_points(xy_d, eye, coeffs, num_iters=_FIXED_POINT_STEPS)  # (C, M, 2)
    for _ in range(_NEWTON_STEPS):
        residual = distort_points(xy, eye, coeffs) - xy_d  # (C, M, 2)
        jac = _pinhole_jacobian(xy, coeffs)  # (C, M, 2, 2)
        a, b, c, d = jac[..., 0, 0], jac[..., 0, 1], jac[..., 1, 0], jac[..., 1, 1]
        det = a * d - b * c  # (C, M); 2x2 solve written out (torch.linalg.solve is slow for tiny systems)
        det = torch.where(det.abs() > 1e-12, det, torch.ones_like(det))
        step_x = (d * residual[..., 0] - b * residual[..., 1]) / det
        step_y = (a * residual[..., 1] - c * residual[..., 0]) / det
        xy = xy - torch.stack([step_x, step_y], -1)
    return xy


def undistort(xy_d: torch.Tensor, coeffs: torch.Tensor, fisheye: torch.Tensor) -> torch.Tensor:
    """Distorted -> undistorted normalized coordinates (the inverse of :func:`distort`).

    Args:
        xy_d: ``(C, M, 2)`` distorted normalized coordinates (``K^-1`` applied to pixels).
        coeffs: ``(C, 5)``; fisheye: ``(C,)`` bool.

    Returns:
        ``(C, M, 2)`` points on the ``z = 1`` plane. Accurate to float rounding inside the image; meaningless
        beyond the fold radius (:func:`fold_radius_sq`), where the forward model is not invertible.
    """
    any_fisheye, all_fisheye = bool(fisheye.any()), bool(fisheye.all())
    pin = None if all_fisheye else _undistort_pinhole(xy_d, coeffs)
    if not any_fisheye:
        return pin
    fish = undistort_points_kannala_brandt(xy_d, _kb_params(coeffs))  # (C, M, 2)
    return fish if pin is None else torch.where(fisheye[:, None, None], fish, pin)


def _first_fold(arg: torch.Tensor, slope: torch.Tensor) -> torch.Tensor:
    """For sampled ``arg (S,)`` and ``slope (C, S)``: the last sample before the slope first drops to <= 0.

    Returns ``(C,)``, ``inf`` where the slope stays positive over all samples.
    """
    bad = slope <= 0  # (C, S)
    first = torch.where(bad.any(-1), bad.int().argmax(-1), torch.full_like(bad[:, 0], -1, dtype=torch.long))
    before = arg[(first - 1).clamp(min=0)]  # (C,)
    inf = torch.full_like(before, float("inf"))
    return torch.where(first < 0, inf, before)


def fold_radius_sq(coeffs: torch.Tensor, fisheye: torch.Tensor) -> torch.Tensor:
    """Squared normalized radius up to which the radial model grows monotonically, per camera.

    Pinhole: ``rho(r) = r (1 + k1 r^2 + k2 r^4 + k3 r^6)``; fisheye: ``theta_d(theta)`` on ``[0, pi/2)``, with
    ``r = tan(theta)``. Tangential terms are ignored (they are orders of magnitude smaller). The result is
    a sampled lower bound (the last sample before the slope turns), ``inf`` where there is no fold.

    Args:
        coeffs: ``(C, 5)``; fisheye: ``(C,)`` bool.

    Returns:
        ``(C,)`` squared radius on the ``z = 1`` plane.
    """
    work = torch.float64 if coeffs.device.type != "mps" else torch.float32
    c = coeffs.to(work)
    # Pinhole: d rho / d r = 1 + 3 k1 r^2 + 5 k2 r^4 + 7 k3 r^6.
    r = torch.linspace(0.0, _FOLD_MAX_RADIUS, _FOLD_SAMPLES, dtype=work, device=coeffs.device)[1:]  # (S,)
    r2 = r * r
    k1, k2, k3 = c[:, 0:1], c[:, 1:2], c[:, 4:5]
    slope_pin = 1 + r2 * (3 * k1 + r2 * (5 * k2 + r2 * 7 * k3))  # (C, S)
    r_pin = _first_fold(r, slope_pin)  # (C,)
    # Fisheye: d theta_d / d theta = 1 + 3 k1 t^2 + 5 k2 t^4 + 7 k3 t^6 + 9 k4 t^8 on [0, pi/2).
    theta = torch.linspace(0.0, torch.pi / 2, _FOLD_SAMPLES + 1, dtype=work, device=coeffs.device)[1:-1]
    t2 = theta * theta
    f1, f2, f3, f4 = c[:, 0:1], c[:, 1:2], c[:, 2:3], c[:, 3:4]
    slope_fish = 1 + t2 * (3 * f1 + t2 * (5 * f2 + t2 * (7 * f3 + t2 * 9 * f4)))  # (C, S)
    r_fish = torch.tan(_first_fold(theta, slope_fish))  # (C,); tan(inf) is nan: handled below
    r_fish = torch.where(torch.isnan(r_fish), torch.full_like(r_fish, float("inf")), r_fish)
    radius = torch.where(fisheye, r_fish, r_pin)
    return (radius * radius).to(coeffs.dtype)
