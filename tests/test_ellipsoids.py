"""Tests of the ray - ellipsoid geometry (torchtrack.ellipsoids) against independent references: closed-form hit
distances, point-in-ellipsoid marching, all (ray, ellipsoid) pairs solved without culling."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from torchtrack.checks import InputError, ShapeError
from torchtrack.ellipsoids import (
    nearest_hits, ray_box_intersect, ray_ellipsoid_intersect, ray_ellipsoid_pair_hits, rays_meet_ellipsoids,
    unit_sphere_hits,
)

from conftest import quadric_matrix, random_rotations, small_body


def march_reference(o, d, centers, Rs, semis, t_max=12.0, steps=24000):
    """Nearest inside sample along each ray, by testing (p - c)^T A (p - c) <= 1 at dense samples (numpy)."""
    ts = np.linspace(0, t_max, steps + 1)[1:]
    As = [quadric_matrix(c, R, a) for c, R, a in zip(centers, Rs, semis)]
    t_ref = np.full(len(o), np.inf)
    part_ref = np.full(len(o), -1)
    first = np.full((len(o), len(As)), np.inf)
    for i in range(len(o)):
        p = o[i] + ts[:, None] * d[i]  # (S, 3)
        for k, (c, A) in enumerate(zip(centers, As)):
            q = p - c
            inside = np.einsum("si,ij,sj->s", q, A, q) <= 1
            if inside.any():
                first[i, k] = ts[np.argmax(inside)]
        if np.isfinite(first[i]).any():
            part_ref[i] = int(np.argmin(first[i]))
            t_ref[i] = first[i, part_ref[i]]
    return t_ref, part_ref, first, ts[1] - ts[0]


def test_sphere_closed_form(device):
    """Rays parallel to z towards a sphere of radius 2 at the origin, from z = -5: t = 5 - sqrt(4 - h^2)."""
    h = torch.tensor([0.0, 0.5, 1.0, 1.9, 2.1, 3.0], dtype=torch.float64, device=device)
    origins = torch.stack([h, torch.zeros_like(h), torch.full_like(h, -5.0)], -1)  # (N, 3)
    dirs = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=device).expand_as(origins)
    centers = torch.zeros(1, 3, dtype=torch.float64, device=device)
    R = torch.eye(3, dtype=torch.float64, device=device)[None]
    semi = torch.full((1, 3), 2.0, dtype=torch.float64, device=device)
    t, part, normal = ray_ellipsoid_intersect(origins, dirs, centers, R, semi)
    hits = h < 2
    expected = 5 - torch.sqrt((4 - h[hits] ** 2))
    torch.testing.assert_close(t[hits], expected)
    assert torch.isinf(t[~hits]).all() and (part[~hits] == -1).all() and (part[hits] == 0).all()
    torch.testing.assert_close(normal[hits], (origins[hits] + t[hits, None] * dirs[hits]) / 2)
    assert (normal[~hits] == 0).all()


def test_rotated_ellipsoid_closed_form(device):
    """A ray along each ellipsoid axis from outside hits at distance - semi-axis; from inside, exits at +semi."""
    gen = torch.Generator().manual_seed(0)
    R = random_rotations(1, gen).to(device)
    semi = torch.tensor([[3.0, 1.0, 2.0]], dtype=torch.float64, device=device)
    center = torch.tensor([[1.0, -2.0, 0.5]], dtype=torch.float64, device=device)
    axes = R[0].T  # (3, 3) rows = axes in world
    origins = center + 10 * axes  # 10 m out along each axis
    t, part, normal = ray_ellipsoid_intersect(origins, -axes, center, R, semi)
    torch.testing.assert_close(t, 10 - semi[0])
    torch.testing.assert_close(normal, axes)  # outward normal at the axis tip
    # Inside: the far root, with the outward normal (pointing along the ray).
    t_in, part_in, normal_in = ray_ellipsoid_intersect(center.expand(3, 3), axes, center, R, semi)
    torch.testing.assert_close(t_in, semi[0])
    torch.testing.assert_close(normal_in, axes)
    assert (part_in == 0).all()
    # Pointing away from an ellipsoid behind the origin: no hit.
    t_away, part_away, _ = ray_ellipsoid_intersect(origins, axes, center, R, semi)
    assert torch.isinf(t_away).all() and (part_away == -1).all()


def test_unit_sphere_far_origin_is_accurate():
    """The |d|^2 - |o x d|^2 discriminant keeps float32 hits exact for origins far from small ellipsoids."""
    o = torch.tensor([[0.0, 0.0, -1.0e3]], dtype=torch.float32)
    d = torch.tensor([[0.999e-3, 0.0, 1.0]], dtype=torch.float32)  # passes 0.999 units off the centre
    t = unit_sphere_hits(o, d)
    t_ref = unit_sphere_hits(o.double(), d.double())
    assert torch.isfinite(t).all()
    torch.testing.assert_close(t.double(), t_ref, rtol=1e-5, atol=0)


def test_random_ellipsoids_against_marching(device):
    gen = torch.Generator().manual_seed(1)
    K, N = 5, 120
    centers = torch.rand(K, 3, generator=gen, dtype=torch.float64) * 4 - 2
    R = random_rotations(K, gen)
    semi = torch.rand(K, 3, generator=gen, dtype=torch.float64) * 0.8 + 0.2
    origins = torch.randn(N, 3, generator=gen, dtype=torch.float64) * 0.3 + torch.tensor([0.0, 0.0, -5.0])
    targets = centers[torch.randint(K, (N,), generator=gen)] + torch.randn(N, 3, generator=gen,
                                                                             dtype=torch.float64) * 0.6
    dirs = torch.nn.functional.normalize(targets - origins, dim=-1)
    t, part, _ = ray_ellipsoid_intersect(*(x.to(device) for x in (origins, dirs, centers, R, semi)), chunk_size=50)
    t, part = t.cpu().numpy(), part.cpu().numpy()
    t_ref, part_ref, first, step = march_reference(*(x.numpy() for x in (origins, dirs, centers, R, semi)))
    both = np.isfinite(t_ref)
    assert both.sum() > N // 3 and (~both).sum() > 5  # the rays exercise hits and misses
    assert np.isfinite(t[both]).all()
    np.testing.assert_array_less(t[both] - step - 1e-9, t_ref[both])
    np.testing.assert_array_less(t_ref[both], t[both] + 1e-9 + step)
    # Same part, unless two parts are entered within a step of each other.
    second = np.sort(first[both], axis=1)[:, 1]
    clear = second - t_ref[both] > 2 * step
    assert (part[both][clear] == part_ref[both][clear]).all()
    # Misses of the marching: either analytic misses or a chord shorter than a step (check it finely).
    for i in np.nonzero(~both & np.isfinite(t))[0]:
        p = origins[i].numpy() + np.linspace(t[i], t[i] + step, 2001)[:, None] * dirs[i].numpy()
        q = p - centers[part[i]].numpy()
        A = quadric_matrix(centers[part[i]].numpy(), R[part[i]].numpy(), semi[part[i]].numpy())
        assert (np.einsum("si,ij,sj->s", q, A, q) <= 1 + 1e-9).any()


def test_dense_equals_culled_and_batched(device):
    """Bounding-sphere culling, chunking and leading dims change nothing: compare with all (ray, part) pairs."""
    gen = torch.Generator().manual_seed(2)
    K, N = 7, 400
    centers = (torch.rand(K, 3, generator=gen) * 4 - 2).to(device)
    R = random_rotations(K, gen).float().to(device)
    semi = (torch.rand(K, 3, generator=gen) * 0.5 + 0.1).to(device)
    origins = (torch.randn(2, N, 3, generator=gen) * 3).to(device)
    dirs = torch.randn(2, N, 3, generator=gen).to(device)
    t, part, normal = ray_ellipsoid_intersect(origins, dirs, centers, R, semi, chunk_size=97)
    assert t.shape == (2, N) and part.shape == (2, N) and normal.shape == (2, N, 3) and part.dtype == torch.int64
    ray = torch.arange(2 * N, device=device).repeat_interleave(K)
    k = torch.arange(K, device=device).repeat(2 * N)
    t_pair = ray_ellipsoid_pair_hits(origins.reshape(-1, 3)[ray], dirs.reshape(-1, 3)[ray], k, centers, R, semi)
    t_dense, part_dense = nearest_hits(t_pair, ray, k, 2 * N)
    torch.testing.assert_close(t.reshape(-1), t_dense)
    assert torch.equal(part.reshape(-1), part_dense)
    t1, part1, normal1 = ray_ellipsoid_intersect(origins[1], dirs[1], centers, R, semi)
    torch.testing.assert_close(t1, t[1])
    torch.testing.assert_close(normal1, normal[1])
    assert (part != -1).sum() > 20


def test_normals_are_quadric_gradients():
    gen = torch.Generator().manual_seed(4)
    centers, R, semi, _ = small_body()
    o = torch.tensor([[3.0, 0.3, 1.2]], dtype=torch.float64).expand(50, 3)
    d = torch.nn.functional.normalize(centers[torch.randint(6, (50,), generator=gen)] - o
                                      + 0.05 * torch.randn(50, 3, generator=gen, dtype=torch.float64), dim=-1)
    t, part, normal = ray_ellipsoid_intersect(o, d, centers, R, semi)
    hit = part >= 0
    p = (o + t[:, None] * d)[hit]
    for pi, ki, ni in zip(p.numpy(), part[hit].numpy(), normal[hit].numpy()):
        A = quadric_matrix(centers[ki].numpy(), R[ki].numpy(), semi[ki].numpy())
        g = 2 * A @ (pi - centers[ki].numpy())  # gradient of (p - c)^T A (p - c)
        np.testing.assert_allclose(ni, g / np.linalg.norm(g), atol=1e-9)
        np.testing.assert_allclose((pi - centers[ki].numpy()) @ A @ (pi - centers[ki].numpy()), 1.0, atol=1e-9)


def test_intersect_bad_input():
    c, R, a = torch.zeros(2, 3), torch.eye(3).expand(2, 3, 3), torch.ones(2, 3)
    with pytest.raises(ShapeError, match="R_world_ellipsoid"):
        ray_ellipsoid_intersect(torch.zeros(4, 3), torch.ones(4, 3), c, R[:1], a)
    with pytest.raises(ShapeError, match="dirs"):
        ray_ellipsoid_intersect(torch.zeros(4, 3), torch.ones(4, 2), c, R, a)
    with pytest.raises(InputError, match="semi_axes"):
        ray_ellipsoid_intersect(torch.zeros(4, 3), torch.ones(4, 3), c, R, torch.tensor([[1.0, 1, 1], [1, 0, 1]]))


def test_box_closed_form(device):
    """A box rotated 90 degrees about z (so its x half-size 0.5 lies along world y), hit along each axis."""
    R = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], device=device)  # columns: box axes in world
    half = torch.tensor([0.5, 0.2, 1.0], device=device)
    center = torch.tensor([1.0, 2.0, 3.0], device=device)
    origins = center + torch.tensor([[5.0, 0, 0], [0, -5, 0], [0, 0, 5], [5, 5, 0], [0, 0, 0]], device=device)
    dirs = torch.tensor([[-1.0, 0, 0], [0, 1, 0], [0, 0, -2], [-1, 0, 0], [1, 0, 0]], device=device)
    t, normal = ray_box_intersect(origins, dirs, center, R, half)
    torch.testing.assert_close(t[:3], torch.tensor([5 - 0.2, 5 - 0.5, (5 - 1.0) / 2], device=device))
    torch.testing.assert_close(normal[:3], -dirs[:3] / dirs[:3].norm(dim=-1, keepdim=True))
    assert torch.isinf(t[3:]).all()  # passes beside it; starts inside


def test_rays_meet_ellipsoids_where_the_caster_hits(device):
    """Whether a camera's rays meet any ellipsoid (from the silhouette conics) is where the exact caster finds a
    hit ahead of the camera, frame by frame; a camera inside an ellipsoid sees it everywhere."""
    gen = torch.Generator().manual_seed(7)
    body, R, semi, _ = small_body()
    T, P = 3, 3000
    centres = body[None] + torch.randn(T, 1, 3, generator=gen, dtype=torch.float64) * 0.2  # (T, K, 3)
    origins = torch.tensor([[3.0, 0.5, 1.4], [-2.5, -2.0, 2.5], [0.3, 0.4, -1.0]], dtype=torch.float64)  # (C, 3)
    centres[2, 0] = origins[2]  # frame 2: camera 2 inside the first ellipsoid
    noise = torch.randn(3, P, 3, generator=gen, dtype=torch.float64) * 0.25
    aim = body[torch.randint(6, (3, P), generator=gen)] + noise
    dirs = F.normalize(aim - origins[:, None], dim=-1)  # (C, P, 3): toward the body's parts, some missing
    dirs[2, : P // 4] *= -1  # and some away from it
    RT = R.expand(T, -1, -1, -1)
    got = rays_meet_ellipsoids(*(x.to(device) for x in (origins, dirs, centres, RT, semi))).cpu()  # (T, C, P)
    assert got.shape == (T, 3, P)
    for t in range(T):
        for c in range(3):
            hit, _, _ = ray_ellipsoid_intersect(origins[c].expand(P, 3), dirs[c], centres[t], R, semi)
            assert torch.equal(got[t, c], torch.isfinite(hit)), (t, c)
    assert got[2, 2].all() and 0.1 < got[:2].double().mean() < 0.9  # hits and misses
    # bundles of 16 rays, tested a pair at a time; a ray that is not finite misses alone, its bundle still tested
    dirs[0, 3] = float("nan")
    small = rays_meet_ellipsoids(*(x.to(device) for x in (origins, dirs, centres, RT, semi)), bundle=16,
                                 max_tests=16).cpu()
    assert not small[:, 0, 3].any()
    small[:, 0, 3] = got[:, 0, 3]
    assert torch.equal(small, got)
