"""The shape fit (torchtrack.blobs.shape) against closed forms and synthetic scenes of known ellipsoids."""

import math
from dataclasses import replace

import pytest
import torch

from torchtrack.blobs.shape import (ShapeFrame, ShapeModel, VoxelDistance, fit_shape, fit_shape_frames,
                                    outside_distance, unit_ball_samples)
from torchtrack.checks import InputError, ShapeError
from torchtrack.occupancy.metrics import inside_ellipsoids


def test_outside_distance_is_exact_for_spheres_and_along_an_ellipsoids_axes():
    gen = torch.Generator().manual_seed(0)
    centres = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    R = torch.eye(3, dtype=torch.float64).expand(2, 3, 3).clone()
    semi = torch.tensor([[0.2, 0.2, 0.2], [0.3, 0.1, 0.05]], dtype=torch.float64)
    p = torch.randn(200, 3, generator=gen, dtype=torch.float64)
    d = outside_distance(p, centres, R, semi)
    # the sphere: |p - c| - r outside, 0 inside
    torch.testing.assert_close(d[:, 0], (p.norm(dim=1) - 0.2).clamp(min=0))
    # the ellipsoid on each of its axes, rotated: |t| - a_i
    Rz = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)  # 90 deg about z
    R[1] = Rz
    for axis in range(3):
        for t in (-0.7, -0.2, 0.02, 0.5):
            q = centres[1] + t * Rz[:, axis]
            got = float(outside_distance(q[None], centres, R, semi)[0, 1])
            assert got == pytest.approx(max(abs(t) - float(semi[1, axis]), 0.0), abs=1e-12), (axis, t)


def test_unit_ball_samples_are_uniform_in_the_ball_and_repeatable():
    u = unit_ball_samples(4000)
    assert u.shape == (4000, 3) and bool((u.norm(dim=1) <= 1).all())
    # uniform in the ball: r^3 is uniform in [0, 1] (mean 1/2, sd 1/sqrt(12) / sqrt(n)); the mean is the origin
    assert float((u.norm(dim=1) ** 3).mean()) == pytest.approx(0.5, abs=4 / math.sqrt(12 * 4000))
    assert float(u.mean(0).norm()) < 0.05
    torch.testing.assert_close(u, unit_ball_samples(4000))
    with pytest.raises(InputError, match="n must be"):
        unit_ball_samples(0)


def test_voxel_distance_matches_a_plain_loop_within_a_cell():
    """The interpolated field against the exact distance to the nearest cube (a plain loop over the cubes), for
    cubes of two sizes, at points near them and far beyond the lattice."""
    gen = torch.Generator().manual_seed(1)
    pts = torch.rand(40, 3, generator=gen, dtype=torch.float64) * 0.6
    sizes = torch.where(torch.arange(40) % 2 == 0, 0.03, 0.06).to(torch.float64)
    cell = 0.015
    field = VoxelDistance.of(pts, sizes, cell, margin=0.2)
    q = torch.cat([torch.rand(300, 3, generator=gen, dtype=torch.float64) * 0.8 - 0.1,  # within the lattice
                   torch.tensor([[3.0, 0.3, 0.3], [0.3, -2.0, 0.3]], dtype=torch.float64)])
    exact = torch.empty(q.shape[0], dtype=torch.float64)
    for i, p in enumerate(q):
        exact[i] = min(float(((p - c).abs() - s / 2).clamp(min=0).norm()) for c, s in zip(pts, sizes))
    got = field(q)
    # covered a cell beyond the cubes: under the exact distance by at most that, over it by at most the
    # interpolation's error at a cube's corner
    assert float((exact - got)[:-2].max()) <= cell + 1e-9
    assert float((got - exact)[:-2].max()) <= 0.5 * cell
    assert float((exact - got)[:-2].abs().mean()) < 0.5 * cell
    # beyond the lattice: the distance to it plus the field at its side (an upper bound)
    assert bool((got[-2:] >= exact[-2:] - cell).all()) and bool((got[-2:] <= exact[-2:] + 0.05).all())


def _limb(length: float, cut_top: float | None = None, voxel: float = 0.015):
    """A two-ellipsoid limb along z (an upper part on [0, L1] and a lower part hanging below it), its voxels
    (a ``voxel`` grid inside the union, the part above ``cut_top`` left out) and the affine model of parameters
    (x0: the upper part's length change, relative; x1: a shift of both along z)."""
    L1 = 0.4
    dt = torch.float64
    R = torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype=dt).expand(2, 3, 3).clone()  # along z
    semi = torch.tensor([[0.5 * L1, 0.06, 0.06], [0.2, 0.05, 0.05]], dtype=dt)

    def centres(L):  # the upper part centred on its bone, the lower one hanging from its end
        return torch.tensor([[0.0, 0.0, 0.5 * L], [0.0, 0.0, L + 0.2]], dtype=dt)

    true_semi = semi.clone()
    true_semi[0, 0] = 0.5 * length
    g = torch.arange(-0.3, 1.2, voxel, dtype=dt)
    grid = torch.stack(torch.meshgrid(g - 0.6, g - 0.6, g, indexing="ij"), -1).reshape(-1, 3)
    grid = grid[(grid[:, 0].abs() < 0.1) & (grid[:, 1].abs() < 0.1)]
    pts = grid[inside_ellipsoids(grid, centres(length), R, true_semi)]
    if cut_top is not None:
        pts = pts[pts[:, 2] <= cut_top]
    d_centres = torch.zeros(2, 3, 2, dtype=dt)
    d_centres[0, 2, 0], d_centres[1, 2, 0] = 0.5 * L1, L1  # x0 = relative change of L1
    d_centres[:, 2, 1] = 1.0
    d_along = torch.tensor([[0.5 * L1, 0.0], [0.0, 0.0]], dtype=dt)
    model = ShapeModel(centres(L1), R, semi, d_centres, d_along)
    return model, pts, torch.full((pts.shape[0],), voxel, dtype=dt)


def test_fit_shape_recovers_a_limbs_length_from_its_voxels():
    """Voxels of a limb whose upper part is 25 % longer than the model's: the fit finds that length (and no
    shift) within a voxel (1.5 cm); a 15 % shorter one too."""
    for true in (0.5, 0.34):
        model, pts, sizes = _limb(true)
        x, energy = fit_shape(model, pts, sizes, torch.ones(pts.shape[0], dtype=pts.dtype),
                              torch.zeros(2, dtype=pts.dtype), torch.zeros(2, dtype=pts.dtype))
        assert float(x[0]) == pytest.approx(true / 0.4 - 1, abs=0.04), (true, x)  # 1.6 cm of 0.4 m
        assert abs(float(x[1])) < 0.01, (true, x)
        assert energy < 1e-5


def test_fit_shape_counts_nothing_out_of_the_observed_volume():
    """The limb's top above the observed volume gives no voxels: told the volume, the fit keeps the true length;
    not told, it takes the missing top for a shorter, lower limb."""
    model, pts, sizes = _limb(0.4, cut_top=0.25)
    w, zero = torch.ones(pts.shape[0], dtype=pts.dtype), torch.zeros(2, dtype=pts.dtype)
    # the limb's upper part starts at z = 0 and reaches 0.4: its top 0.15 m is out of a box capped at 0.25
    x, _ = fit_shape(model, pts, sizes, w, zero, zero, volume_m=((-1.0, -1.0, -1.0), (1.0, 1.0, 0.25)))
    assert abs(float(x[0])) < 0.03 and abs(float(x[1])) < 0.01, x
    x_blind, _ = fit_shape(model, pts, sizes, w, zero, zero)
    assert float(x_blind[0]) < -0.1 or float(x_blind[1]) < -0.05, x_blind


def test_fit_shape_ridge_and_starts():
    """A ridge far stronger than the voxels' pull holds the parameters at its target (a closed form: the minimum
    of ``ridge * (x - target)^2`` alone). Of several starts the least objective wins: a ball of radius 0.1 m that
    may only move up and down, over the voxels of a ball as large at z = 0 and one of radius 0.07 at z = 1 m, stays
    at the small one from a start there (a local minimum), and with a start at 0 beside it the fit takes the large
    one."""
    model, pts, sizes = _limb(0.5)
    w = torch.ones(pts.shape[0], dtype=pts.dtype)
    target = torch.tensor([-0.1, 0.02], dtype=pts.dtype)
    x_held, _ = fit_shape(model, pts, sizes, w, torch.full((2,), 10.0, dtype=pts.dtype), target)
    torch.testing.assert_close(x_held, target, atol=1e-3, rtol=0)

    dt = torch.float64
    g = (torch.arange(-10, 10, dtype=dt) + 0.5) * 0.01
    grid = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    big, small = grid[grid.norm(dim=1) <= 0.1], grid[grid.norm(dim=1) <= 0.07]
    pts = torch.cat([big, small + torch.tensor([0.0, 0.0, 1.0], dtype=dt)])
    sizes, w = torch.full((pts.shape[0],), 0.01, dtype=dt), torch.ones(pts.shape[0], dtype=dt)
    ball = ShapeModel(torch.zeros(1, 3, dtype=dt), torch.eye(3, dtype=dt)[None], torch.full((1, 3), 0.1, dtype=dt),
                      torch.tensor([[[0.0], [0.0], [1.0]]], dtype=dt), torch.zeros(1, 1, dtype=dt))
    zero = torch.zeros(1, dtype=dt)
    x_one, e_one = fit_shape(ball, pts, sizes, w, zero, zero, starts=[torch.tensor([0.9], dtype=dt)])
    assert float(x_one[0]) == pytest.approx(1.0, abs=0.03), x_one
    for starts in ([torch.tensor([0.9], dtype=dt), zero + 0.1], [zero + 0.1, torch.tensor([0.9], dtype=dt)]):
        x_two, e_two = fit_shape(ball, pts, sizes, w, zero, zero, starts=starts)
        # at the large ball, 2.6 cm up: the Cauchy penalty's tail lets the small ball's voxels pull it a little
        assert abs(float(x_two[0])) < 0.05 and e_two < e_one, (x_two, e_two, e_one)


def _chain_frame(bend: float, shift: tuple[float, float, float], voxel: float = 0.015) -> ShapeFrame:
    """A two-segment chain, the upper segment up z from the origin and the lower one on from its end bent by
    ``bend`` (rad, towards x), true lengths 0.44 and 0.27 m (as round in cross-section, 5 cm): its voxels (a
    ``voxel`` grid inside the union, shifted by ``shift``) and the model of lengths 0.4 and 0.3 with parameters
    (the segments' relative length changes, a shift in x, y, z)."""
    dt = torch.float64
    up = torch.tensor([0.0, 0.0, 1.0], dtype=dt)
    d = torch.tensor([math.sin(bend), 0.0, math.cos(bend)], dtype=dt)
    side = torch.tensor([0.0, 1.0, 0.0], dtype=dt)
    R = torch.stack([torch.stack([u, side, torch.linalg.cross(u, side)], 1) for u in (up, d)])  # (2, 3, 3)

    def centres(l1, l2):
        return torch.stack([0.5 * l1 * up, l1 * up + 0.5 * l2 * d])

    def semi(l1, l2):
        return torch.tensor([[0.5 * l1, 0.05, 0.05], [0.5 * l2, 0.05, 0.05]], dtype=dt)

    g = torch.arange(-0.45, 0.9, voxel, dtype=dt)
    grid = torch.stack(torch.meshgrid(g, torch.arange(-0.0825, 0.09, voxel, dtype=dt), g, indexing="ij"), -1)
    grid = grid.reshape(-1, 3)
    pts = grid[inside_ellipsoids(grid, centres(0.44, 0.27) + torch.tensor(shift, dtype=dt), R, semi(0.44, 0.27))]
    d_centres = torch.zeros(2, 3, 5, dtype=dt)
    d_centres[0, :, 0], d_centres[1, :, 0], d_centres[1, :, 1] = 0.2 * up, 0.4 * up, 0.15 * d
    d_centres[:, :, 2:] = torch.eye(3, dtype=dt)
    d_along = torch.zeros(2, 5, dtype=dt)
    d_along[0, 0], d_along[1, 1] = 0.2, 0.15
    model = ShapeModel(centres(0.4, 0.3), R, semi(0.4, 0.3), d_centres, d_along)
    return ShapeFrame(model, pts, torch.full((pts.shape[0],), voxel, dtype=pts.dtype),
                      torch.ones(pts.shape[0], dtype=pts.dtype))


def test_fit_shape_frames_shares_the_lengths_and_gives_each_frame_its_shift():
    """Two frames of a two-segment chain (10 % longer and 10 % shorter than the model), straight and bent 90 deg,
    their voxels shifted differently: fitted together, both lengths within 2 % (8 and 6 mm) and each frame's
    shift within a voxel. In the straight frame alone the joint only shows in the union's waist: the lower
    segment comes out 3.6 % short (1.1 cm)."""
    shifts = [(0.0, 0.0, 0.0), (0.03, 0.0, -0.02)]
    frames = [_chain_frame(0.0, shifts[0]), _chain_frame(math.pi / 2, shifts[1])]
    zero = torch.zeros(2, dtype=torch.float64)
    shared, own, energy = fit_shape_frames(frames, zero, zero, local=3)
    true = torch.tensor([0.1, -0.1], dtype=torch.float64)
    assert float((shared - true).abs().max()) < 0.02, shared
    assert own.shape == (2, 3) and float((own - torch.tensor(shifts, dtype=own.dtype)).abs().max()) < 0.015, own
    assert energy < 1e-5
    straight, _, _ = fit_shape_frames(frames[:1], zero, zero, local=3)
    assert float((straight - true).abs().max()) > 1.5 * float((shared - true).abs().max()), (straight, shared)
    f = frames[0]
    with pytest.raises(InputError, match="no frames"):
        fit_shape_frames([], zero, zero, local=3)
    with pytest.raises(InputError, match="local must be in"):
        fit_shape_frames(frames, zero, zero, local=6)
    with pytest.raises(ShapeError, match="ridge"):
        fit_shape_frames(frames, zero, zero, local=2)
    other = ShapeFrame(_limb(0.4)[0], f.points, f.sizes, f.weights)
    with pytest.raises(InputError, match="frame 1's model has 2 parameters"):
        fit_shape_frames([f, other], zero, zero, local=3)
    with pytest.raises(InputError, match=r"positive sum.*\(frame 1\)"):
        fit_shape_frames([f, replace(f, weights=torch.zeros_like(f.weights))], zero, zero, local=3)


def test_fit_shape_rejects_bad_input():
    model, pts, sizes = _limb(0.4)
    zero = torch.zeros(2, dtype=pts.dtype)
    with pytest.raises(InputError, match="positive sum"):
        fit_shape(model, pts, sizes, torch.zeros(pts.shape[0], dtype=pts.dtype), zero, zero)
    with pytest.raises(InputError, match="positive sum"):
        fit_shape(model, pts, sizes, torch.full((pts.shape[0],), math.nan, dtype=pts.dtype), zero, zero)
    with pytest.raises(ShapeError, match="sizes"):
        fit_shape(model, pts, sizes[:-1], torch.ones(pts.shape[0], dtype=pts.dtype), zero, zero)
    with pytest.raises(ShapeError, match="ridge"):
        fit_shape(model, pts, sizes, torch.ones(pts.shape[0], dtype=pts.dtype), torch.zeros(3), zero)
    with pytest.raises(ShapeError, match="d_along"):
        ShapeModel(model.centres, model.R_world, model.semi_axes, model.d_centres, model.d_along[:, :1])
