"""Write complete synthetic sequence folders (docs/formats.md) from a motion.

A sequence: a ring rig (``calibration.toml``), empty-scene ``background/`` frames, the rendered
``video/<cam>.mp4`` (or PNG frames), ground truth ``gt.npz`` in the poses schema (landmarks and all 22
kinematic joints, state vectors, plus the blob ellipsoids per frame as extra keys) and ``meta.toml``.
The folder appears atomically when everything is written.
"""

from __future__ import annotations

import copy
import hashlib
import logging
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from torchtrack.blobs import BlobModel
from torchtrack.cameras import CameraRig, save_calibration
from torchtrack.checks import InputError
from torchtrack.io.atomic import atomic_dir
from torchtrack.io.poses import Poses, save_poses
from torchtrack.resources import builtin_config
from torchtrack.skeleton import Skeleton
from torchtrack.synth.markers import MarkerStyle, marker_names, marker_positions, visible_centroids
from torchtrack.synth.motion import MOTIONS, on_the_floor, path_position, procedural_motion, walks_path
from torchtrack.synth.retarget import RETARGET_REVISION
from torchtrack.synth.scene import SceneConfig, SceneRenderer

log = logging.getLogger(__name__)

#: The walk on a path (:func:`~torchtrack.synth.motion.walks_path`) in meta.toml's ``[synth]`` table, so that a
#: sequence kept from before it (the circle walk carried along the path, its feet sliding) goes stale.
PATH_WALK_REVISION = 2


@dataclass(frozen=True)
class RigConfig:
    """A ring of cameras around the capture volume, all looking at ``target_m``.

    Attributes:
        num_cameras: cameras evenly spread on the circle (the first on +X).
        width, height: image size in pixels (even numbers, for video).
        radius_m: circle radius; height_m: camera height above the floor.
        hfov_deg: horizontal field of view.
        k1: radial distortion of every camera (OpenCV k1), a mild barrel by default.
        target_m: the point every camera looks at.
        overhead: one more camera (the last) straight above ``target_m`` looking down, at ``overhead_height_m``
            with a horizontal field of view of ``overhead_hfov_deg``, its image x along world +X.
    """

    num_cameras: int = 8
    width: int = 640
    height: int = 480
    radius_m: float = 3.5
    height_m: float = 2.2
    hfov_deg: float = 62.0
    k1: float = -0.04
    target_m: tuple[float, float, float] = (0.0, 0.0, 0.95)
    overhead: bool = False
    overhead_height_m: float = 3.6
    overhead_hfov_deg: float = 90.0


def make_ring_rig(cfg: RigConfig = RigConfig(), dtype: torch.dtype = torch.float64) -> CameraRig:
    """A :class:`CameraRig` of ``cfg.num_cameras`` cameras named ``cam0..``, OpenCV convention, Z up world."""
    if cfg.num_cameras < 1 or cfg.width < 16 or cfg.height < 16:
        raise InputError(f"rig: need >= 1 camera and images of >= 16 px, got {cfg}")
    C = cfg.num_cameras
    az = torch.arange(C, dtype=dtype) * (2 * math.pi / C)  # (C,) the ring
    centres = torch.stack([cfg.radius_m * az.cos(), cfg.radius_m * az.sin(),
                           torch.full_like(az, cfg.height_m)], dim=1)  # (C, 3)
    forward = torch.tensor(cfg.target_m, dtype=dtype) - centres
    forward = forward / forward.norm(dim=1, keepdim=True)  # camera z
    up = torch.tensor([0.0, 0.0, 1.0], dtype=dtype).expand_as(forward)
    right = torch.cross(forward, up, dim=1)
    right = right / right.norm(dim=1, keepdim=True)  # camera x
    down = torch.cross(forward, right, dim=1)  # camera y
    R_cam_world = torch.stack([right, down, forward], dim=1)  # rows: camera axes in world, (C, 3, 3)
    f = 0.5 * cfg.width / math.tan(math.radians(cfg.hfov_deg) / 2)
    focal = [f] * C
    if cfg.overhead:
        if not cfg.target_m[2] < cfg.overhead_height_m:
            raise InputError(f"rig: the overhead camera ({cfg.overhead_height_m} m) must be above the target "
                             f"{cfg.target_m}")
        top = torch.tensor([[cfg.target_m[0], cfg.target_m[1], cfg.overhead_height_m]], dtype=dtype)
        down_view = torch.tensor([[[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]], dtype=dtype)
        centres, R_cam_world = torch.cat([centres, top]), torch.cat([R_cam_world, down_view])
        focal.append(0.5 * cfg.width / math.tan(math.radians(cfg.overhead_hfov_deg) / 2))
        C += 1
    t_cam_world = -(R_cam_world @ centres[..., None])[..., 0]
    K = torch.tensor([[[fc, 0, (cfg.width - 1) / 2], [0, fc, (cfg.height - 1) / 2], [0, 0, 1]] for fc in focal],
                     dtype=dtype)
    dist = torch.zeros(C, 5, dtype=dtype)
    dist[:, 0] = cfg.k1
    size = torch.tensor([[cfg.width, cfg.height]] * C, dtype=torch.int64)
    return CameraRig([f"cam{i}" for i in range(C)], K, R_cam_world, t_cam_world, size, dist=dist)


@dataclass(frozen=True)
class BodyConfig:
    """The rendered subject's body beyond its height (the defaults: the template of configs/blobs.yaml).

    Attributes:
        bone_scale: ``(bone, factor)`` pairs: those bones' lengths times the factor, after the skeleton is
            scaled to the subject's height (the height then follows from the bones).
        girth: every blob's two cross semi-axes times this (a slimmer or a stouter body).
        colours: ``(blob, (r, g, b))`` pairs replacing those blobs' colours (clothing, skin, hair), RGB in [0, 1].
    """

    bone_scale: tuple[tuple[str, float], ...] = ()
    girth: float = 1.0
    colours: tuple[tuple[str, tuple[float, float, float]], ...] = ()

    def __post_init__(self) -> None:
        if not 0.3 <= self.girth <= 3.0:
            raise InputError(f"BodyConfig.girth must be in [0.3, 3], got {self.girth}")
        for name, rgb in self.colours:
            if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
                raise InputError(f"BodyConfig.colours: {name!r} needs an RGB triple in [0, 1], got {rgb}")

    def apply(self, skel: Skeleton, blobs: BlobModel) -> BlobModel:
        """``blobs`` with this body's girth (:meth:`BlobModel.widened`) and colours (``skel``: for the bone names in
        messages)."""
        blobs = blobs.widened(self.girth)
        for name, rgb in self.colours:
            if name not in blobs.names:
                raise InputError(f"BodyConfig.colours: unknown blob {name!r}; blobs: {list(blobs.names)}")
            blobs.colour[blobs.names.index(name)] = torch.tensor(rgb, dtype=blobs.colour.dtype)
        return blobs

    def skeleton(self, skel: Skeleton) -> Skeleton:
        """``skel`` with the bones scaled by ``bone_scale``."""
        if not self.bone_scale:
            return skel
        length = dict(zip(skel.bone_names, (float(v) for v in skel.bone_lengths)))
        unknown = [b for b, _ in self.bone_scale if b not in length]
        if unknown:
            raise InputError(f"BodyConfig.bone_scale: unknown bones {unknown}; bones: {list(skel.bone_names)}")
        return skel.with_bone_lengths({b: length[b] * float(f) for b, f in self.bone_scale})


@dataclass(frozen=True)
class SynthConfig:
    """What `torchtrack synth` renders.

    Attributes:
        motion: a procedural motion (walk, turn, arm_raise, squat, kick) or a path to a BVH file.
        duration_s: seconds of motion after the starfish start (BVH: at most this much of the file).
        starfish_s: seconds of starfish pose at the start.
        fps: frame rate of the sequence (a BVH file is resampled to it).
        subject_height_m: subject height (BVH: measured from the file instead).
        background_frames: empty-scene frames written to background/.
        video_format: "mp4" or "png".
        rig, scene: camera ring and scene options (noise, illumination change, shadow, distractor).
        body: the subject's proportions, girth and colours beyond the template's.
        starfish_arms, starfish_legs: the starfish's arm and leg abduction (rad), its style.
        path: ``(time_s, x, y)`` waypoints (m), eased between waypoints (smoothstep), held before the first and
            after the last; times from the sequence's start, starfish included. The walk walks it, facing the way
            it goes, stopping at each waypoint and turning where it pauses (its starfish stands where the path is
            when the starfish ends); any other motion is carried over the floor by this offset from where the
            motion puts it. Empty: no path.
        markers: coloured balls on the body (:mod:`torchtrack.synth.markers`), for the colour marker detector:
            gt.npz then also holds their centres and visible pixels, and ``marker_labels.csv`` the labels of frame 0
            as a person would click them. None: no markers.
        seed: seeds the sensor noise.
    """

    motion: str = "walk"
    duration_s: float = 3.0
    starfish_s: float = 1.0
    fps: float = 30.0
    subject_height_m: float = 1.75
    background_frames: int = 20
    video_format: str = "mp4"
    rig: RigConfig = field(default_factory=RigConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    body: BodyConfig = field(default_factory=BodyConfig)
    starfish_arms: float = 1.25
    starfish_legs: float = 0.3
    path: tuple[tuple[float, float, float], ...] = ()
    markers: MarkerStyle | None = None
    seed: int = 0


def motion_angles(cfg: SynthConfig, skel: Skeleton) -> tuple[Skeleton, torch.Tensor]:
    """The skeleton (scaled to the subject, its bones as ``cfg.body`` says) and its (T, D) state vectors for
    ``cfg.motion`` on ``cfg.path`` (the walk walks it, other motions are carried along it)."""
    style = {"arm_abduction": cfg.starfish_arms, "leg_abduction": cfg.starfish_legs}
    if cfg.motion in MOTIONS:
        skel = cfg.body.skeleton(skel.scaled_to_height(cfg.subject_height_m))
        angles = procedural_motion(skel, cfg.motion, cfg.duration_s, cfg.fps, cfg.starfish_s, cfg.path, **style)
        if walks_path(cfg.motion, cfg.path):
            return skel, angles
    else:
        path = Path(cfg.motion)
        if path.suffix.lower() == ".bvh":
            from torchtrack.synth.bvh_motion import bvh_motion as capture_motion  # BVH import and retargeting
        elif path.suffix.lower() == ".c3d":
            from torchtrack.synth.c3d_motion import c3d_motion as capture_motion  # joint centres, retargeting
        else:
            raise InputError(f"motion {cfg.motion!r}: not one of {', '.join(MOTIONS)} and not a .bvh or .c3d file")
        skel, angles = capture_motion(path, skel, cfg.fps, cfg.duration_s, cfg.starfish_s, **style)
        if cfg.body.bone_scale:
            skel = cfg.body.skeleton(skel)
            angles = on_the_floor(skel, angles)
    return skel, carried_along(skel, angles, cfg.path, cfg.fps)


def carried_along(skel: Skeleton, angles: torch.Tensor, path: Sequence[Sequence[float]], fps: float
                  ) -> torch.Tensor:
    """(T, D) ``angles`` with the root moved over the floor by the offset of ``path`` (``(time_s, x, y)``
    waypoints, see :class:`SynthConfig`) at each frame's time ``t / fps``."""
    if not path:
        return angles
    t = torch.arange(angles.shape[0], dtype=torch.float64) / fps  # (T,)
    offset = path_position(path, t)[0]  # (T, 2)
    out = angles.clone()
    idx = skel.dof_index(["root_tx", "root_ty"])
    out[:, idx] += offset.to(out)
    return out


def _to_uint8(images: torch.Tensor) -> np.ndarray:
    """(C, 3, H, W) float in [0, 1] -> (C, H, W, 3) uint8."""
    return (images.clamp(0, 1) * 255 + 0.5).to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()


def _write_streams(folder: Path, names: list[str], frames: Path, fmt: str, fps: float) -> None:
    """Encode per-camera frames from the (T, C, H, W, 3) uint8 memmap ``frames`` into ``folder``."""
    from torchtrack.io.video import write_frames_png, write_video

    data = np.load(frames, mmap_mode="r")
    for c, name in enumerate(names):
        stream = (data[t, c] for t in range(data.shape[0]))
        if fmt == "mp4":
            write_video(folder / f"{name}.mp4", stream, fps)
        else:
            write_frames_png(folder / name, stream)


def write_sequence(cfg: SynthConfig, out: str | Path, device: torch.device | str | None = None,
                   progress: bool = True) -> Path:
    """Render ``cfg`` into the sequence folder ``out`` (replaced atomically when complete).

    Returns:
        ``out`` as a Path.
    """
    from tqdm import tqdm

    if cfg.video_format not in ("mp4", "png"):
        raise InputError(f"video_format must be 'mp4' or 'png', got {cfg.video_format!r}")
    device = torch.device(device or "cpu")
    out = Path(out)
    table = _synth_table(cfg)  # the body model's digest as of the start, before the body is read
    skel, angles = motion_angles(cfg, Skeleton.from_urdf())
    blobs = BlobModel.from_config(skel)
    blobs = cfg.body.apply(skel, blobs)
    rig = make_ring_rig(cfg.rig)
    # .float() and .to() convert a module in place: the renderer gets its own copy, the saved calibration
    # keeps the rig's float64 values
    renderer = SceneRenderer(copy.deepcopy(rig).float().to(device), cfg.scene).to(device)
    gen = torch.Generator(device=device).manual_seed(cfg.seed)
    T = angles.shape[0]
    with torch.no_grad():
        fk = skel(angles.double())
        centres, R = blobs.ellipsoids(fk.bone_frames)  # (T, K, 3), (T, K, 3, 3)
    semi = blobs.semi_axes.float().to(device)
    colours = blobs.colour.float().to(device)
    K = len(blobs.names)
    if cfg.markers is not None:  # the balls are M more ellipsoids of the body: parts K .. K + M - 1
        balls = marker_positions(list(blobs.names), centres, R, blobs.semi_axes.double(), cfg.markers.radius_m)
        M = balls.shape[1]
        centres = torch.cat([centres, balls], 1)
        R = torch.cat([R, torch.eye(3, dtype=R.dtype).expand(T, M, 3, 3)], 1)
        semi = torch.cat([semi, torch.full((M, 3), cfg.markers.radius_m, device=device)])
        colours = torch.cat([colours, torch.tensor(cfg.markers.colour, device=device).expand(M, 3)])
        marker_uv = np.full((T, rig.num_cameras, M, 2), np.nan, dtype=np.float32)
        marker_px = np.zeros((T, rig.num_cameras, M), dtype=np.int32)
    C, (W, H) = rig.num_cameras, (cfg.rig.width, cfg.rig.height)  # C: the ring and any overhead camera
    with atomic_dir(out) as tmp:
        save_calibration(rig, tmp / "calibration.toml")
        bg = np.lib.format.open_memmap(tmp / "bg.npy", mode="w+", dtype=np.uint8,
                                       shape=(cfg.background_frames, C, H, W, 3))
        for i in range(cfg.background_frames):
            bg[i] = _to_uint8(renderer.background(generator=gen))
        bg.flush()
        del bg
        frames = np.lib.format.open_memmap(tmp / "frames.npy", mode="w+", dtype=np.uint8, shape=(T, C, H, W, 3))
        for t in tqdm(range(T), desc=f"render {out.name}", unit="frame", disable=not progress):
            images, _, parts = renderer.render(centres[t].float().to(device), R[t].float().to(device), semi,
                                               colours, frame=t, num_frames=T, generator=gen)
            frames[t] = _to_uint8(images)
            if cfg.markers is not None:
                uv, count = visible_centroids(parts, K, M)
                marker_uv[t], marker_px[t] = uv.cpu().numpy(), count.cpu().numpy()
        frames.flush()
        del frames
        if cfg.background_frames:  # none: a recording without empty frames (the background estimated from video)
            _write_streams(tmp / "background", rig.names, tmp / "bg.npy", cfg.video_format, cfg.fps)
        _write_streams(tmp / "video", rig.names, tmp / "frames.npy", cfg.video_format, cfg.fps)
        (tmp / "bg.npy").unlink()
        (tmp / "frames.npy").unlink()
        poses = Poses(
            fps=cfg.fps, frame_index=np.arange(T), joint_names=list(skel.output_names),
            joints3d=fk.output_points.float().numpy(),
            dof_names=list(skel.dof_names), angles=angles.float().numpy(), valid=np.ones(T, dtype=bool),
            confidence=np.ones((T, len(skel.output_names)), dtype=np.float32),
            extra={"blob_names": np.asarray(blobs.names), "blob_centres": centres[:, :K].float().numpy(),
                   "blob_R_world": R[:, :K].float().numpy(), "blob_semi_axes": blobs.semi_axes.numpy(),
                   "bone_names": np.asarray(skel.bone_names), "bone_lengths": skel.bone_lengths.numpy()})
        if cfg.markers is not None:
            poses.extra.update(marker_names=np.asarray(marker_names()), markers3d=balls.float().numpy(),
                               marker_uv=marker_uv, marker_pixels=marker_px)
            write_marker_labels(tmp / "marker_labels.csv", rig.names, marker_names(), marker_uv[0], marker_px[0])
        save_poses(poses, tmp / "gt.npz")
        _write_meta(tmp / "meta.toml", cfg, skel, table)
        (tmp / "body.urdf").write_text(skel.urdf_text, encoding="utf-8")
    log.info("wrote %s: %d cameras, %d frames (%d background)", out, C, T, cfg.background_frames)
    return out


#: ``marker_labels.csv`` lists a marker in a view where at least this many of its pixels show, as a person labelling
#: the frame would click the balls they can see.
MIN_LABEL_PIXELS = 4


def write_marker_labels(path: Path, cameras: list[str], names: list[str], uv: np.ndarray, pixels: np.ndarray) -> None:
    """One frame's labels (``frame,camera,marker,u,v``; frame 0) of the markers seen well in each view: the whole
    pixel nearest the visible centroid ``uv (C, M, 2)``, where ``pixels (C, M)`` reaches MIN_LABEL_PIXELS."""
    rows = ["frame,camera,marker,u,v"]
    for c, cam in enumerate(cameras):
        for m, name in enumerate(names):
            if pixels[c, m] >= MIN_LABEL_PIXELS:
                rows.append(f"0,{cam},{name},{round(float(uv[c, m, 0]))},{round(float(uv[c, m, 1]))}")
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")


def body_model_digest() -> str:
    """The first 16 hex digits of the SHA-256 of the built-in body model the renderer draws (``configs/body.urdf``
    and ``configs/blobs.yaml``, whatever the working directory holds); meta.toml's ``synth.body_model`` records
    it."""
    from torchtrack.blobs.model import DEFAULT_BLOBS
    from torchtrack.skeleton.model import DEFAULT_URDF

    h = hashlib.sha256()
    for name in (DEFAULT_URDF, DEFAULT_BLOBS):
        h.update(builtin_config(name).read_bytes())
    return h.hexdigest()[:16]


def _plain(value):
    """A config value as TOML holds it: tuples as lists, None dropped from tables."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items() if v is not None}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return value


def _synth_table(cfg: SynthConfig) -> dict:
    """meta.toml's ``[synth]`` table for ``cfg``: what rendered the sequence."""
    return {"motion": cfg.motion, "duration_s": cfg.duration_s, "starfish_s": cfg.starfish_s, "seed": cfg.seed,
            "subject_height_m": cfg.subject_height_m, "background_frames": cfg.background_frames,
            "video_format": cfg.video_format, "body_model": body_model_digest(), "rig": _plain(asdict(cfg.rig)),
            "scene": _plain(asdict(cfg.scene)), "body": _plain(asdict(cfg.body)),
            "starfish": [cfg.starfish_arms, cfg.starfish_legs], "path": _plain(cfg.path),
            **({} if cfg.markers is None else {"markers": _plain(asdict(cfg.markers))}),
            **({} if cfg.motion in MOTIONS else {"retarget": RETARGET_REVISION}),
            **({"path_walk": PATH_WALK_REVISION} if walks_path(cfg.motion, cfg.path) else {})}


def is_current(out: str | Path, cfg: SynthConfig) -> bool:
    """Whether ``out`` is a complete sequence that :func:`write_sequence` rendered from ``cfg`` with today's body
    model (its meta.toml's frame rate and ``[synth]`` table equal what ``cfg`` would write now): scripts that keep
    rendered sequences between runs re-render the ones that are not. Not seen: changes to the code (renderer,
    procedural motions; the retargeting only as far as ``RETARGET_REVISION`` says) and to a capture file's
    contents under the same path."""
    import tomllib

    out = Path(out)
    if not (out / "gt.npz").is_file() or not (out / "meta.toml").is_file():
        return False
    try:
        meta = tomllib.loads((out / "meta.toml").read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError):
        return False
    return meta.get("fps") == cfg.fps and meta.get("synth") == _synth_table(cfg)


def _write_meta(path: Path, cfg: SynthConfig, skel: Skeleton, table: dict) -> None:
    import tomli_w

    doc = {"fps": cfg.fps, "subject_height_m": round(skel.height(), 4),
           "notes": "synthetic sequence rendered by torchtrack synth; body.urdf is the subject's skeleton",
           "synth": table}
    path.write_text(tomli_w.dumps(doc), encoding="utf-8")
