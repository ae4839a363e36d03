"""A static textured room seen by a calibrated rig, and an ellipsoid body rendered into it.

Conventions (see :mod:`torchtrack.conventions`): world Z up, metres, OpenCV cameras, images ``(C, 3, H, W)``
RGB in [0, 1]. Pixel centres are at integer pixel coordinates; every pixel is one ray through its centre (no
anti-aliasing, so silhouettes are exact point-in-conic tests at pixel centres).

The room: a textured floor ``z = 0`` (checker + smooth noise), a textured cylindrical wall of radius
``wall_radius_m`` centred on the world origin, and a flat ceiling at ``wall_height_m``. Everything static
(per-pixel rays, the room image and its depth, the optional distractor) is cast once in ``__init__``; a frame
only casts body rays for the (image tile, part) pairs whose cone of rays meets the part's bounding sphere.

Cameras with different image sizes are batched too: internally images are ``(C, 3, Hp, Wp)`` with ``Hp, Wp``
the largest size rounded up to whole tiles, each camera using its top-left ``H_c x W_c`` corner.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from torchtrack.checks import InputError, check_shape
from torchtrack.ellipsoids import check_ellipsoids, ellipsoid_world_to_unit, ray_box_intersect, unit_sphere_hits
from torchtrack.synth.render import shade

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
    distractor_xy_m: tuple[float, float] = (2.2, 0.9)
    distractor_size_m: tuple[float, float, float] = (0.45, 0.45, 0.9)
    distractor_yaw: float = 0.4
    distractor_colour: tuple[float, float, float] = (0.85, 0.42, 0.12)
    distractor_cameras: tuple[int, ...] | None = None
    part_shading_variation: float = 0.12
    tile_px: int = 8
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
                  period_u: float | None = None) -> torch.Tensor:
    """Smooth deterministic noise in about [-1, 1]: sums of random plane waves (cheap and seamless).

    Args:
        uv: (N, 2) texture coordinates (about one feature per unit at the first octave).
        period_u: if given, the noise repeats with this period along u (for a coordinate that wraps).

    Returns:
        (N,) noise.
    """
    out = torch.zeros(uv.shape[:-1], dtype=uv.dtype, device=uv.device)
    total = 0.0
    for o in range(octaves):
        f = 2.0 ** o
        ang = torch.rand(waves, generator=generator, dtype=torch.float64) * 2 * math.pi
        phase = torch.rand(waves, generator=generator, dtype=torch.float64) * 2 * math.pi
        freq = torch.stack([ang.cos(), ang.sin()], -1) * f  # (waves, 2) cycles per unit
        if period_u is not None:
            freq[:, 0] = (freq[:, 0] * period_u).round() / period_u
        arg = torch.addmm(phase.to(uv), uv, freq.T.to(uv), alpha=2 * math.pi)  # (N, waves)
        out += arg.sin_().sum(-1) / (f * math.sqrt(waves / 2))
        total += 1.0 / f
    return out / total


#: Muted wall-panel colours, some near skin and clothing tones so that the body is not always far from the room.
_WALL_PALETTE = (
    (0.62, 0.55, 0.46), (0.55, 0.30, 0.24), (0.30, 0.36, 0.50), (0.45, 0.47, 0.34), (0.50, 0.50, 0.50),
    (0.24, 0.38, 0.40), (0.70, 0.56, 0.45), (0.42, 0.24, 0.28), (0.28, 0.28, 0.30), (0.66, 0.64, 0.58),
)


class SceneRenderer(nn.Module):
    """Renders ellipsoid bodies into a static textured room seen by every camera of a rig.

    Args:
        rig: a ``CameraRig`` (``image_size_wh (C, 2)``, ``pixel_rays(uv_px (C, N, 2))``); its cameras must be
            central (every pixel ray starts at the camera centre) and inside the room.
        config: the room and effects.

    Attributes:
        image_sizes_wh: per camera (W, H). distractor_visible: (C,) bool buffer, views that show the distractor.

    Internal buffers (``Hp, Wp``: the largest image size rounded up to whole tiles; ``G = C * nT`` tiles of
    ``T2 = tile_px^2`` pixels, tile-major): cam_centers (C, 3); tile_dirs (G, T2, 3) unit pixel rays;
    tile_pixel (nT, T2) flat index into (Hp * Wp); tile_axis (C, nT, 3) and tile_half_angle (C, nT), the tiles'
    ray cones; room (C, 3, Hp, Wp) and room_depth (C, Hp * Wp) (0 outside a camera's image, so the body never
    shows there); room_floor_xy (G, T2, 2) (NaN off the floor) with its per-tile box floor_lo / floor_hi (G, 2);
    and, with the distractor, scene / scene_depth / scene_floor_xy / scene_floor_lo / scene_floor_hi likewise.
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
        size = sizes.to(ref.device)
        valid = (xs[None] < size[:, 0, None, None]) & (ys[None] < size[:, 1, None, None])  # (C, Hp, Wp)
        # Padding pixels (beyond a camera's image) repeat its edge pixels: harmless rays, never drawn.
        uv = torch.stack([torch.minimum(xs[None], size[:, 0, None, None] - 1).to(ref.dtype),
                          torch.minimum(ys[None], size[:, 1, None, None] - 1).to(ref.dtype)], -1)
        with torch.no_grad():
            origins, dirs = rig.pixel_rays(uv.reshape(C, Hp * Wp, 2))  # (C, HpWp, 3) each
        origins, dirs = origins.detach(), F.normalize(dirs.detach(), dim=-1)
        bad = (~torch.isfinite(dirs).all(-1)).any(-1)  # (C,) cameras with a non-finite pixel ray
        if bool(bad.any()):
            raise InputError(f"the rig gives non-finite pixel rays in cameras {bad.nonzero()[:, 0].tolist()}")
        centers = origins.mean(1)  # (C, 3)
        if bool(((origins - centers[:, None]).norm(dim=-1) > 1e-4).any()):
            raise InputError("SceneRenderer needs central cameras: every pixel ray must start at the camera centre")
        self._check_inside_room(centers)
        dirs = dirs.reshape(C, Hp, Wp, 3)
        self._buffer("cam_centers", centers)
        self._build_tiles(dirs)
        with torch.no_grad():
            self._build_room(centers, dirs, valid)

    # ---------------------------------------------------------------- static precomputation

    def _buffer(self, name: str, value: torch.Tensor) -> None:
        """Derived from the rig and config, so not part of the state dict; moves with ``.to()``."""
        self.register_buffer(name, value, persistent=False)

    def _check_inside_room(self, centers: torch.Tensor) -> None:
        cfg = self.config
        radial = centers[:, :2].norm(dim=-1)
        if bool((radial >= cfg.wall_radius_m).any()) or bool((centers[:, 2] >= cfg.wall_height_m).any()):
            raise InputError(f"every camera must be inside the room (wall radius {cfg.wall_radius_m} m, "
                             f"height {cfg.wall_height_m} m); camera centres: {centers.tolist()}")
        if bool((centers[:, 2] <= 0).any()):
            raise InputError("every camera must be above the floor (z > 0)")

    def _to_tiles(self, x: torch.Tensor) -> torch.Tensor:
        """(C, Hp, Wp, ...) -> (C * nT, T^2, ...), tile-major."""
        C, T, (nTy, nTx) = x.shape[0], self.config.tile_px, self.tiles_hw
        x = x.reshape(C, nTy, T, nTx, T, *x.shape[3:]).transpose(2, 3)
        return x.reshape(C * nTy * nTx, T * T, *x.shape[5:]).contiguous()

    def _build_tiles(self, dirs: torch.Tensor) -> None:
        """Tile-major rays, their pixel indices and each tile's bounding cone. dirs: (C, Hp, Wp, 3)."""
        C, Hp, Wp, _ = dirs.shape
        tiled = self._to_tiles(dirs)  # (G, T2, 3)
        axis = F.normalize(tiled.mean(1), dim=-1)  # (G, 3)
        cos_min = (tiled * axis[:, None]).sum(-1).amin(1).clamp(-1, 1)  # (G,)
        pixel = torch.arange(Hp * Wp, device=dirs.device).reshape(1, Hp, Wp)
        self._buffer("tile_dirs", tiled)
        self._buffer("tile_pixel", self._to_tiles(pixel))  # (nT, T2), the same in every camera
        self._buffer("tile_axis", axis.reshape(C, -1, 3))
        self._buffer("tile_half_angle", (torch.arccos(cos_min) + 1e-4).reshape(C, -1))

    def _register_static(self, prefix: str, rgb, depth, floor_xy) -> None:
        """Store one static image: rgb (C, Hp, Wp, 3), depth (C, Hp, Wp), floor_xy (C, Hp, Wp, 2)."""
        xy = self._to_tiles(floor_xy)  # (G, T2, 2)
        finite = torch.isfinite(xy).all(-1, keepdim=True)  # (G, T2, 1)
        inf = torch.full_like(xy, float("inf"))
        self._buffer(f"{prefix}", rgb.permute(0, 3, 1, 2).contiguous())
        self._buffer(f"{prefix}_depth", depth.flatten(1).contiguous())
        self._buffer(f"{prefix}_floor_xy", xy)
        self._buffer(f"{prefix}_floor_lo", torch.where(finite, xy, inf).amin(1))  # (G, 2)
        self._buffer(f"{prefix}_floor_hi", torch.where(finite, xy, -inf).amax(1))  # (G, 2)

    def _build_room(self, centers: torch.Tensor, dirs: torch.Tensor, valid: torch.Tensor) -> None:
        """Cast the static room (and distractor) once. centers (C, 3), dirs (C, Hp, Wp, 3), valid (C, Hp, Wp)."""
        cfg = self.config
        gen = torch.Generator().manual_seed(cfg.seed)
        o = centers[:, None, None, :].expand_as(dirs)  # (C, Hp, Wp, 3)
        rgb, depth, floor_xy = _cast_room(o, dirs, cfg, gen)
        depth = torch.where(valid, depth, torch.zeros_like(depth))  # the body never wins outside the image
        self._register_static("room", rgb, depth, floor_xy)
        show = torch.zeros_like(valid)
        if cfg.distractor:
            t_box, rgb_box = _cast_box(o, dirs, cfg)  # (C, Hp, Wp), (C, Hp, Wp, 3)
            show = valid & (t_box < depth)
            if cfg.distractor_cameras is not None:
                allowed = torch.zeros(len(centers), dtype=torch.bool, device=dirs.device)
                allowed[list(cfg.distractor_cameras)] = True
                show &= allowed[:, None, None]
            self._register_static("scene", torch.where(show[..., None], rgb_box, rgb),
                                  torch.where(show, t_box, depth),
                                  torch.where(show[..., None], float("nan"), floor_xy))
        self._buffer("distractor_visible", show.flatten(1).any(1))  # (C,)

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
        return self._finish(self.room, 1.0, generator)

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
            before the room or distractor (the shadow is not part of them); part_ids: (C, H, W) int64 visible
            part, -1 elsewhere. When the cameras' image sizes differ, each is a list over cameras of
            (3, H_c, W_c) / (H_c, W_c) tensors.
        """
        check_ellipsoids(centers, R_world_ellipsoid, semi_axes)
        check_shape(colours, (centers.shape[0], 3), "colours")
        ref = self.tile_dirs
        centers, R_world_ellipsoid, semi_axes, colours = (
            x.to(device=ref.device, dtype=ref.dtype) for x in (centers, R_world_ellipsoid, semi_axes, colours))
        gain = illumination_gain(frame, num_frames, self.config.illumination_change)
        prefix = "scene" if self.config.distractor else "room"
        base, depth = getattr(self, prefix), getattr(self, f"{prefix}_depth")
        image = base.clone()  # (C, 3, Hp, Wp)
        flat = image.view(*image.shape[:2], -1)  # (C, 3, Hp * Wp)
        if self.config.shadow:
            cam, pix, dark = self._shadow(prefix, centers, R_world_ellipsoid, semi_axes)
            flat[cam, :, pix] *= (1.0 - dark)[:, None]
        cam, pix, part, rgb = self._cast_body(centers, R_world_ellipsoid, semi_axes, colours, depth)
        flat[cam, :, pix] = rgb
        part_ids = torch.full(depth.shape, -1, dtype=torch.int64, device=ref.device)  # (C, Hp * Wp)
        part_ids[cam, pix] = part
        images = self._finish(image, gain, generator)
        part_ids = self._crop(part_ids.view(image.shape[0], *image.shape[2:]))
        silhouettes = [p >= 0 for p in part_ids] if isinstance(part_ids, list) else part_ids >= 0
        return images, silhouettes, part_ids

    def _crop(self, x: torch.Tensor):
        """(C, ..., Hp, Wp) -> (C, ..., H, W), or a list of (..., H_c, W_c) when sizes differ."""
        if self.same_size:
            W, H = self.image_sizes_wh[0]
            return x[..., :H, :W].contiguous()
        return [x[c, ..., :h, :w].contiguous() for c, (w, h) in enumerate(self.image_sizes_wh)]

    def _finish(self, image: torch.Tensor, gain: float, generator: torch.Generator | None):
        """``clamp(gain * image + noise, 0, 1)``, cropped. image: (C, 3, Hp, Wp)."""
        if self.config.noise_std > 0:
            out = torch.randn(image.shape, generator=generator, device=image.device, dtype=image.dtype)
            out.mul_(self.config.noise_std).add_(image, alpha=gain)
        else:
            out = image * gain
        return self._crop(out.clamp_(0, 1))

    def _cast_body(self, centers, R_world_ellipsoid, semi_axes, colours, depth):
        """Cast body rays, tile by tile, for the (tile, part) pairs whose ray cone meets the part's bounding sphere.

        Args:
            centers, R_world_ellipsoid, semi_axes, colours: (K, 3), (K, 3, 3), (K, 3), (K, 3).
            depth: (C, Hp * Wp) distance to the static scene.

        Returns:
            cam, pix: (Nb,) camera and flat pixel of each body pixel; part: (Nb,) int64; rgb: (Nb, 3).
        """
        C, nT = self.tile_half_angle.shape
        v = centers[None] - self.cam_centers[:, None]  # (C, K, 3) camera -> part centre
        dist = v.norm(dim=-1)  # (C, K)
        radius = semi_axes.amax(-1)[None].expand_as(dist)  # (C, K) bounding-sphere radius
        beta = torch.where(dist > radius, torch.arcsin((radius / dist).clamp(max=1)), math.pi)  # (C, K)
        cos_ang = (self.tile_axis @ F.normalize(v, dim=-1).transpose(1, 2)).clamp(-1, 1)  # (C, nT, K)
        near = torch.arccos(cos_ang) <= self.tile_half_angle[..., None] + beta[:, None]  # (C, nT, K)
        cam, tile, k = near.nonzero(as_tuple=True)  # (M,) candidate (tile, part) blocks
        tile = cam * nT + tile  # (M,) global tile
        B = ellipsoid_world_to_unit(R_world_ellipsoid, semi_axes)[k]  # (M, 3, 3)
        o_unit = (B @ (self.cam_centers[cam] - centers[k])[..., None]).transpose(1, 2)  # (M, 1, 3)
        d_unit = self.tile_dirs[tile] @ B.transpose(1, 2)  # (M, T2, 3)
        t = unit_sphere_hits(o_unit, d_unit)  # (M, T2)
        # Nearest part per ray, over the blocks of each touched tile (ties go to the lower part).
        tiles, slot = torch.unique(tile, return_inverse=True)  # (U,), (M,)
        T2 = t.shape[1]
        slot_px = slot[:, None].expand(-1, T2)  # (M, T2)
        t_best = torch.full((tiles.shape[0], T2), float("inf"), dtype=t.dtype, device=t.device)
        t_best.scatter_reduce_(0, slot_px, t, reduce="amin")  # (U, T2)
        big = torch.iinfo(torch.int64).max
        wins = torch.isfinite(t) & (t == t_best.gather(0, slot_px))  # (M, T2)
        k_win = torch.where(wins, k[:, None], big)  # (M, T2)
        part = torch.full_like(t_best, big, dtype=torch.int64).scatter_reduce_(0, slot_px, k_win, reduce="amin")
        # The winning (block, ray) of every body pixel in front of the static scene.
        cam_u = torch.div(tiles, nT, rounding_mode="floor")  # (U,)
        pix_u = self.tile_pixel[tiles % nT]  # (U, T2)
        front = (part != big) & (t_best < depth[cam_u[:, None], pix_u])  # (U, T2)
        win = wins & (k_win == part.gather(0, slot_px)) & front.gather(0, slot_px)  # (M, T2), one per pixel
        m, j = win.nonzero(as_tuple=True)  # (Nb,) block and ray in tile
        part, cam, pix = k[m], cam_u[slot[m]], pix_u[slot[m], j]  # (Nb,)
        p_unit = o_unit[m, 0] + t[m, j, None] * d_unit[m, j]  # (Nb, 3) hit in the unit-sphere frame
        normal = F.normalize((B[m].transpose(1, 2) @ p_unit[..., None])[..., 0], dim=-1)  # (Nb, 3) world
        variation = p_unit.gather(1, semi_axes.argmax(-1)[part][:, None])[:, 0]  # (Nb,) along the long axis
        light = torch.tensor(self.config.light_dir, device=t.device, dtype=t.dtype)
        rgb = shade(normal, part, colours, light, self.config.ambient, variation,
                    self.config.part_shading_variation)
        return cam, pix, part, rgb

    def _shadow(self, prefix: str, centers, R_world_ellipsoid, semi_axes):
        """Soft vertical shadow of the body on the floor.

        Returns:
            cam, pix: (S,) camera and flat pixel of the floor pixels near the footprint; dark: (S,) in [0, 1).
        """
        cfg = self.config
        nT = self.tile_half_angle.shape[1]
        U = ellipsoid_world_to_unit(R_world_ellipsoid, semi_axes)
        A = U.transpose(1, 2) @ U  # (K, 3, 3) quadric: inside iff (p - c)^T A (p - c) <= 1
        # Vertical footprint ellipse (Schur complement on z): q^T M q <= 1, q = xy - c_xy.
        M = A[:, :2, :2] - A[:, :2, 2:] @ A[:, 2:, :2] / A[:, 2:, 2:]  # (K, 2, 2)
        cov = R_world_ellipsoid @ (semi_axes.square()[..., None] * R_world_ellipsoid.transpose(1, 2))  # A^-1
        height = (centers[:, 2] - cov[:, 2, 2].sqrt()).clamp_min(0)  # (K,) lowest point above the floor
        soft = cfg.shadow_softness_m * (1.0 + 1.5 * height)  # (K,) blurrier for high parts
        strength = cfg.shadow_strength / (1.0 + 0.5 * height)  # (K,) fainter for high parts
        ext = cov[:, :2, :2].diagonal(dim1=1, dim2=2).sqrt() + soft[:, None]  # (K, 2) footprint half extent
        lo, hi = (centers[:, :2] - ext).amin(0), (centers[:, :2] + ext).amax(0)  # (2,) footprint box
        tiles = ((getattr(self, f"{prefix}_floor_lo") <= hi) & (getattr(self, f"{prefix}_floor_hi") >= lo))
        tiles = tiles.all(-1).nonzero()[:, 0]  # (U,) tiles with floor inside the box
        xy = getattr(self, f"{prefix}_floor_xy")[tiles]  # (U, T2, 2), NaN off the floor
        inside = ((xy >= lo) & (xy <= hi)).all(-1)  # (U, T2)
        cam = torch.div(tiles, nT, rounding_mode="floor")[:, None].expand_as(inside)[inside]  # (S,)
        pix = self.tile_pixel[tiles % nT][inside]  # (S,)
        q = xy[inside][:, None] - centers[None, :, :2]  # (S, K, 2)
        qx, qy = q[..., 0], q[..., 1]
        r2 = M[:, 0, 0] * qx * qx + 2 * M[:, 0, 1] * qx * qy + M[:, 1, 1] * qy * qy  # (S, K)
        signed = q.norm(dim=-1) * (1.0 - r2.clamp_min(1e-12).rsqrt())  # (S, K) ~ metres outside the edge
        w = ((soft - signed) / (2 * soft)).clamp(0, 1)  # (S, K) 1 inside, 0 outside
        w = w * w * (3 - 2 * w)  # smoothstep
        return cam, pix, (strength * w).amax(-1)


def _cast_room(o: torch.Tensor, d: torch.Tensor, cfg: SceneConfig, gen: torch.Generator):
    """Floor, wall and ceiling hit by rays o + t d (unit d); camera centres inside the room.

    Args:
        o, d: (..., 3).

    Returns:
        rgb (..., 3), depth (...), floor_xy (..., 2) (NaN where the ray does not end on the floor).
    """
    R, Hw = cfg.wall_radius_m, cfg.wall_height_m
    # Wall: |o_xy + t d_xy| = R, the positive root.
    a = d[..., :2].square().sum(-1).clamp_min(1e-12)
    b = (o[..., :2] * d[..., :2]).sum(-1)
    c = o[..., :2].square().sum(-1) - R * R
    t_wall = (-b + (b * b - a * c).clamp_min(0).sqrt()) / a  # (...)
    t_floor = torch.where(d[..., 2] < 0, -o[..., 2] / d[..., 2], float("inf"))
    t_ceil = torch.where(d[..., 2] > 0, (Hw - o[..., 2]) / d[..., 2], float("inf"))
    depth = torch.minimum(torch.minimum(t_wall, t_floor), t_ceil)
    p = o + depth[..., None] * d  # (..., 3)
    on_floor = t_floor <= depth
    on_ceil = (t_ceil <= depth) & ~on_floor
    on_wall = ~on_floor & ~on_ceil
    rgb = torch.empty_like(p)
    rgb[on_floor] = _floor_texture(p[on_floor], cfg, gen)
    rgb[on_wall] = _wall_texture(p[on_wall], cfg, gen)
    rgb[on_ceil] = _ceiling_texture(p[on_ceil], gen)
    floor_xy = torch.where(on_floor[..., None], p[..., :2], float("nan"))
    return rgb.clamp(0, 1).contiguous(), depth.contiguous(), floor_xy.contiguous()


def _lambert(normal: torch.Tensor, cfg: SceneConfig) -> torch.Tensor:
    """Ambient + diffuse factor (N,) for world normals (N, 3) or (3,)."""
    light = F.normalize(torch.tensor(cfg.light_dir, dtype=normal.dtype, device=normal.device), dim=0)
    return cfg.ambient + (1 - cfg.ambient) * (normal @ light).clamp_min(0)


def _floor_texture(p: torch.Tensor, cfg: SceneConfig, gen: torch.Generator) -> torch.Tensor:
    """Two-tone checker with smooth brightness and tint noise. p: (N, 3) floor points -> rgb (N, 3)."""
    s = cfg.floor_texture_scale_m
    checker = ((torch.floor(p[:, 0] / s) + torch.floor(p[:, 1] / s)) % 2)[:, None]  # (N, 1)
    tone0 = torch.tensor([0.60, 0.55, 0.47], dtype=p.dtype, device=p.device)
    tone1 = torch.tensor([0.38, 0.40, 0.44], dtype=p.dtype, device=p.device)
    uv = p[:, :2] / (2.5 * s)
    bright = _smooth_noise(uv, gen)[:, None]  # (N, 1)
    tint = torch.stack([_smooth_noise(uv * 0.5, gen, octaves=2) for _ in range(3)], -1)  # (N, 3)
    rgb = (tone0 + (tone1 - tone0) * checker) * (1 + 0.2 * bright) + 0.03 * tint
    up = torch.tensor([0.0, 0.0, 1.0], dtype=p.dtype, device=p.device)
    return rgb * _lambert(up, cfg)


def _wall_texture(p: torch.Tensor, cfg: SceneConfig, gen: torch.Generator) -> torch.Tensor:
    """Coloured panels with smooth noise and a dark skirting board. p: (N, 3) wall points -> rgb (N, 3)."""
    R = cfg.wall_radius_m
    az = (torch.atan2(p[:, 1], p[:, 0]) / (2 * math.pi)) % 1.0  # (N,) in [0, 1)
    panels = 16
    palette = torch.tensor(_WALL_PALETTE, dtype=p.dtype, device=p.device)
    pick = torch.randint(len(_WALL_PALETTE), (panels,), generator=gen).to(p.device)
    jitter = 1 + 0.15 * (torch.rand(panels, 1, generator=gen, dtype=torch.float64).to(p) - 0.5)
    panel = (palette[pick] * jitter)[(az * panels).long().clamp(max=panels - 1)]  # (N, 3)
    feature_m = 1.2
    uv = torch.stack([az * (2 * math.pi * R), p[:, 2]], -1) / feature_m  # (N, 2) about one feature per unit
    period = 2 * math.pi * R / feature_m
    bright = _smooth_noise(uv, gen, octaves=2, period_u=period)[:, None]
    tint = torch.stack([_smooth_noise(uv * 0.5, gen, octaves=2, period_u=period) for _ in range(3)], -1)
    rgb = panel * (1 + 0.25 * bright) + 0.03 * tint
    rgb = torch.where(p[:, 2:] < 0.12, rgb * 0.35, rgb)
    normal_in = -F.normalize(torch.cat([p[:, :2], torch.zeros_like(p[:, 2:])], -1), dim=-1)  # (N, 3)
    return rgb * (0.5 + 0.5 * _lambert(normal_in, cfg))[:, None]  # walls also get light bounced off the floor


def _ceiling_texture(p: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Light grey with faint noise (lit indirectly). p: (N, 3) ceiling points -> rgb (N, 3)."""
    grey = torch.tensor([0.62, 0.62, 0.60], dtype=p.dtype, device=p.device)
    return grey * (1 + 0.06 * _smooth_noise(p[:, :2] / 2, gen))[:, None]


def _cast_box(o: torch.Tensor, d: torch.Tensor, cfg: SceneConfig):
    """The distractor box standing on the floor. o, d: (..., 3). Returns t (...) (+inf on a miss), rgb (..., 3)."""
    cy, sy = math.cos(cfg.distractor_yaw), math.sin(cfg.distractor_yaw)
    R_world_box = torch.tensor([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]], dtype=d.dtype, device=d.device)
    half = torch.tensor(cfg.distractor_size_m, dtype=d.dtype, device=d.device) / 2
    center = torch.tensor([*cfg.distractor_xy_m, float(half[2])], dtype=d.dtype, device=d.device)
    t, normal = ray_box_intersect(o, d, center, R_world_box, half)
    albedo = torch.tensor(cfg.distractor_colour, dtype=d.dtype, device=d.device)
    return t, (albedo * _lambert(normal, cfg)[..., None]).clamp(0, 1)
