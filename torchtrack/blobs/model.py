"""Body appearance model: Gaussian blobs attached to bones (de Bem eq. 17-18, Caillette §4.1).

A blob is a solid ellipsoid rigidly attached to a bone: centre at ``offset`` along the bone, semi-axes
(along, depth, width) in an "aligned" frame whose first axis is the bone direction. For a pose, with the
bone's world transform (R_world_bone, P_bone):

    mu    = P_bone + R_world_bone @ (offset * d_bone)                      (eq. 17, d_bone unit bone direction)
    Sigma = R @ diag(sigma^2) @ R^T,  R = R_world_bone @ A_bone,  sigma = semi_axes / sqrt(5)     (eq. 18)

``A_bone`` maps the aligned frame to the bone's frame. sqrt(5) makes the Gaussian's covariance equal to that
of the uniform solid ellipsoid, which is what EM estimates from voxels.
"""

from __future__ import annotations

import copy

import math
from dataclasses import dataclass
from pathlib import Path

import torch
import yaml
from torch import nn

from torchtrack.checks import InputError, check_shape
from torchtrack.resources import builtin_config, config_path
from torchtrack.skeleton import Skeleton

DEFAULT_BLOBS = "blobs.yaml"
#: A uniform solid ellipsoid's covariance is diag(semi_axes^2 / 5) in its axes: its surface lies at this squared
#: Mahalanobis distance from its centre.
SURFACE_MAHALANOBIS2 = 5.0
_FIELDS = ("name", "bone", "offset", "along", "depth", "width", "colour")


@dataclass(frozen=True)
class BlobSpec:
    """One blob of the config file (see configs/blobs.yaml for the meaning of each field)."""

    name: str
    bone: str
    offset: float
    along: float
    depth: float
    width: float
    colour: tuple[float, float, float]


def load_blob_specs(path: str | Path | None = None) -> tuple[list[BlobSpec], float]:
    """Read a blob config: (specs, reference height in metres)."""
    p = builtin_config(DEFAULT_BLOBS) if path is None else config_path(path)
    try:
        doc = yaml.safe_load(p.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise InputError(f"{p}: not valid YAML ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("blobs"), list) or not doc["blobs"]:
        raise InputError(f"{p}: expected a mapping with a non-empty list 'blobs'")
    specs = []
    for i, b in enumerate(doc["blobs"]):
        where = f"{p}: blob {i} ({b.get('name', '?') if isinstance(b, dict) else repr(b)})"
        if not isinstance(b, dict) or any(k not in b for k in _FIELDS):
            missing = [k for k in _FIELDS if not isinstance(b, dict) or k not in b]
            raise InputError(f"{where}: missing fields {missing}")
        try:
            spec = BlobSpec(str(b["name"]), str(b["bone"]), float(b["offset"]), float(b["along"]),
                            float(b["depth"]), float(b["width"]), tuple(float(c) for c in b["colour"]))
        except (TypeError, ValueError) as exc:
            raise InputError(f"{where}: bad value ({exc})") from None
        if len(spec.colour) != 3 or not all(0.0 <= c <= 1.0 for c in spec.colour):
            raise InputError(f"{where}: colour must be 3 values in [0, 1], got {b['colour']}")
        if min(spec.along, spec.depth, spec.width) <= 0:
            raise InputError(f"{where}: along, depth and width must be positive")
        specs.append(spec)
    return specs, float(doc.get("reference_height_m", 1.75))


def _aligned_frames(dirs_local: torch.Tensor) -> torch.Tensor:
    """(nb, 3) unit bone directions -> (nb, 3, 3) rotations whose columns are (dir, depth axis, width axis).

    The width axis is the body's left (+Y of the bone frame) made orthogonal to the bone; for the bones of the
    body model, which lie in the sagittal plane at rest, this is exactly +Y and depth is front-back.
    """
    left = torch.tensor([0.0, 1.0, 0.0], dtype=dirs_local.dtype).expand_as(dirs_local)
    width = left - (left * dirs_local).sum(-1, keepdim=True) * dirs_local
    width = width / width.norm(dim=-1, keepdim=True)
    depth = torch.cross(width, dirs_local, dim=-1)
    return torch.stack([dirs_local, depth, width], dim=-1)


class BlobModel(nn.Module):
    """K blobs on the bones of a :class:`Skeleton`, as buffers.

    Attributes:
        names: (K,) blob names; ``bone_of_blob (K,)`` index into ``skeleton.bone_names``.
        offset_local: (K, 3) blob centre in its bone's frame (m).
        R_bone_blob: (K, 3, 3) blob axes (along, depth, width) in its bone's frame.
        semi_axes: (K, 3) ellipsoid semi-axes (m); ``sigma = semi_axes / sqrt(5)``.
        colour: (K, 3) RGB prior in [0, 1].
    """

    def __init__(self, skeleton: Skeleton, specs: list[BlobSpec], reference_height_m: float = 1.75) -> None:
        super().__init__()
        self.names = tuple(s.name for s in specs)
        bones = list(skeleton.bone_names)
        unknown = [s.bone for s in specs if s.bone not in bones]
        if unknown:
            raise InputError(f"blob bones {unknown} are not bones of the skeleton {bones}")
        bone_idx = torch.tensor([bones.index(s.bone) for s in specs])
        length = skeleton.bone_lengths.cpu()[bone_idx]  # (K,) built on the CPU, moved to the skeleton's device
        d = skeleton.bone_dirs_local.cpu()[bone_idx]  # (K, 3)
        scale = skeleton.height() / reference_height_m
        along = torch.tensor([s.along for s in specs]) * length
        cross = torch.tensor([[s.depth, s.width] for s in specs]) * scale
        self.register_buffer("bone_of_blob", bone_idx, persistent=False)
        self.register_buffer("offset_local", torch.tensor([s.offset for s in specs])[:, None] * length[:, None] * d,
                             persistent=False)
        self.register_buffer("R_bone_blob", _aligned_frames(d), persistent=False)
        self.register_buffer("semi_axes", torch.cat([along[:, None], cross], dim=1), persistent=False)
        self.register_buffer("colour", torch.tensor([s.colour for s in specs]), persistent=False)
        self.to(skeleton.lower.device)

    @classmethod
    def stack(cls, models: list[BlobModel]) -> BlobModel:
        """B subjects' blob models as one whose geometry buffers (``offset_local``, ``R_bone_blob``,
        ``semi_axes``) have a leading B: its :meth:`gaussians` of ``(B, nb, 4, 4)`` bone frames places body b's
        blobs on frames b (the lockstep tracker's subjects). The blobs' names, bones and colours must agree."""
        first = models[0]
        for m in models[1:]:
            if m.names != first.names or not torch.equal(m.bone_of_blob, first.bone_of_blob):
                raise InputError(f"BlobModel.stack: blob sets differ ({first.names} and {m.names})")
        out = copy.deepcopy(first)
        for name in ("offset_local", "R_bone_blob", "semi_axes"):
            setattr(out, name, torch.stack([getattr(m, name) for m in models]))
        return out

    @classmethod
    def from_config(cls, skeleton: Skeleton, path: str | Path | None = None) -> BlobModel:
        specs, ref = load_blob_specs(path)
        return cls(skeleton, specs, ref)

    @property
    def num_blobs(self) -> int:
        return len(self.names)

    def widened(self, girth: float) -> BlobModel:
        """A copy with every blob's two cross semi-axes times ``girth`` (a stouter body above 1, a slimmer one below;
        the lengths along the bones kept): the synthetic subjects' build and the tracker's fitted one."""
        out = copy.deepcopy(self)
        out.semi_axes[..., 1:] *= girth
        return out

    def ellipsoids(self, bone_frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World placement of every blob's ellipsoid.

        Args:
            bone_frames: (B, nb, 4, 4) bone-to-world transforms (``Skeleton.forward(...).bone_frames``).

        Returns:
            centres (B, K, 3) and R_world_blob (B, K, 3, 3) (columns: the along, depth, width axes).
        """
        check_shape(bone_frames, ("B", None, 4, 4), "bone_frames")
        T = bone_frames[:, self.bone_of_blob.to(bone_frames.device)]  # (B, K, 4, 4)
        R_wb, P_wb = T[..., :3, :3], T[..., :3, 3]
        centres = P_wb + torch.einsum("...kij,...kj->...ki", R_wb, self.offset_local.to(T))  # eq. 17
        R_world_blob = R_wb @ self.R_bone_blob.to(T)  # (B, K, 3, 3)
        return centres, R_world_blob

    def gaussians(self, bone_frames: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, nb, 4, 4) -> means (B, K, 3), covariances (B, K, 3, 3) (eq. 17-18)."""
        centres, R = self.ellipsoids(bone_frames)
        return centres, ellipsoid_covariance(R, self.semi_axes.to(R))


def ellipsoid_covariance(R: torch.Tensor, semi_axes: torch.Tensor) -> torch.Tensor:
    """The covariance of uniform solid ellipsoids (eq. 18): axes ``R (..., 3, 3)`` (columns), ``semi_axes (..., 3)``
    -> ``R diag(semi_axes^2 / SURFACE_MAHALANOBIS2) R^T (..., 3, 3)``."""
    var = (semi_axes / math.sqrt(SURFACE_MAHALANOBIS2)) ** 2
    return R @ torch.diag_embed(var) @ R.transpose(-1, -2)


def blob_volumes(blobs: BlobModel) -> torch.Tensor:
    """(K,) each blob's solid-ellipsoid volume (m^3), ``4/3 pi`` times the product of its semi-axes."""
    return (4.0 / 3.0) * math.pi * blobs.semi_axes.double().prod(-1)
