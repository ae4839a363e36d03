"""Shared test fixtures: the real data folder, devices, small synthetic walks."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = (REPO / ".." / "shared" / "data").resolve()

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def shared_data(*parts: str) -> Path:
    """Path of a file in ../shared/data; skips the test with a reason when it is absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real data not available: {p} (../shared/data is absent on this machine)")
    return p


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    return torch.device(request.param)


def small_walk(out: Path, *, duration_s: float, video_format: str, starfish_s: float = 0.2,
               background_frames: int = 4, size_wh: tuple[int, int] = (320, 240), noise: bool = True) -> Path:
    """A short synthetic 4-camera walk at 20 fps rendered into ``out`` (sequence folder with gt.npz)."""
    import dataclasses

    from torchtrack.synth.scene import SceneConfig
    from torchtrack.synth.sequence import RigConfig, SynthConfig, write_sequence

    scene = dataclasses.replace(SceneConfig(), noise_std=1 / 255) if noise else SceneConfig()
    cfg = SynthConfig(motion="walk", duration_s=duration_s, starfish_s=starfish_s, fps=20,
                      background_frames=background_frames, video_format=video_format,
                      rig=RigConfig(num_cameras=4, width=size_wh[0], height=size_wh[1]), scene=scene)
    return write_sequence(cfg, out, progress=False)


def voxelise(centres, R, semi, voxel=0.03):
    """Voxel centres of a 3D grid (cells aligned to the origin) inside any of the ellipsoids, and which ellipsoid
    (nearest in unit distance) each belongs to."""
    from torchtrack.occupancy.metrics import inside_ellipsoids

    reach = float(semi.max())
    lower = torch.floor((centres.amin(0) - reach) / voxel) * voxel
    upper = centres.amax(0) + reach
    axes = [torch.arange(float(lo) + voxel / 2, float(hi), voxel, dtype=torch.float64) for lo, hi in zip(lower, upper)]
    g = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = inside_ellipsoids(g, centres, R, semi)
    pts = g[inside]
    local = torch.einsum("nkj,kji->nki", pts[:, None] - centres[None], R) / semi[None]
    owner = (local ** 2).sum(-1).argmin(1)
    return pts, owner


def voxelised_observation(skel, blobs, angles, voxel=0.03, shift=(0.0, 0.0, 0.0), cameras=4):
    """The voxels of the body ``skel`` with ``blobs`` at ``angles (D,)``, each seen by every camera in its blob's
    colour (float32)."""
    from torchtrack.tracking.observation import VoxelObservation

    fk = skel.forward(angles[None].double())
    centres, R = blobs.ellipsoids(fk.bone_frames)
    pts, owner = voxelise(centres[0] + torch.tensor(shift, dtype=torch.float64), R[0], blobs.semi_axes.double(),
                           voxel)
    colour = blobs.colour.double()[owner]  # (N, 3) every view sees the blob's colour
    colours = colour[:, None, :].expand(-1, cameras, -1).clone()
    sizes = torch.full((pts.shape[0],), voxel, dtype=torch.float64)
    return VoxelObservation(pts.float(), sizes.float(), (sizes ** 3).float(), colours.float(),
                            torch.ones(cameras, dtype=torch.bool))


# ---------------------------------------------------------------------------------- ellipsoid bodies


def random_rotations(n: int, gen: torch.Generator) -> torch.Tensor:
    """(n, 3, 3) random rotations (QR of Gaussian matrices, sign-fixed)."""
    q, r = torch.linalg.qr(torch.randn(n, 3, 3, generator=gen, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r, dim1=1, dim2=2))[:, None, :]
    return q * torch.det(q)[:, None, None]


def small_body(dtype=torch.float64):
    """Six ellipsoids roughly shaped like a person standing at the origin: centres, R, semi-axes, colours."""
    gen = torch.Generator().manual_seed(3)
    centers = torch.tensor([[0, 0, 1.0], [0, 0, 1.35], [0, 0, 1.65], [0.05, 0.25, 1.2],
                            [0, -0.1, 0.5], [0.02, 0.12, 0.5]], dtype=torch.float64)
    semi = torch.tensor([[0.12, 0.18, 0.14], [0.13, 0.2, 0.16], [0.1, 0.09, 0.12], [0.05, 0.05, 0.25],
                         [0.07, 0.07, 0.4], [0.07, 0.07, 0.4]], dtype=torch.float64)
    R = random_rotations(6, gen)
    R[[4, 5]] = torch.eye(3, dtype=torch.float64)
    colours = torch.rand(6, 3, generator=gen, dtype=torch.float64) * 0.6 + 0.2
    return centers.to(dtype), R.to(dtype), semi.to(dtype), colours.to(dtype)


def quadric_matrix(c: np.ndarray, R: np.ndarray, a: np.ndarray) -> np.ndarray:
    """A with (p - c)^T A (p - c) <= 1 inside."""
    return R @ np.diag(1.0 / a**2) @ R.T


# ------------------------------------------------------------------------- tracking voxelised bodies


def landmarks_of(skel, angles):
    """The landmarks of ``skel`` at ``angles (D,)``."""
    return skel.forward(angles[None]).landmarks[0]


def track_voxelised(skel, motion, frames, tracker=None, edit=None):
    """Track voxelised ground truth of a subject 1.80 m tall (the tracker starts from the generic 1.75 m body):
    the tracker, the landmark errors of the valid frames (m) and the frames' results."""
    from torchtrack.blobs import BlobModel
    from torchtrack.synth.motion import procedural_motion
    from torchtrack.tracking.markerless import MarkerlessTracker

    subj = skel.scaled_to_height(1.80)
    blobs = BlobModel.from_config(subj)
    T = procedural_motion(subj, motion, frames / 30, 30, starfish_s=0.3)
    tracker = tracker or MarkerlessTracker(skel)
    errs, results = [], []
    for t in range(T.shape[0]):
        obs = voxelised_observation(subj, blobs, T[t])
        if edit is not None:
            obs = edit(t, obs)
        r = tracker.step(obs)
        results.append(r)
        if r.valid:
            errs.append(float((r.output_points[:16] - landmarks_of(subj, T[t])).norm(dim=-1).mean()))
    return tracker, np.array(errs), results


def search_turned_round(monkeypatch) -> None:
    """Force the start search's answers to face backwards (their states turned round), for the start race's tests."""
    import dataclasses

    import torchtrack.tracking.search as search
    from torchtrack.tracking.poses import turned_round

    found = search.search_pose
    monkeypatch.setattr(search, "search_pose", lambda obs, sk, *a, **k: dataclasses.replace(
        r := found(obs, sk, *a, **k), angles=turned_round(sk, r.angles)))


def apply_revised(out: list, late: list) -> None:
    """In place: a tracker's ``take_revised()`` results replace the last ``len(late)`` of the results ``out``."""
    for j, (res, _version) in enumerate(late):
        out[len(out) - len(late) + j] = res


def facing_pair_rig(k1: float = 0.0, W: int = 64, H: int = 64):
    """Two cameras of W x H pixels 4 m from the origin, looking at it horizontally from +y and from -x; the second
    with radial distortion ``k1``."""
    from torchtrack.cameras import CameraRig

    K = torch.tensor([[80.0, 0, (W - 1) / 2], [0, 80.0, (H - 1) / 2], [0, 0, 1]], dtype=torch.float64)
    Rs, ts = [], []
    for yaw in (math.pi / 2, math.pi):
        centre = torch.tensor([4 * math.cos(yaw), 4 * math.sin(yaw), 0.9], dtype=torch.float64)
        z = -centre / centre.norm()
        z[2] = 0.0
        z = z / z.norm()
        x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
        y = torch.linalg.cross(z, x)
        R = torch.stack([x, y, z])  # world -> camera rows
        Rs.append(R)
        ts.append(-R @ centre)
    return CameraRig(["a", "b"], K.expand(2, 3, 3).clone(), torch.stack(Rs), torch.stack(ts),
                     torch.tensor([[W, H], [W, H]]),
                     torch.tensor([[0.0] * 5, [k1, 0, 0, 0, 0]], dtype=torch.float64)).float()


def pose_at(skel, x: float, y: float = 0.0) -> torch.Tensor:
    """The rest pose with the root at (x, y)."""
    a = skel.rest_angles()
    a[skel.dof_names.index("root_tx")] = x
    a[skel.dof_names.index("root_ty")] = y
    return a


#: The real Pose2Sim demo's Qualisys rig (4 cameras) in ../shared/data, as its TOML.
DEMO_RIG = ("pose2sim_demo", "calibration", "Calib_qualisys_pose2sim.toml")


def demo_rig():
    """The real Pose2Sim demo's rig in float64; skips the test where ../shared/data is absent."""
    from torchtrack.cameras import load_calibration

    return load_calibration(shared_data(*DEMO_RIG), warn_units=False).double()


def stooped_observation(case, cameras):
    """A 1.6 m body stooped over (spine flexed, head bowed, knees bent, a hand at the chest, the other arm swung
    back; each joint near its value), at a heading, with its voxels and the silhouettes of its blobs on a ring of
    ``cameras`` (ground truth: clearance.body_masks): the observation, the template, the true landmarks, their
    indices among the skeleton's outputs, the true state and the subject's body."""
    from torchtrack.blobs import BlobModel
    from torchtrack.conventions import LANDMARKS
    from torchtrack.skeleton import Skeleton
    from torchtrack.synth.sequence import RigConfig, make_ring_rig
    from torchtrack.tracking.clearance import body_masks
    from torchtrack.tracking.voxels import ViewSilhouettes

    skel = Skeleton.from_urdf()
    names, idx = list(skel.dof_names), [list(skel.output_names).index(n) for n in LANDMARKS]
    gen = torch.Generator().manual_seed(case)
    truth = torch.zeros(skel.num_dofs, dtype=torch.float64)
    for dof, value in {"spine_flex": 0.5, "neck_flex": 0.95, "l_knee_flex": 0.7, "r_knee_flex": 0.9,
                       "l_hip_flex": 0.4, "r_hip_flex": 0.5, "r_shoulder_flex": 0.6, "r_elbow_flex": 2.1,
                       "l_shoulder_flex": -0.7, "l_elbow_flex": 0.3}.items():
        truth[names.index(dof)] = value + 0.1 * float(torch.randn(1, generator=gen))
    truth[names.index("root_rz")] = 0.5 + 2.0 * case
    truth = skel.clamp(truth[None])[0]
    subj = skel.scaled_to_height(1.6)
    blobs = BlobModel.from_config(subj)
    truth[names.index("root_tz")] -= float(subj.forward(truth[None]).output_points[0, :, 2].min())
    rig = make_ring_rig(RigConfig(num_cameras=cameras, width=320, height=240, radius_m=4.0)).float()
    fg = body_masks(rig, subj, truth[None], blobs=blobs)[0].float()
    obs = voxelised_observation(subj, blobs, truth, cameras=cameras)
    obs = dataclasses.replace(obs, silhouettes=ViewSilhouettes.from_evidence(2 * fg - 1, rig))
    return obs, skel, subj.forward(truth[None]).output_points[0, idx], idx, truth, subj


def carved_observation(subj, blobs, angles, cameras, silhouettes=False):
    """The visual hull of the body ``subj`` at ``angles`` on a ring of ``cameras``: the 3 cm voxels every view sees on
    the body's silhouette (clearance.body_masks carved by the occupancy's plain silhouette carving), each seen by
    every camera; with ``silhouettes``, the cameras' foreground (those silhouettes) kept as the observer keeps it."""
    from torchtrack.occupancy.grid import GridSpec, VoxelLookup
    from torchtrack.occupancy.silhouette import carve
    from torchtrack.synth.sequence import RigConfig, make_ring_rig
    from torchtrack.tracking.clearance import body_masks
    from torchtrack.tracking.voxels import ViewSilhouettes, VoxelObservation

    rig = make_ring_rig(RigConfig(num_cameras=cameras, width=320, height=240, radius_m=4.0)).float()
    masks = body_masks(rig, subj, angles[None], blobs=blobs) > 0.5  # (1, C, H, W)
    spec = GridSpec((-1.0, -1.0, 0.0), (1.0, 1.0, 2.0), 0.03)
    pts = spec.centres()[carve(masks, VoxelLookup(rig, spec), min_views=cameras)[0]]
    N = pts.shape[0]
    views = ViewSilhouettes.from_evidence(masks[0].float() * 2 - 1, rig) if silhouettes else None
    return VoxelObservation(pts, torch.full((N,), 0.03), torch.full((N,), 0.03 ** 3), torch.zeros(N, cameras, 3),
                            torch.ones(cameras, dtype=torch.bool), camera_centres=rig.centers().float(),
                            silhouettes=views)
