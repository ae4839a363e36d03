"""Ghost voxels (torchtrack/tracking/ghosts.py) against a plain loop of ray-ellipsoid intersections, and the
ghosts of a 4-camera visual hull of two legs on the diagonal."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchtrack.checks import InputError, ShapeError
from torchtrack.tracking.ghosts import ghost_voxels


def _reference(points, seen, centres, mean, cov, inside_scale, cover_scale, covers=None, self_scale=0.0):
    """Per voxel, camera and ellipsoid {x: (x - m)^T cov^-1 (x - m) <= 5 s^2}: the quadratic of the line from
    the camera through the voxel, a hit where its roots are real and the far one lies in front of the camera
    (an ellipsoid that holds the voxel when grown by ``self_scale`` is no hit)."""
    out = np.zeros(len(points), bool)
    inv = [np.linalg.inv(c) for c in cov]
    covers = np.ones(len(mean), bool) if covers is None else covers
    for n, v in enumerate(points):
        if not seen[n].any():
            continue
        if any((v - m) @ A @ (v - m) <= 5 * inside_scale ** 2 for m, A in zip(mean, inv)):
            continue
        ghost = True
        for c, o in enumerate(centres):
            if not seen[n, c]:
                continue
            d = v - o
            hit = False
            for m, A, may in zip(mean, inv, covers):
                if not may or (v - m) @ A @ (v - m) <= 5 * self_scale ** 2:
                    continue
                a, b, cc = d @ A @ d, 2 * d @ A @ (o - m), (o - m) @ A @ (o - m) - 5 * cover_scale ** 2
                disc = b * b - 4 * a * cc
                if disc >= 0 and (-b + np.sqrt(disc)) / (2 * a) > 0:
                    hit = True
                    break
            ghost &= hit
        out[n] = ghost
    return out


def _reference_batched(points, seen, centres, mean, cov, inside_scale, cover_scale):
    """_reference's quadratics for all voxels, cameras and ellipsoids at once, in float64 numpy (for the many
    voxels a float32 check needs)."""
    inv = np.linalg.inv(cov)  # (K, 3, 3)
    rel = points[:, None] - mean[None]  # (N, K, 3)
    inside = (np.einsum("nki,kij,nkj->nk", rel, inv, rel) <= 5 * inside_scale ** 2).any(1)
    hit = np.zeros(seen.shape, bool)
    for c, o in enumerate(centres):
        d = points - o  # (N, 3)
        om = o - mean  # (K, 3)
        a = np.einsum("ni,kij,nj->nk", d, inv, d)
        b = 2 * np.einsum("ni,kij,kj->nk", d, inv, om)
        cc = np.einsum("ki,kij,kj->k", om, inv, om) - 5 * cover_scale ** 2
        disc = b * b - 4 * a * cc
        far_root = (-b + np.sqrt(np.maximum(disc, 0))) / (2 * a)
        hit[:, c] = ((disc >= 0) & (far_root > 0)).any(1)
    return ~inside & seen.any(1) & (hit | ~seen).all(1)


def test_ghost_voxels_match_a_plain_loop_of_ray_ellipsoid_intersections():
    rng = np.random.default_rng(0)
    K, C, N = 5, 4, 400
    mean = rng.uniform(-0.4, 0.4, (K, 3)) + [0, 0, 1.0]
    A = rng.normal(size=(K, 3, 3)) * 0.15
    cov = A @ A.transpose(0, 2, 1) + 0.004 * np.eye(3)
    az = np.arange(C) * 2 * np.pi / C + 0.3
    centres = np.stack([3.5 * np.cos(az), 3.5 * np.sin(az), np.full(C, 2.2)], 1)
    points = rng.uniform([-0.7, -0.7, 0.4], [0.7, 0.7, 1.6], (N, 3))
    seen = rng.uniform(size=(N, C)) > 0.1
    seen[:5] = False  # seen by no view: never a ghost
    for inside_scale, cover_scale in ((1.15, 1.2), (1.0, 1.0), (0.8, 1.5)):
        ref = _reference(points, seen, centres, mean, cov, inside_scale, cover_scale)
        got = ghost_voxels(torch.tensor(points), torch.tensor(seen), torch.tensor(centres), torch.tensor(mean),
                           torch.tensor(cov), inside_scale, cover_scale, chunk=64).numpy()
        assert 20 < ref.sum() < N - 20  # both kinds present
        np.testing.assert_array_equal(got, ref)
        np.testing.assert_array_equal(_reference_batched(points, seen, centres, mean, cov, inside_scale,
                                                         cover_scale), ref)
    # only some blobs may explain a ray (the tracker's: those its last frame filled); all count for "inside"
    covers = np.array([True, False, True, False, True])
    ref = _reference(points, seen, centres, mean, cov, 1.15, 1.2, covers)
    got = ghost_voxels(torch.tensor(points), torch.tensor(seen), torch.tensor(centres), torch.tensor(mean),
                       torch.tensor(cov), 1.15, 1.2, covers=torch.tensor(covers)).numpy()
    assert 10 < ref.sum() < _reference(points, seen, centres, mean, cov, 1.15, 1.2).sum()
    np.testing.assert_array_equal(got, ref)
    # a blob does not explain a voxel inside its own ellipsoid grown by self_scale
    for self_scale in (1.3, 2.0):
        ref = _reference(points, seen, centres, mean, cov, 1.15, 1.2, covers, self_scale)
        got = ghost_voxels(torch.tensor(points), torch.tensor(seen), torch.tensor(centres), torch.tensor(mean),
                           torch.tensor(cov), 1.15, 1.2, covers=torch.tensor(covers), chunk=64,
                           self_scale=self_scale).numpy()
        assert 5 < ref.sum() < _reference(points, seen, centres, mean, cov, 1.15, 1.2, covers).sum()
        np.testing.assert_array_equal(got, ref)


def test_frames_of_different_rigs_in_one_batch_match_the_plain_loop_each():
    """Three frames padded into one batch (the lockstep tracker's): different voxel counts, 3 to 5 cameras, bodies
    and covering blobs; each frame's ghosts are the plain loop's on that frame alone, and padding is no ghost."""
    rng = np.random.default_rng(1)
    K, frames = 5, []
    for N, C in ((300, 4), (180, 3), (250, 5)):
        mean = rng.uniform(-0.4, 0.4, (K, 3)) + [rng.uniform(-1, 1), rng.uniform(-1, 1), 1.0]
        A = rng.normal(size=(K, 3, 3)) * 0.15
        cov = A @ A.transpose(0, 2, 1) + 0.004 * np.eye(3)
        az = np.arange(C) * 2 * np.pi / C + rng.uniform(0, 1)
        centres = np.stack([3.5 * np.cos(az), 3.5 * np.sin(az), np.full(C, 2.2)], 1)
        points = mean.mean(0) + rng.uniform(-0.7, 0.7, (N, 3))
        seen = rng.uniform(size=(N, C)) > 0.1
        covers = rng.uniform(size=K) > 0.3
        frames.append((points, seen, centres, mean, cov, covers))
    B, N, C = len(frames), max(len(f[0]) for f in frames), max(f[2].shape[0] for f in frames)
    points, seen = np.full((B, N, 3), np.nan), np.zeros((B, N, C), bool)
    centres, mean, cov = np.zeros((B, C, 3)), np.stack([f[3] for f in frames]), np.stack([f[4] for f in frames])
    for b, (p, sn, cen, *_) in enumerate(frames):
        points[b, :len(p)], seen[b, :len(p), :sn.shape[1]], centres[b, :len(cen)] = p, sn, cen
    got = ghost_voxels(torch.tensor(points), torch.tensor(seen), torch.tensor(centres), torch.tensor(mean),
                       torch.tensor(cov), 1.15, 1.2, covers=torch.tensor(np.stack([f[5] for f in frames])),
                       self_scale=1.3, chunk=64).numpy()
    for b, (p, sn, cen, m, c, cv) in enumerate(frames):
        ref = _reference(p, sn, cen, m, c, 1.15, 1.2, cv, 1.3)
        assert 5 < ref.sum() < len(p) - 5
        np.testing.assert_array_equal(got[b, :len(p)], ref)
        assert not got[b, len(p):].any()


def test_a_limb_that_moved_past_its_prediction_is_not_explained_away_by_itself():
    """An arm raised faster than predicted, seen by 4 cameras 5 m up that look down on it: the voxels just
    beyond the predicted arm's tip have every view's ray through the predicted arm itself, so without
    ``self_scale`` they are ghosts and the arm cannot follow them; inside its ellipsoid grown by ``self_scale``
    the arm does not explain them. A hand-sized ball just above the tip, whose own shell does not hold the tip,
    still explains it in every view."""
    az = np.arange(4) * np.pi / 2 + np.pi / 4
    centres = np.stack([2.5 * np.cos(az), 2.5 * np.sin(az), np.full(4, 5.0)], 1)
    tip_z = 1.6 + 0.3 * 1.18  # outside the arm grown by 1.15, inside it grown by 1.3
    arm = (np.array([0.0, 0.0, 1.6]), np.diag([0.04 ** 2, 0.04 ** 2, 0.3 ** 2]) / 5)  # semi-axes 4, 4, 30 cm
    ball = (np.array([0.0, 0.0, tip_z + 0.097]), np.eye(3) * 0.07 ** 2 / 5)  # 7 cm, 1.39x its radius away
    tip = np.array([[0.0, 0.0, tip_z]])
    seen = np.ones((1, 4), bool)
    for blobs, self_scale, ghost in (([arm], 0.0, True), ([arm], 1.3, False), ([arm, ball], 1.3, True),
                                     ([ball], 1.3, True)):
        mean, cov = np.stack([b[0] for b in blobs]), np.stack([b[1] for b in blobs])
        assert _reference(tip, seen, centres, mean, cov, 1.15, 1.2, self_scale=self_scale)[0] == ghost
        got = ghost_voxels(*[torch.tensor(a) for a in (tip, seen, centres, mean, cov)], self_scale=self_scale)
        assert bool(got[0]) == ghost, (len(blobs), self_scale)


def test_ghost_voxels_in_float32_far_from_the_world_origin_with_thin_blobs():
    """Blobs of 1.2-3 cm standard deviation (a forearm's is 1.25 cm) around a subject 50 m from the world origin
    (a calibration's origin may lie anywhere): float32 gives the float64 quadratics' answer but for voxels within
    rounding of a threshold."""
    rng = np.random.default_rng(1)
    K, C, N = 12, 4, 40000
    offset = np.array([40.0, -30.0, 0.0])
    mean = rng.uniform(-0.3, 0.3, (K, 3)) + [0, 0, 1.0] + offset
    R = np.linalg.qr(rng.normal(size=(K, 3, 3)))[0]
    std = rng.uniform(0.012, 0.03, (K, 3)) * [1, 1, 4]  # elongated along one axis, as limbs
    cov = np.einsum("kij,kj,klj->kil", R, std ** 2, R)
    az = np.arange(C) * 2 * np.pi / C
    centres = np.stack([3.5 * np.cos(az), 3.5 * np.sin(az), np.full(C, 2.2)], 1) + offset
    points = rng.uniform([-0.5, -0.5, 0.5], [0.5, 0.5, 1.5], (N, 3)) + offset
    seen = np.ones((N, C), bool)
    ref = _reference_batched(points, seen, centres, mean, cov, 1.15, 1.2)
    assert ref.sum() > 500
    args = [torch.tensor(a).float() for a in (points, centres, mean, cov)]
    got32 = ghost_voxels(args[0], torch.tensor(seen), *args[1:]).numpy()
    assert (got32 != ref).sum() <= 5, (got32 != ref).sum()  # measured 2; 12 without the centring


def test_only_a_blob_in_front_of_the_camera_explains_a_voxel():
    """One camera, a voxel 3.5 m in front of it and a blob on the same line: beyond the voxel, the blob explains
    it (the view sees the blob through it); behind the camera, on the line's other side, it does not."""
    centre = torch.tensor([[3.5, 0.0, 1.0]], dtype=torch.float64)
    voxel = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    cov = (torch.eye(3, dtype=torch.float64) * 0.1 ** 2 / 5)[None]  # a ball of 10 cm radius
    seen = torch.ones(1, 1, dtype=torch.bool)
    for x, ghost in ((-0.8, True), (5.0, False), (2.0, True), (0.05, False)):  # the last: the voxel inside it
        got = ghost_voxels(voxel, seen, centre, torch.tensor([[x, 0.0, 1.0]], dtype=torch.float64), cov)
        assert bool(got[0]) == ghost, x
        assert _reference(voxel.numpy(), seen.numpy(), centre.numpy(), np.array([[x, 0.0, 1.0]]), cov.numpy(),
                          1.15, 1.2)[0] == ghost


def _hull(points, centres, body_points, radius):
    """Voxels every camera sees as foreground: a plain silhouette test, the ray from each camera through the
    voxel passing within ``radius`` of some body point (pixels are rays)."""
    keep = np.ones(len(points), bool)
    for o in centres:
        d = points - o
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        rel = body_points[None] - o  # (1, M, 3)
        along = np.einsum("nj,nmj->nm", d, np.broadcast_to(rel, (len(points), *rel.shape[1:])))
        perp = np.linalg.norm(rel - along[..., None] * d[:, None], axis=-1)
        keep &= ((perp < radius) & (along > 0)).any(1)
    return keep


@pytest.mark.parametrize("self_scale", [0.0, 1.3])
def test_the_ghost_legs_of_four_cameras_are_explained_away_and_the_legs_kept(self_scale):
    """Two vertical legs (cylinders of 7 cm radius, 0.8 m long) on the diagonal of a ring of 4 cameras 90 deg
    apart: the silhouettes carve two more leg-sized ghosts on the other diagonal. With the legs' own ellipsoids as
    the predicted body, the ghosts come out as ghosts and no voxel of a leg does; a voxel of a leg the prediction
    misses (the second leg left out of it) is kept, since two views see it against nothing predicted. The ghosts
    lie beyond the legs' own shells (``self_scale``), so they are found with it too."""
    r, a = 0.07, 0.13
    legs = np.array([[a, a], [-a, -a]])
    z = np.arange(0.1, 0.9, 0.02)
    body = np.concatenate([np.stack([np.full_like(z, x), np.full_like(z, y), z], 1) for x, y in legs])
    centres = np.array([[3.5, 0, 0.5], [0, 3.5, 0.5], [-3.5, 0, 0.5], [0, -3.5, 0.5]])
    g = np.arange(-0.35, 0.35, 0.02)
    grid = np.stack(np.meshgrid(g, g, [0.3, 0.5, 0.7], indexing="ij"), -1).reshape(-1, 3)
    occupied = grid[_hull(grid, centres, body, r)]
    on_leg = np.min([np.hypot(occupied[:, 0] - x, occupied[:, 1] - y) for x, y in legs], 0) < r + 0.01
    assert on_leg.sum() > 20 and (~on_leg).sum() > 20  # the hull holds ghosts as large as the legs
    # the legs as uniform solid ellipsoids: semi-axes r, r, 0.4 (cov = semi^2 / 5)
    mean = np.array([[x, y, 0.5] for x, y in legs])
    cov = np.stack([np.diag([r * r, r * r, 0.16]) / 5] * 2)
    seen = torch.ones(len(occupied), 4, dtype=torch.bool)
    ghost = ghost_voxels(torch.tensor(occupied), seen, torch.tensor(centres, dtype=torch.float64),
                         torch.tensor(mean), torch.tensor(cov), self_scale=self_scale).numpy()
    assert not ghost[on_leg].any()
    assert ghost[~on_leg].mean() > 0.9, ghost[~on_leg].mean()
    # the voxels between the legs grown by 1.15 and by 1.3: ghosts unless the shell keeps them
    rel = occupied[:, None] - mean[None]
    m2 = np.einsum("nki,kij,nkj->nk", rel, np.linalg.inv(cov), rel).min(1)
    shell = (m2 > 5 * 1.15 ** 2) & (m2 <= 5 * 1.3 ** 2)
    assert shell.sum() >= 4
    assert ghost[shell].all() if self_scale == 0 else not ghost[shell].any()
    # predicted: the first leg only. Voxels of the second leg are not explained in the views that see them
    # clear of the first leg, and stay
    one = ghost_voxels(torch.tensor(occupied), seen, torch.tensor(centres, dtype=torch.float64),
                       torch.tensor(mean[:1]), torch.tensor(cov[:1]), self_scale=self_scale).numpy()
    second = np.hypot(occupied[:, 0] - legs[1, 0], occupied[:, 1] - legs[1, 1]) < r
    assert second.any() and not one[second].any()


def test_ghost_voxels_check_their_inputs():
    pts = torch.zeros(3, 3)
    with pytest.raises(ShapeError, match="seen"):
        ghost_voxels(pts, torch.ones(3, 2, dtype=torch.bool), torch.zeros(4, 3), torch.zeros(1, 3),
                     torch.eye(3)[None])
    with pytest.raises(InputError, match="scales"):
        ghost_voxels(pts, torch.ones(3, 4, dtype=torch.bool), torch.zeros(4, 3), torch.zeros(1, 3),
                     torch.eye(3)[None], inside_scale=0.0)
    with pytest.raises(InputError, match="self_scale"):
        ghost_voxels(pts, torch.ones(3, 4, dtype=torch.bool), torch.zeros(4, 3), torch.zeros(1, 3),
                     torch.eye(3)[None], self_scale=-1.0)
    assert not ghost_voxels(pts[:0], torch.ones(0, 4, dtype=torch.bool), torch.zeros(4, 3), torch.zeros(1, 3),
                            torch.eye(3)[None]).any()
