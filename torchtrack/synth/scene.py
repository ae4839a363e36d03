"""A static textured room seen by a calibrated rig, and an ellipsoid body rendered into it.

Conventions (see :mod:`torchtrack.conventions`): world Z up, metres, OpenCV cameras, images ``(C, 3, H, W)``
RGB in [0, 1]. Pixel centres are at integer pixel coordinates; every pixel is one ray through its centre (no
anti-aliasing, so silhouettes are exact point-in-conic tests at pixel centres).

The room: a textured floor ``z = 0`` (checker + smooth noise), a textured cylindrical wall of radius
``wall_radius_m`` centred on the world origin, and a flat ceiling at ``wall_height_m``. Everything static
(per-pixel rays, the room image and its depth, the optional distractor) is cast once in ``__init__``; a frame
only casts body rays for pixels in image tiles whose cone of rays meets a part's bounding sphere.

Internally images are kept as ``(C, Hp, Wp, 3)`` with ``Hp, Wp`` the largest image size rounded up to whole
tiles; cameras with smaller images use the top-left corner, and pixels outside it are never drawn into.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from torchtrack.checks import InputError, check_shape
from torchtrack.synth.render import (
    check_ellipsoids, ellipsoid_normals, ellipsoid_world_to_unit, nearest_hits, ray_ellipsoid_pair_hits, shade,
)

__all__ = ["SceneConfig", "SceneRenderer", "illumination_gain"]


@dataclass(frozen=True)
class SceneConfig:
    """Appearance of the synthetic room and the effects applied to rendered frames.

    Attributes:
        floor_texture_scale_m: side of one floor checker square (m); the smooth floor noise scales with it.
        wall_radius_m: radius of the cylindrical wall around the world origin (m); must enclose every camera.
        wall_height_m: height of the wall, where the flat ceiling is (m); must be above every camera.
        light_dir: direction *towards* the directional light (world, need not be unit).
        ambient: fraction of light reaching every surface, in [0, 1].
        noise_std: standard deviation of the additive Gaussian sensor noise per channel (image units).
        illumination_change: amplitude ``a`` of the global gain ``1 + a sin(2 pi frame / num_frames)``
            applied to the whole frame (body and room); 0 turns it off.
        shadow: draw a soft shadow on the floor under the body (light from straight above: each part darkens
            the floor inside its vertical footprint ellipse, with a soft edge). Not part of the silhouettes.
        shadow_strength: darkening factor at the centre of a footprint, in [0, 1).
        shadow_softness_m: half width of the shadow's soft edge (m) for a part at floor level; it grows with
            the part's height above the floor.
        distractor: draw a static coloured box standing on the floor in the video frames (never in
            :meth:`SceneRenderer.background` frames, never in the silhouettes). It is physically placed and
            cast like the room, so it shows only in the views whose field of view contains it (see
            ``SceneRenderer.distractor_visible``) and is occluded by the body.
        distractor_xy_m: floor position (x, y) of the box centre (m).
        distractor_size_m: box size along its own x, y and z (m).
        distractor_yaw: rotation of the box about the world Z axis (rad).
        distractor_colour: RGB albedo of the box.
        distractor_cameras: if given, the box is drawn only in these camera indices (an inconsistent,
            view-dependent distractor); ``None`` draws it in every view that sees it.
        part_shading_variation: relative brightness change along each part's longest axis (texture-free
            variation so that a part is not one flat colour).
        tile_px: side of the square pixel tiles used to cull body rays.
        seed: seed of the room textures (deterministic).
    """

    floor_texture_scale_m: float = 0.5
    wall_radius_m: float = 6.0
    wall_height_m: float = 4.0
    light_dir: tuple[float, float, float] = (0.35, -0.25, 1.0)
    ambient: float = 0.4
    noise_std: float = 2.0 / 255.0
    illumination_change: float = 0.0
    shadow: bool = False
    shadow_strength: float = 0.45
    shadow_softness_m: float = 0.06
    distractor: bool = False
    distractor_xy_m: tuple[float, float] = (1.9, 0.7)
    distractor_size_m: tuple[float, float, float] = (0.45, 0.45, 0.9)
    distractor_yaw: float = 0.4
    distractor_colour: tuple[float, float, float] = (0.85, 0.42, 0.12)
    distractor_cameras: tuple[int, ...] | None = None
    part_shading_variation: float = 0.12
    tile_px: int = 16
    seed: int = 0

    def __post_init__(self) -> None:
        positive = ("floor_texture_scale_m", "wall_radius_m", "wall_height_m", "shadow_softness_m", "tile_px")
        for name in positive:
            if not getattr(self, name) > 0:
                raise InputError(f"SceneConfig.{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 <= self.ambient <= 1.0:
            raise InputError(f"SceneConfig.ambient must be in [0, 1], got {self.ambient}")
        if not 0.0 <= self.shadow_strength < 1.0:
            raise InputError(f"SceneConfig.shadow_strength must be in [0, 1), got {self.shadow_strength}")
        if self.noise_std < 0 or not 0.0 <= self.illumination_change < 1.0:
            raise InputError("SceneConfig: noise_std must be >= 0 and illumination_change in [0, 1)")
        if any(s <= 0 for s in self.distractor_size_m):
            raise InputError(f"SceneConfig.distractor_size_m must be > 0, got {self.distractor_size_m}")
        if math.hypot(*self.light_dir) == 0:
            raise InputError("SceneConfig.light_dir must not be zero")


def illumination_gain(frame: int, num_frames: int, amplitude: float) -> float:
    """Global image gain of frame ``frame`` of ``num_frames``: ``1 + amplitude * sin(2 pi frame / num_frames)``."""
    if num_frames < 1:
        raise InputError(f"num_frames must be >= 1, got {num_frames}")
    return 1.0 + amplitude * math.sin(2.0 * math.pi * frame / num_frames)


def _smooth_noise(uv: torch.Tensor, generator: torch.Generator, octaves: int = 3, waves: int = 6,
                  periodic_u: bool = False) -> torch.Tensor:
    """Smooth deterministic noise in about [-1, 1]: sums of random plane waves.

    Args:
        uv: (..., 2) texture coordinates (about one unit per feature at the first octave).
        periodic_u: use integer frequencies along u (for a coordinate that wraps at 1).

    Returns:
        (...) noise.
    """
    out = torch.zeros(uv.shape[:-1], dtype=uv.dtype, device=uv.device)
    total = 0.0
    for o in range(octaves):
        f = 2.0 ** o
        ang = torch.rand(waves, generator=generator, dtype=torch.float64) * 2 * math.pi
        phase = torch.rand(waves, generator=generator, dtype=torch.float64) * 2 * math.pi
        freq = torch.stack([ang.cos(), ang.sin()], -1) * f  # (waves, 2) cycles per unit
        if periodic_u:
            freq[:, 0] = (freq[:, 0] * 6).round()
        arg = uv @ freq.T.to(uv) * (2 * math.pi) + phase.to(uv)  # (..., waves)
        out = out + arg.sin().sum(-1) / (f * math.sqrt(waves / 2))
        total += 1.0 / f
    return out / total


class SceneRenderer(nn.Module):
    """Renders ellipsoid bodies into a static textured room seen by every camera of a rig.

    Args:
        rig: a ``CameraRig`` (``image_size_wh (C, 2)``, ``pixel_rays(uv_px (C, N, 2))``); its cameras must be
            central (every pixel ray starts at the camera centre) and inside the room.
        config: the room and effects.

    Buffers (``Hp, Wp``: largest image size rounded up to whole tiles; ``nT`` tiles per camera, ``T = tile_px``):
        cam_centers (C, 3); dirs_tiled (C * nT * T^2, 3) unit pixel rays, tile-major;
        tile_to_image (C * nT * T^2,) flat index into (C, Hp, Wp); tile_axis (C, nT, 3), tile_half_angle (C, nT);
        room (C, Hp, Wp, 3) and room_depth (C, Hp, Wp) (0 outside a camera's image); floor_xy (C, Hp, Wp, 2)
        (NaN off the floor); and, with the distractor, scene / scene_depth / scene_floor likewise.
    """

    def __init__(self, rig: nn.Module, config: SceneConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or SceneConfig()
        self.rig = rig
        sizes = rig.image_size_wh.detach().cpu().long()  # (C, 2) W, H
        self.image_sizes_wh: list[tuple[int, int]] = [(int(w), int(h)) for w, h in sizes.tolist()]
        C, T = len(self.image_sizes_wh), config.tile_px
        W_max, H_max = int(sizes[:, 0].max()), int(sizes[:, 1].max())
        self.tiles_hw = (-(-H_max // T), -(-W_max // T))
        Hp, Wp = self.tiles_hw[0] * T, self.tiles_hw[1] * T
        if config.distractor_cameras is not None and any(not 0 <= c < C for c in config.distractor_cameras):
            raise InputError(f"SceneConfig.distractor_cameras must index the {C} cameras")

        ref = rig.K
        ys, xs = torch.meshgrid(torch.arange(Hp, device=ref.device, dtype=ref.dtype),
                                torch.arange(Wp, device=ref.device, dtype=ref.dtype), indexing="ij")
        uv = torch.stack([xs, ys], -1).reshape(1, Hp * Wp, 2).expand(C, -1, -1).contiguous()  # (C, HpWp, 2)
        with torch.no_grad():
            origins, dirs = rig.pixel_rays(uv)  # (C, HpWp, 3) each
        origins, dirs = origins.detach(), F.normalize(dirs.detach(), dim=-1)
        centers = origins.mean(1)  # (C, 3)
        if bool(((origins - centers[:, None]).norm(dim=-1) > 1e-4).any()):
            raise InputError("SceneRenderer needs central cameras: every pixel ray must start at the camera centre")
        self._check_inside_room(centers)
        valid = (xs[None] < sizes[:, 0, None, None].to(xs)) & (ys[None] < sizes[:, 1, None, None].to(ys))
        dirs = dirs.reshape(C, Hp, Wp, 3)
        self.register_buffer("cam_centers", centers)
        self.register_buffer("pixel_valid", valid)  # (C, Hp, Wp)
        self._build_tiles(dirs)
        self._build_room(centers, dirs, valid)

    # ---------------------------------------------------------------- static precomputation

    def _check_inside_room(self, centers: torch.Tensor) -> None:
        cfg = self.config
        radial = centers[:, :2].norm(dim=-1)
        if bool((radial >= cfg.wall_radius_m).any()) or bool((centers[:, 2] >= cfg.wall_height_m).any()):
            raise InputError(f"every camera must be inside the room (wall radius {cfg.wall_radius_m} m, "
                             f"height {cfg.wall_height_m} m); camera centres: {centers.tolist()}")
        if bool((centers[:, 2] <= 0).any()):
            raise InputError("every camera must be above the floor (z > 0)")

    def _build_tiles(self, dirs: torch.Tensor) -> None:
        """Tile-major rays, their image indices and each tile's bounding cone. dirs: (C, Hp, Wp, 3)."""
        C, Hp, Wp, _ = dirs.shape
        T = self.config.tile_px
        nTy, nTx = self.tiles_hw

        def to_tiles(x: torch.Tensor) -> torch.Tensor:  # (C, Hp, Wp, ...) -> (C, nT, T*T, ...)
            x = x.reshape(C, nTy, T, nTx, T, *x.shape[3:]).transpose(2, 3)
            return x.reshape(C, nTy * nTx, T * T, *x.shape[5:])

        tiled = to_tiles(dirs)  # (C, nT, T^2, 3)
        axis = F.normalize(tiled.mean(2), dim=-1)  # (C, nT, 3)
        cos_min = (tiled * axis[:, :, None]).sum(-1).amin(2).clamp(-1, 1)  # (C, nT)
        image_index = torch.arange(C * Hp * Wp, device=dirs.device).reshape(C, Hp, Wp)
        self.register_buffer("dirs_tiled", tiled.reshape(-1, 3).contiguous())
        self.register_buffer("tile_to_image", to_tiles(image_index).reshape(-1).contiguous())
        self.register_buffer("tile_axis", axis)
        self.register_buffer("tile_half_angle", torch.arccos(cos_min) + 1e-4)

    def _build_room(self, centers: torch.Tensor, dirs: torch.Tensor, valid: torch.Tensor) -> None:
        """Cast the static room (and distractor) once. centers (C, 3), dirs (C, Hp, Wp, 3), valid (C, Hp, Wp)."""
        cfg = self.config
        gen = torch.Generator().manual_seed(cfg.seed)
        o = centers[:, None, None, :].expand_as(dirs)  # (C, Hp, Wp, 3)
        rgb, depth, floor_xy = _cast_room(o, dirs, cfg, gen)
        depth = torch.where(valid, depth, torch.zeros_like(depth))  # body never wins outside the image
        self.register_buffer("room", rgb)  # (C, Hp, Wp, 3)
        self.register_buffer("room_depth", depth)  # (C, Hp, Wp)
        self.register_buffer("floor_xy", floor_xy)  # (C, Hp, Wp, 2), NaN off the floor
        if not cfg.distractor:
            self.register_buffer("distractor_visible", torch.zeros(len(centers), dtype=torch.bool,
                                                                   device=dirs.device))
            return
        t_box, rgb_box = _cast_box(o, dirs, cfg)  # (C, Hp, Wp), (C, Hp, Wp, 3)
        show = valid & (t_box < depth)
        if cfg.distractor_cameras is not None:
            allowed = torch.zeros(len(centers), dtype=torch.bool, device=dirs.device)
            allowed[list(cfg.distractor_cameras)] = True
            show &= allowed[:, None, None]
        self.register_buffer("scene", torch.where(show[..., None], rgb_box, rgb))
        self.register_buffer("scene_depth", torch.where(show, t_box, depth))
        self.register_buffer("scene_floor_xy", torch.where(show[..., None], float("nan"), floor_xy))
        self.register_buffer("distractor_visible", show.flatten(1).any(1))  # (C,)

    # ---------------------------------------------------------------- frames

    @property
    def num_cameras(self) -> int:
        return len(self.image_sizes_wh)

    @property
    def same_size(self) -> bool:
        """True when every camera has the same image size (outputs are then single tensors)."""
        return len(set(self.image_sizes_wh)) == 1

    def background(self, generator: torch.Generator | None = None):
        """An empty-room frame (no body, no distractor, no shadow, gain 1) with sensor noise.

        Args:
            generator: for the sensor noise (on this module's device); ``None`` uses the global RNG.

        Returns:
            images: (C, 3, H, W) in [0, 1]; a list of (3, H_c, W_c) when image sizes differ.
        """
        return self._finish(self.room, 1.0, generator)[0]

    def render(
        self,
        centers: torch.Tensor,
        R_world_ellipsoid: torch.Tensor,
        semi_axes: torch.Tensor,
        colours: torch.Tensor,
        frame: int = 0,
        num_frames: int = 1,
        generator: torch.Generator | None = None,
    ):
        """Render one frame of a body made of K ellipsoids in every view.

        Args:
            centers: (K, 3) ellipsoid centres (world, m).
            R_world_ellipsoid: (K, 3, 3), columns = ellipsoid axes in world.
            semi_axes: (K, 3) semi-axis lengths (m), > 0.
            colours: (K, 3) RGB albedo per part in [0, 1].
            frame, num_frames: the frame's place in the sequence (drives the illumination change).
            generator: for the sensor noise (on this module's device); ``None`` uses the global RNG.
            Inputs are moved to this module's device and dtype.

        Returns:
            images: (C, 3, H, W) float in [0, 1]; silhouettes: (C, H, W) bool, pixels whose ray hits the body
            first (shadow and distractor excluded); part_ids: (C, H, W) int64 visible part, -1 elsewhere.
            When the cameras' image sizes differ, each is a list over cameras of (3, H_c, W_c) / (H_c, W_c).
        """
        ref = self.dirs_tiled
        centers, R_world_ellipsoid, semi_axes, colours = (
            x.to(device=ref.device, dtype=ref.dtype) for x in (centers, R_world_ellipsoid, semi_axes, colours))
        check_ellipsoids(centers, R_world_ellipsoid, semi_axes)
        check_shape(colours, (centers.shape[0], 3), "colours")
        gain = illumination_gain(frame, num_frames, self.config.illumination_change)
        cfg = self.config
        base, depth, floor_xy = ((self.scene, self.scene_depth, self.scene_floor_xy) if cfg.distractor
                                 else (self.room, self.room_depth, self.floor_xy))
        image = base.clone()  # (C, Hp, Wp, 3)
        if cfg.shadow:
            self._apply_shadow(image, floor_xy, centers, R_world_ellipsoid, semi_axes)
        pix, part, rgb = self._cast_body(centers, R_world_ellipsoid, semi_axes, colours, depth)
        image.view(-1, 3)[pix] = rgb
        part_ids = torch.full(depth.shape, -1, dtype=torch.int64, device=ref.device)  # (C, Hp, Wp)
        part_ids.view(-1)[pix] = part
        images, part_ids = self._finish(image, gain, generator, part_ids)
        silhouettes = [p >= 0 for p in part_ids] if isinstance(part_ids, list) else part_ids >= 0
        return images, silhouettes, part_ids

    def _finish(self, image: torch.Tensor, gain: float, generator: torch.Generator | None,
                part_ids: torch.Tensor | None = None):
        """Gain, sensor noise, clamp, crop. image: (C, Hp, Wp, 3); part_ids: (C, Hp, Wp) or None."""
        out = image.permute(0, 3, 1, 2) * gain  # (C, 3, Hp, Wp), new memory
        if self.config.noise_std > 0:
            out += self.config.noise_std * torch.randn(out.shape, generator=generator, device=out.device,
                                                       dtype=out.dtype)
        out.clamp_(0, 1)
        if self.same_size:
            W, H = self.image_sizes_wh[0]
            crop = (out[..., :H, :W].contiguous(), None if part_ids is None else part_ids[:, :H, :W].contiguous())
            return crop
        images = [out[c, :, :h, :w].contiguous() for c, (w, h) in enumerate(self.image_sizes_wh)]
        ids = None if part_ids is None else [part_ids[c, :h, :w].contiguous()
                                              for c, (w, h) in enumerate(self.image_sizes_wh)]
        return images, ids

    def _cast_body(self, centers, R_world_ellipsoid, semi_axes, colours, depth):
        """Cast body rays in the tiles whose ray cone meets a part's bounding sphere.

        Returns:
            pix: (Nb,) flat indices into (C, Hp, Wp) of body pixels; part: (Nb,) int64; rgb: (Nb, 3).
        """
        C, nT = self.tile_half_angle.shape
        T2 = self.config.tile_px ** 2
        v = centers[None] - self.cam_centers[:, None]  # (C, K, 3) camera -> part centre
        dist = v.norm(dim=-1)  # (C, K)
        radius = semi_axes.amax(-1)[None].expand_as(dist)  # (C, K) bounding-sphere radius
        beta = torch.where(dist > radius, torch.arcsin((radius / dist).clamp(max=1)), math.pi)  # (C, K)
        cos_ang = (self.tile_axis @ F.normalize(v, dim=-1).transpose(1, 2)).clamp(-1, 1)  # (C, nT, K)
        near = torch.arccos(cos_ang) <= self.tile_half_angle[..., None] + beta[:, None]  # (C, nT, K)
        cam, tile, k = near.nonzero(as_tuple=True)  # (M,) each
        ray = ((cam * nT + tile) * T2)[:, None] + torch.arange(T2, device=cam.device)  # (M, T^2) tiled ray
        ray, k_pair = ray.reshape(-1), k[:, None].expand(-1, T2).reshape(-1)  # (P,)
        cam_pair = cam[:, None].expand(-1, T2).reshape(-1)  # (P,)
        origins, dirs = self.cam_centers[cam_pair], self.dirs_tiled[ray]  # (P, 3)
        t_pair = ray_ellipsoid_pair_hits(origins, dirs, k_pair, centers, R_world_ellipsoid, semi_axes)
        hit = torch.isfinite(t_pair)
        ray, k_pair, t_pair, cam_pair = ray[hit], k_pair[hit], t_pair[hit], cam_pair[hit]
        # Reduce over the rays that hit something only: compact their ids first.
        uniq, inverse = torch.unique(ray, return_inverse=True)  # (Nh,), (P',)
        t_hit, part = nearest_hits(t_pair, inverse, k_pair, uniq.shape[0])  # (Nh,)
        pix = self.tile_to_image[uniq]  # (Nh,) flat (C, Hp, Wp)
        front = t_hit < depth.view(-1)[pix]  # in front of the room / distractor, inside the image
        uniq, pix, t_hit, part = uniq[front], pix[front], t_hit[front], part[front]
        cam = torch.div(uniq, nT * T2, rounding_mode="floor")
        points = self.cam_centers[cam] + t_hit[:, None] * self.dirs_tiled[uniq]  # (Nb, 3)
        normal = ellipsoid_normals(points, part, centers, R_world_ellipsoid, semi_axes)  # (Nb, 3)
        B = ellipsoid_world_to_unit(R_world_ellipsoid, semi_axes)  # (K, 3, 3)
        p_unit = (B[part] @ (points - centers[part])[..., None])[..., 0]  # (Nb, 3)
        long_axis = semi_axes.argmax(-1)[part]  # (Nb,)
        variation = p_unit.gather(1, long_axis[:, None])[:, 0]  # (Nb,) position along the long axis
        light = torch.tensor(self.config.light_dir, device=points.device, dtype=points.dtype)
        rgb = shade(normal, part, colours, light, self.config.ambient, variation,
                    self.config.part_shading_variation)
        return pix, part, rgb

    def _apply_shadow(self, image, floor_xy, centers, R_world_ellipsoid, semi_axes) -> None:
        """Darken, in place, floor pixels under the body's vertical footprint. image: (C, Hp, Wp, 3)."""
        cfg = self.config
        A = ellipsoid_world_to_unit(R_world_ellipsoid, semi_axes)
        A = A.transpose(1, 2) @ A  # (K, 3, 3) quadric matrix: inside iff (p-c)^T A (p-c) <= 1
        # Vertical footprint ellipse (Schur complement on z): q^T M q <= 1, q = xy - c_xy.
        M = A[:, :2, :2] - A[:, :2, 2:] @ A[:, 2:, :2] / A[:, 2:, 2:]  # (K, 2, 2)
        height = (centers[:, 2] - 1.0 / A[:, 2, 2].sqrt()).clamp_min(0)  # (K,) approx. bottom above floor
        soft = cfg.shadow_softness_m * (1.0 + 2.0 * height)  # (K,)
        strength = cfg.shadow_strength / (1.0 + height)  # (K,) fainter for high parts
        ext = torch.linalg.inv(M).diagonal(dim1=1, dim2=2).clamp_min(0).sqrt() + 2 * soft[:, None]  # (K, 2)
        lo = (centers[:, :2] - ext).amin(0)
        hi = (centers[:, :2] + ext).amax(0)
        xy = floor_xy.view(-1, 2)
        sel = ((xy >= lo) & (xy <= hi)).all(-1).nonzero()[:, 0]  # (S,) floor pixels near the footprint
        q = xy[sel][:, None] - centers[None, :, :2]  # (S, K, 2)
        r = ((q[..., None, :] @ M[None] @ q[..., None])[..., 0, 0]).clamp_min(1e-12).sqrt()  # (S, K)
        signed = q.norm(dim=-1) * (1.0 - 1.0 / r)  # (S, K) approx. distance outside the footprint edge (m)
        w = ((soft - signed) / (2 * soft)).clamp(0, 1)  # (S, K) 1 inside, 0 outside
        w = w * w * (3 - 2 * w)  # smoothstep
        dark = (strength * w).amax(-1)  # (S,)
        image.view(-1, 3)[sel] *= (1.0 - dark)[:, None]


def _cast_room(o: torch.Tensor, d: torch.Tensor, cfg: SceneConfig, gen: torch.Generator):
    """Floor, wall and ceiling hit by rays o + t d (unit d).

    Args:
        o, d: (..., 3).

    Returns:
        rgb (..., 3), depth (...), floor_xy (..., 2) (NaN where the ray does not end on the floor).
    """
    R, Hw = cfg.wall_radius_m, cfg.wall_height_m
    light = F.normalize(torch.tensor(cfg.light_dir, dtype=d.dtype, device=d.device), dim=0)
    # Wall: |o_xy + t d_xy| = R, the positive root (cameras are inside).
    a = d[..., :2].square().sum(-1).clamp_min(1e-12)
    b = (o[..., :2] * d[..., :2]).sum(-1)
    c = o[..., :2].square().sum(-1) - R * R
    t_wall = (-b + (b * b - a * c).clamp_min(0).sqrt()) / a  # (...)
    t_floor = torch.where(d[..., 2] < 0, -o[..., 2] / d[..., 2], float("inf"))
    t_ceil = torch.where(d[..., 2] > 0, (Hw - o[..., 2]) / d[..., 2], float("inf"))
    depth = torch.minimum(torch.minimum(t_wall, t_floor), t_ceil)
    p = o + depth[..., None] * d  # (..., 3)
    on_floor, on_ceil = t_floor <= depth, (t_ceil <= depth) & (t_floor > depth)

    # Floor: two-tone checker with smooth noise in colour and brightness.
    s = cfg.floor_texture_scale_m
    checker = ((torch.floor(p[..., 0] / s) + torch.floor(p[..., 1] / s)) % 2)[..., None]  # (..., 1)
    tone0 = torch.tensor([0.58, 0.52, 0.44], dtype=d.dtype, device=d.device)
    tone1 = torch.tensor([0.36, 0.39, 0.44], dtype=d.dtype, device=d.device)
    n = torch.stack([_smooth_noise(p[..., :2] / (3 * s), gen) for _ in range(3)], -1)  # (..., 3)
    floor = (tone0 + (tone1 - tone0) * checker) * (1 + 0.18 * n.mean(-1, keepdim=True)) + 0.05 * n
    floor = floor * (cfg.ambient + (1 - cfg.ambient) * light[2].clamp_min(0))

    # Wall: panels of muted colours (some close to clothing and skin tones) with noise and a dark skirting.
    az = (torch.atan2(p[..., 1], p[..., 0]) / (2 * math.pi)) % 1.0  # (...) in [0, 1)
    panels = 14
    palette = 0.25 + 0.5 * torch.rand(panels, 3, generator=gen, dtype=torch.float64)
    panel = palette.to(d)[(az * panels).long().clamp(max=panels - 1)]  # (..., 3)
    wuv = torch.stack([az, p[..., 2] / (2 * math.pi * R)], -1)
    wn = torch.stack([_smooth_noise(wuv * 12, gen, periodic_u=True) for _ in range(3)], -1)
    wall = panel * (1 + 0.2 * wn.mean(-1, keepdim=True)) + 0.04 * wn
    wall = torch.where((p[..., 2:] < 0.12), wall * 0.35, wall)
    normal_in = -F.normalize(torch.cat([p[..., :2], torch.zeros_like(p[..., 2:])], -1), dim=-1)
    wall = wall * (cfg.ambient + (1 - cfg.ambient) * (normal_in @ light).clamp_min(0))[..., None]

    ceil = torch.tensor([0.78, 0.78, 0.76], dtype=d.dtype, device=d.device) * (
        1 + 0.06 * _smooth_noise(p[..., :2] / 2, gen))[..., None] * 0.8
    rgb = torch.where(on_floor[..., None], floor, torch.where(on_ceil[..., None], ceil, wall)).clamp(0, 1)
    floor_xy = torch.where(on_floor[..., None], p[..., :2], float("nan"))
    return rgb.contiguous(), depth.contiguous(), floor_xy.contiguous()


def _cast_box(o: torch.Tensor, d: torch.Tensor, cfg: SceneConfig):
    """The distractor box (slab test). o, d: (..., 3). Returns t (...) (+inf on a miss) and rgb (..., 3)."""
    cy, sy = math.cos(cfg.distractor_yaw), math.sin(cfg.distractor_yaw)
    R_world_box = torch.tensor([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]], dtype=d.dtype, device=d.device)
    half = torch.tensor(cfg.distractor_size_m, dtype=d.dtype, device=d.device) / 2
    center = torch.tensor([*cfg.distractor_xy_m, float(half[2])], dtype=d.dtype, device=d.device)
    ob, db = (o - center) @ R_world_box, d @ R_world_box  # (..., 3) in the box frame
    db = torch.where(db.abs() < 1e-12, torch.full_like(db, 1e-12), db)
    t0, t1 = (-half - ob) / db, (half - ob) / db  # (..., 3)
    t_enter, axis = torch.minimum(t0, t1).max(-1)  # (...), entry face axis
    t_exit = torch.maximum(t0, t1).amin(-1)
    hit = (t_enter <= t_exit) & (t_enter > 0)
    t = torch.where(hit, t_enter, float("inf"))
    sign = -torch.sign(db.gather(-1, axis[..., None]))  # (..., 1) the face looks back at the ray
    normal = F.one_hot(axis, 3).to(d) * sign @ R_world_box.T  # (..., 3) world
    light = F.normalize(torch.tensor(cfg.light_dir, dtype=d.dtype, device=d.device), dim=0)
    albedo = torch.tensor(cfg.distractor_colour, dtype=d.dtype, device=d.device)
    rgb = albedo * (cfg.ambient + (1 - cfg.ambient) * (normal @ light).clamp_min(0))[..., None]
    return t, rgb.clamp(0, 1)
