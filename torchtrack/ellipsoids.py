"""Rays against ellipsoids: exact hits, nearest hits, normals, and whether rays meet any of a body's ellipsoids.
Pure functions, batched, CPU or GPU; shared by the synthetic renderer (:mod:`torchtrack.synth.scene`) and the
background refinement's body masks (:mod:`torchtrack.tracking.refine`).

Conventions (see :mod:`torchtrack.conventions`): world Z up, metres. An ellipsoid ``k`` is given by its centre
``centers[k]`` (3,), a rotation ``R_world_ellipsoid[k]`` (3, 3) whose *columns* are its axes in world
coordinates, and its semi-axis lengths ``semi_axes[k]`` (3,) along those axes. A point ``p`` is inside iff
``|B_k (p - c_k)| <= 1`` with ``B_k = diag(1 / semi_axes[k]) @ R_world_ellipsoid[k].T`` (world -> unit-sphere
frame). A ray is ``origin + t * dir``; ``t`` is a distance in metres when ``dir`` is a unit vector.

Why hand-written: kornia and PyTorch3D rasterize meshes; an analytic ray/quadric intersection is exact at the
pixel centre (so silhouettes can be checked against the projected conic) and needs no tessellation.

The work is split in three steps so that callers can choose how to find candidate (ray, ellipsoid) pairs:
:func:`ray_ellipsoid_pair_hits` solves the quadratic for given pairs, :func:`nearest_hits` reduces the pairs to
the nearest hit per ray, :func:`ellipsoid_normals` gives outward normals. :func:`ray_ellipsoid_intersect` chains
them for dense rays with a bounding-sphere cull in bounded chunks; the scene renderer instead culls per image
tile (see :mod:`torchtrack.synth.scene`). :func:`rays_meet_ellipsoids` answers only whether a camera's rays meet
any ellipsoid, from the ellipsoids' silhouette conics, without solving per (ray, ellipsoid) pair.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from torchtrack.checks import InputError, check_shape

__all__ = [
    "check_ellipsoids",
    "ellipsoid_world_to_unit",
    "ray_ellipsoid_pair_hits",
    "unit_sphere_hits",
    "nearest_hits",
    "ellipsoid_normals",
    "bounding_sphere_pairs",
    "ray_ellipsoid_intersect",
    "ray_box_intersect",
    "rays_meet_ellipsoids",
]


def check_ellipsoids(centers: torch.Tensor, R_world_ellipsoid: torch.Tensor, semi_axes: torch.Tensor) -> None:
    """Validate ellipsoid parameters: centers (K, 3), R_world_ellipsoid (K, 3, 3), semi_axes (K, 3) > 0.

    Raises:
        ShapeError: wrong shapes. InputError: non-positive or non-finite semi-axes.
    """
    check_shape(centers, ("K", 3), "centers")
    K = centers.shape[0]
    check_shape(R_world_ellipsoid, (K, 3, 3), "R_world_ellipsoid")
    check_shape(semi_axes, (K, 3), "semi_axes")
    if not bool(torch.isfinite(semi_axes).all()) or bool((semi_axes <= 0).any()):
        raise InputError("semi_axes: every semi-axis must be finite and > 0")


def ellipsoid_world_to_unit(R_world_ellipsoid: torch.Tensor, semi_axes: torch.Tensor) -> torch.Tensor:
    """Linear map from world offsets ``p - c`` to the ellipsoid's unit-sphere frame.

    Args:
        R_world_ellipsoid: (K, 3, 3), columns = ellipsoid axes in world.
        semi_axes: (K, 3).

    Returns:
        B: (K, 3, 3) = ``diag(1 / semi_axes) @ R_world_ellipsoid^T``.
    """
    return R_world_ellipsoid.transpose(-1, -2) / semi_axes[..., :, None]


def ray_ellipsoid_pair_hits(
    origins: torch.Tensor,
    dirs: torch.Tensor,
    part_index: torch.Tensor,
    centers: torch.Tensor,
    R_world_ellipsoid: torch.Tensor,
    semi_axes: torch.Tensor,
) -> torch.Tensor:
    """Nearest positive hit parameter of each (ray, ellipsoid) pair.

    Rays whose origin lies inside the ellipsoid hit it where they leave it (the far root). Origins on the
    surface count as inside when the ray enters, so a ray never hits at ``t <= 0``.

    Args:
        origins: (P, 3) ray origin of each pair.
        dirs: (P, 3) ray direction of each pair (need not be unit; ``t`` is in units of ``|dir|``).
        part_index: (P,) int64 ellipsoid of each pair, in [0, K).
        centers, R_world_ellipsoid, semi_axes: (K, 3), (K, 3, 3), (K, 3).

    Returns:
        t: (P,) hit parameter, ``+inf`` where the ray misses.
    """
    B = ellipsoid_world_to_unit(R_world_ellipsoid, semi_axes)[part_index]  # (P, 3, 3)
    o = (B @ (origins - centers[part_index])[..., None])[..., 0]  # (P, 3) origin, unit-sphere frame
    d = (B @ dirs[..., None])[..., 0]  # (P, 3) direction, unit-sphere frame
    return unit_sphere_hits(o, d)


def unit_sphere_hits(origins_unit: torch.Tensor, dirs_unit: torch.Tensor) -> torch.Tensor:
    """Nearest positive hit of rays with the unit sphere (rays already in an ellipsoid's unit-sphere frame).

    Solves ``|o + t d|^2 = 1`` and returns the near root if positive, else the far root if positive (origin
    inside), else ``+inf``.

    Args:
        origins_unit: (..., 3), dirs_unit: (..., 3), broadcastable.

    Returns:
        t: (...) hit parameter, ``+inf`` on a miss.
    """
    o, d = torch.broadcast_tensors(origins_unit, dirs_unit)
    a = (d * d).sum(-1)  # (...)
    b = (o * d).sum(-1)  # (...) half the linear coefficient
    c = (o * o).sum(-1) - 1.0  # (...)
    # b^2 - a c rewritten as |d|^2 - |o x d|^2: no cancellation when the origin is far away.
    disc = a - torch.linalg.cross(o, d).square().sum(-1)  # (...)
    q = -(b + torch.copysign(disc.clamp_min(0).sqrt(), b))  # (...) stable root pair: t1 = q / a, t2 = c / q
    t1, t2 = q / a, c / q
    t_near, t_far = torch.minimum(t1, t2), torch.maximum(t1, t2)
    t = torch.where(t_near > 0, t_near, t_far)
    hit = (disc >= 0) & (t > 0) & torch.isfinite(t)
    return torch.where(hit, t, torch.full_like(t, float("inf")))


def nearest_hits(
    t_pair: torch.Tensor, ray_index: torch.Tensor, part_index: torch.Tensor, num_rays: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Reduce per-pair hits to the nearest hit per ray.

    Ties (equal ``t``) go to the lower part index.

    Args:
        t_pair: (P,) hit parameter per pair, ``+inf`` for misses.
        ray_index: (P,) int64 ray of each pair, in [0, num_rays).
        part_index: (P,) int64 ellipsoid of each pair.
        num_rays: R.

    Returns:
        t_hit: (R,) nearest hit, ``+inf`` where none. part_id: (R,) int64, -1 where none.
    """
    t_hit = torch.full((num_rays,), float("inf"), dtype=t_pair.dtype, device=t_pair.device)
    t_hit = t_hit.scatter_reduce(0, ray_index, t_pair, reduce="amin")
    wins = torch.isfinite(t_pair) & (t_pair == t_hit[ray_index])  # (P,)
    big = torch.iinfo(torch.int64).max
    part_id = torch.full((num_rays,), big, dtype=torch.int64, device=t_pair.device)
    part_id = part_id.scatter_reduce(0, ray_index[wins], part_index[wins], reduce="amin")
    part_id = torch.where(part_id == big, torch.full_like(part_id, -1), part_id)
    return t_hit, part_id


def ellipsoid_normals(
    points: torch.Tensor,
    part_id: torch.Tensor,
    centers: torch.Tensor,
    R_world_ellipsoid: torch.Tensor,
    semi_axes: torch.Tensor,
) -> torch.Tensor:
    """Outward unit normals of ellipsoids at surface points (the normalized gradient of ``|B (p - c)|^2``).

    Args:
        points: (..., 3) world points on the surfaces.
        part_id: (...) int64 ellipsoid of each point; entries < 0 give a zero normal.
        centers, R_world_ellipsoid, semi_axes: (K, 3), (K, 3, 3), (K, 3).

    Returns:
        normal: (..., 3) world unit normals, zeros where ``part_id < 0``.
    """
    valid = part_id >= 0
    k = part_id.clamp_min(0)
    B = ellipsoid_world_to_unit(R_world_ellipsoid, semi_axes)  # (K, 3, 3)
    p_unit = (B[k] @ (points - centers[k])[..., None])  # (..., 3, 1) point in the unit-sphere frame
    grad = (B[k].transpose(-1, -2) @ p_unit)[..., 0]  # (..., 3) = R diag(1/a) p_unit
    grad = torch.where(valid[..., None] & torch.isfinite(grad), grad, torch.zeros_like(grad))
    return F.normalize(grad, dim=-1)


def bounding_sphere_pairs(
    origins: torch.Tensor, dirs: torch.Tensor, centers: torch.Tensor, radii: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Candidate (ray, sphere) pairs: rays that pass within a sphere's radius ahead of their origin.

    Two levels: rays that miss the sphere enclosing all K spheres are dropped with one test each; the others
    are tested against every sphere.

    Args:
        origins, dirs: (N, 3).
        centers: (K, 3). radii: (K,).

    Returns:
        ray_index: (P,) int64, part_index: (P,) int64, sorted by ray then part.
    """
    middle = centers.mean(0, keepdim=True)  # (1, 3)
    outer = ((centers - middle).norm(dim=-1) + radii).amax(0, keepdim=True)  # (1,) enclosing sphere
    near = _sphere_test(origins, dirs, middle, outer)[:, 0].nonzero()[:, 0]  # (N',)
    keep = _sphere_test(origins[near], dirs[near], centers, radii)  # (N', K)
    ray_index, part_index = keep.nonzero(as_tuple=True)
    return near[ray_index], part_index


def _sphere_test(origins: torch.Tensor, dirs: torch.Tensor, centers: torch.Tensor, radii: torch.Tensor):
    """(N, K) bool: ray n passes within radii[k] of centers[k], ahead of (or around) its origin."""
    d = F.normalize(dirs, dim=-1)  # (N, 3)
    along = d @ centers.T - (d * origins).sum(-1, keepdim=True)  # (N, K) distance to the closest approach
    v2 = (origins.square().sum(-1, keepdim=True) - 2 * origins @ centers.T
          + centers.square().sum(-1)[None])  # (N, K) squared distance origin -> centre
    r = radii[None] * (1 + 1e-4)  # (1, K) a little margin for the rounding of the expanded forms
    return (v2 - along.square() <= r * r + 1e-6 * v2) & (along > -r)


def ray_ellipsoid_intersect(
    origins: torch.Tensor,
    dirs: torch.Tensor,
    centers: torch.Tensor,
    R_world_ellipsoid: torch.Tensor,
    semi_axes: torch.Tensor,
    chunk_size: int = 1 << 16,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nearest hit of each ray with a set of K ellipsoids.

    Rays are processed in chunks of ``chunk_size``; within a chunk, bounding spheres select the candidate
    pairs (:func:`bounding_sphere_pairs`: one test per ray against the sphere around all ellipsoids, then K
    tests for the rays that pass it) and the quadratic is solved only for those, so memory is bounded by
    ``chunk_size * K`` and the cost follows the rays that come near the ellipsoids (on a 640x480 view of a
    19-part body many times less than solving every pair; ``scripts/bench_render.py``).

    A ray whose origin is inside an ellipsoid hits it where it leaves it; the normal there is the outward
    normal (it points along the ray).

    Args:
        origins: (..., N, 3) ray origins (broadcast against ``dirs``).
        dirs: (..., N, 3) ray directions; ``t`` is in units of ``|dir|`` (a distance for unit directions).
        centers: (K, 3). R_world_ellipsoid: (K, 3, 3), columns = ellipsoid axes in world. semi_axes: (K, 3).
        chunk_size: rays per chunk.

    Returns:
        t_hit: (..., N) nearest positive hit, ``+inf`` where none.
        part_id: (..., N) int64 ellipsoid hit, -1 where none (ties go to the lower index).
        normal: (..., N, 3) outward unit normal at the hit, zeros where none.
    """
    check_shape(dirs, ("...", "N", 3), "dirs")
    check_shape(origins, ("...", 3), "origins")
    check_ellipsoids(centers, R_world_ellipsoid, semi_axes)
    if chunk_size < 1:
        raise InputError(f"chunk_size must be >= 1, got {chunk_size}")
    shape = torch.broadcast_shapes(origins.shape, dirs.shape)
    o_all = origins.expand(shape).reshape(-1, 3)  # (R, 3)
    d_all = dirs.expand(shape).reshape(-1, 3)  # (R, 3)
    radii = semi_axes.amax(-1)  # (K,) bounding spheres
    t_out, id_out = [], []
    for start in range(0, o_all.shape[0], chunk_size):
        o, d = o_all[start:start + chunk_size], d_all[start:start + chunk_size]
        ray_idx, part_idx = bounding_sphere_pairs(o, d, centers, radii)
        t_pair = ray_ellipsoid_pair_hits(o[ray_idx], d[ray_idx], part_idx, centers, R_world_ellipsoid, semi_axes)
        t, pid = nearest_hits(t_pair, ray_idx, part_idx, o.shape[0])
        t_out.append(t)
        id_out.append(pid)
    if t_out:
        t_hit, part_id = torch.cat(t_out), torch.cat(id_out)
    else:
        t_hit = torch.empty(0, dtype=d_all.dtype, device=d_all.device)
        part_id = torch.empty(0, dtype=torch.int64, device=d_all.device)
    hit = (part_id >= 0).nonzero()[:, 0]  # (Nh,)
    points = o_all[hit] + t_hit[hit, None] * d_all[hit]  # (Nh, 3)
    normal = torch.zeros_like(d_all)  # (R, 3)
    normal[hit] = ellipsoid_normals(points, part_id[hit], centers, R_world_ellipsoid, semi_axes)
    return t_hit.reshape(shape[:-1]), part_id.reshape(shape[:-1]), normal.reshape(shape)


def ray_box_intersect(
    origins: torch.Tensor, dirs: torch.Tensor, center: torch.Tensor, R_world_box: torch.Tensor,
    half_size: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Entry hit of rays with one oriented box (slab test); rays starting inside the box miss it.

    Args:
        origins, dirs: (..., 3) rays (``t`` in units of ``|dir|``).
        center: (3,) box centre. R_world_box: (3, 3), columns = box axes in world. half_size: (3,) > 0.

    Returns:
        t: (...) entry distance, ``+inf`` on a miss. normal: (..., 3) outward world normal of the entry face.
    """
    check_shape(center, (3,), "center")
    check_shape(R_world_box, (3, 3), "R_world_box")
    check_shape(half_size, (3,), "half_size")
    o, d = (origins - center) @ R_world_box, dirs @ R_world_box  # (..., 3) in the box frame
    d = torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)  # parallel to a slab: never crosses it
    t0, t1 = (-half_size - o) / d, (half_size - o) / d  # (..., 3) slab crossings
    t_enter, axis = torch.minimum(t0, t1).max(-1)  # (...), the entry face's axis
    t_exit = torch.maximum(t0, t1).amin(-1)
    t = torch.where((t_enter <= t_exit) & (t_enter > 0), t_enter, float("inf"))
    sign = -torch.sign(d.gather(-1, axis[..., None]))  # (..., 1) the entry face looks back at the ray
    normal = F.one_hot(axis, 3).to(d) * sign @ R_world_box.T  # (..., 3)
    return t, normal


def rays_meet_ellipsoids(origins: torch.Tensor, dirs: torch.Tensor, centres: torch.Tensor, R: torch.Tensor,
                         semi_axes: torch.Tensor, bundle: int = 64, max_tests: int = 1 << 22) -> torch.Tensor:
    """Whether each camera's rays meet any of each frame's ellipsoids ahead of the camera.

    All rays of a camera leave its centre, so for the ray ``o + t d`` and the ellipsoid ``(x - c)^T A (x - c) = 1``
    (``A = R diag(1/a^2) R^T``, ``m = o - c``, ``g = m^T A m - 1 > 0`` for a camera outside it) the two roots in
    ``t`` are real where ``d^T ((A m)(A m)^T / g - A) d >= 0`` and positive where ``d . A m < 0``: a quadratic and
    a linear form in ``d`` whose coefficients are the camera's and ellipsoid's (the ellipsoid's silhouette conic).
    A ray is tested against an ellipsoid only where its bundle's cone (``bundle`` consecutive rays about their
    mean direction) meets the cone of the ellipsoid's bounding sphere: an ellipsoid covers a small part of an image,
    so consecutive rays that are near each other (an image's pixels in tiles, as the refinement's body masks order
    them) make few tests. The result does not depend on the order. A camera inside an ellipsoid sees it everywhere.

    Args:
        origins: (C, 3) camera centres. dirs: (C, P, 3) unit ray directions. centres: (T, K, 3), R: (T, K, 3, 3)
            (columns: the axes), semi_axes: (K, 3) or (T, K, 3): T frames' K ellipsoids.
        bundle: rays screened together. max_tests: (ray, ellipsoid) tests held at once (memory).

    Returns:
        (T, C, P) bool.
    """
    T, K, _ = centres.shape
    C, P, _ = dirs.shape
    if bundle < 1 or max_tests < bundle:
        raise InputError(f"rays_meet_ellipsoids: bundle must be >= 1 and max_tests >= bundle, got {bundle}, "
                         f"{max_tests}")
    semi_axes = semi_axes.expand(T, K, 3)
    A = (R / semi_axes[..., None, :].square()) @ R.transpose(-1, -2)  # (T, K, 3, 3)
    m = origins[:, None, None] - centres[None]  # (C, T, K, 3)
    Am = (A[None] @ m[..., None])[..., 0]  # (C, T, K, 3)
    g = (m * Am).sum(-1) - 1.0  # (C, T, K), > 0: the camera outside
    B = Am[..., :, None] * Am[..., None, :] / g.clamp(min=1e-12)[..., None, None] - A[None]  # (C, T, K, 3, 3)
    quad = torch.stack([B[..., 0, 0], B[..., 1, 1], B[..., 2, 2], 2 * B[..., 0, 1], 2 * B[..., 0, 2],
                        2 * B[..., 1, 2]], -1)  # (C, T, K, 6)
    # the bundles' cones: the rays padded with the last to whole bundles, each bundle's mean direction and the
    # largest angle of its rays from it; a bundle with a ray that is not finite (a pixel the lens model cannot
    # undistort) is not screened
    nb = -(-P // bundle)
    padded = torch.cat([dirs, dirs[:, -1:].expand(C, nb * bundle - P, 3)], 1)  # (C, nb * bundle, 3)
    bundles = padded.view(C, nb, bundle, 3)
    axis = F.normalize(bundles.nan_to_num(0.0, 0.0, 0.0).sum(2), dim=-1)  # (C, nb, 3)
    spread = torch.acos((bundles * axis[:, :, None]).sum(-1).amin(-1).clamp(-1, 1))  # (C, nb)
    spread = torch.where(torch.isfinite(bundles).all(-1).all(-1), spread, torch.pi)
    x, y, z = padded.unbind(-1)
    mono = torch.stack([x * x, y * y, z * z, x * y, x * z, y * z], -1)  # (C, nb * bundle, 6): the quadratic's terms
    # each ellipsoid's bounding sphere from each camera: its direction and angular radius (a little wider for
    # the rounding; a camera inside the sphere: every direction)
    dist = m.norm(dim=-1)  # (C, T, K)
    radius = semi_axes.amax(-1)[None] * 1.01 + 1e-6  # (1, T, K)
    reach = torch.where(dist > radius, torch.asin((radius / dist).clamp(max=1.0)), torch.full_like(dist, torch.pi))
    out = torch.zeros((C, T, nb, bundle), dtype=torch.bool, device=dirs.device)
    mono, padded = mono.view(C, nb, bundle, 6), padded.view(C, nb, bundle, 3)
    for c in range(C):
        # (T, K, nb): the angle between the bundle's axis and the sphere's centre within the two cones' sum; the
        # bundles that meet any of a frame's spheres are tested against all its ellipsoids, one matrix product each
        cos_apart = torch.einsum("bi,tki->tkb", axis[c], -m[c] / dist[c, ..., None].clamp(min=1e-12))
        apart = torch.acos(cos_apart.clamp(-1, 1))
        t, b = (apart <= reach[c, ..., None] + spread[c] + 1e-4).any(1).nonzero(as_tuple=True)
        step = max(1, max_tests // (bundle * K))
        for s in range(0, t.numel(), step):
            ts, bs = t[s:s + step], b[s:s + step]
            meets = torch.bmm(mono[c, bs], quad[c, ts].transpose(1, 2)) >= 0  # (n, bundle, K)
            ahead = torch.bmm(padded[c, bs], Am[c, ts].transpose(1, 2)) < 0
            out[c, ts, bs] = (meets & ahead).any(-1)
    out = out.view(C, T, nb * bundle)
    out[(g <= 0).any(-1)] = True  # (C, T): a camera inside an ellipsoid
    return out[..., :P].transpose(0, 1).contiguous()
