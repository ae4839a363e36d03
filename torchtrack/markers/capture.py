"""A simulated marker capture: a C3D file's real markers, with its subject's body as the occluder, placed in a
calibrated rig's capture area and seen through the simulated detector (:mod:`torchtrack.markers.simulate`).
``torchtrack synth markers`` writes it as a folder: ``calibration.toml``, ``markers2d.npz`` and ``gt.npz`` (the
retargeted body's joints and the 3D markers)."""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from torchtrack.blobs import BlobModel
from torchtrack.checks import InputError
from torchtrack.io.c3d import read_c3d
from torchtrack.io.markers2d import Markers2D
from torchtrack.io.poses import Poses
from torchtrack.markers.simulate import DetectorModel, marker_visibility, simulate_detections
from torchtrack.occupancy import capture_views, grid_from_rig
from torchtrack.skeleton import Skeleton
from torchtrack.synth.c3d_motion import c3d_resampled, retarget_c3d

__all__ = ["MarkerScene", "capture_centre", "marker_scene", "simulated_capture", "write_marker_capture"]

log = logging.getLogger(__name__)


def capture_centre(rig: nn.Module) -> torch.Tensor:
    """(2,) the middle of the floor area that every camera sees (or, where none is, half of them), in x and y."""
    for need in (rig.num_cameras, capture_views(rig.num_cameras)):
        try:
            spec = grid_from_rig(rig, 0.05, min_views=need)
        except InputError:
            continue
        return torch.tensor([0.5 * (spec.lower_m[i] + spec.upper_m[i]) for i in range(2)], dtype=torch.float64)
    raise InputError(f"no floor area is seen by {capture_views(rig.num_cameras)} of the rig's {rig.num_cameras} "
                     "cameras: nowhere to place the capture")


@dataclass(frozen=True)
class MarkerScene:
    """A C3D capture placed in a rig, before the detector: the markers' pinhole projections, which the body hides,
    and the truth. Detections under any detector and seed come from it (:meth:`detections`) without retargeting
    the capture again, the part that takes long (e.g. a sweep over the detector's settings, or many seeds)."""

    fps: float
    camera_names: list[str]
    image_size_wh: torch.Tensor  # (C, 2)
    uv: torch.Tensor  # (T, C, M, 2) the markers' projections, pixels
    visible: torch.Tensor  # (T, C, M) in the image and not behind the body
    skin_m: float  # the skin offset the visibility was computed with
    truth: Poses  # joints of the retargeted body, marker_names and markers3d

    def detections(self, model: DetectorModel = DetectorModel(), seed: int = 0) -> Markers2D:
        """The scene through the detector ``model`` (its ``skin_m`` must be the scene's), random draws from a
        ``torch.Generator`` seeded with ``seed``; ``extra``: ``true_index (T, C, M)`` and ``visible (T, C, M)``."""
        if model.skin_m != self.skin_m:
            raise InputError(f"the detector's skin_m {model.skin_m} is not the scene's {self.skin_m}: make the scene "
                             "again with it (marker_scene)")
        det = simulate_detections(self.uv, self.visible, self.image_size_wh, model,
                                  torch.Generator().manual_seed(int(seed)))
        T = self.visible.shape[0]
        log.info("%d frames, %d markers, %d cameras: %.1f %% of the markers seen, %.1f %% detected", T,
                 self.visible.shape[2], self.visible.shape[1], 100.0 * float(self.visible.double().mean()),
                 100.0 * float((det.true_index >= 0).double().mean()))
        return Markers2D(self.fps, np.arange(T), list(self.camera_names), list(self.truth.marker_names),
                         det.uv.float().numpy(),
                         extra={"true_index": det.true_index.numpy(), "visible": self.visible.numpy()})


def marker_scene(path: str | Path, rig: nn.Module, fps: float | None = None, duration_s: float | None = None,
                 skin_m: float = DetectorModel().skin_m) -> MarkerScene:
    """The markers of the C3D file ``path`` placed in ``rig``'s capture area, as :class:`MarkerScene`.

    The capture is resampled to ``fps`` (None: the file's rate) and cut to ``duration_s`` (None: all of it); its
    joint centres are retargeted onto our skeleton, whose blob ellipsoids (grown by ``skin_m``) hide the markers
    behind the body; the hips' path is centred over the rig's capture area (:func:`capture_centre`)."""
    c3d = read_c3d(path)
    fps = c3d.rate_hz if fps is None else float(fps)
    names, pos, frames, shift = c3d_resampled(c3d, fps, duration_s)
    ret = retarget_c3d(path, Skeleton.from_urdf(), fps, duration_s, positions=(names, pos))
    body = ret.skeleton
    blobs = BlobModel.from_config(body)
    rig = copy.deepcopy(rig).double()  # .double() converts in place: never the caller's rig
    place = capture_centre(rig)
    keep = c3d.markers()
    if not keep:
        raise InputError(f"{path}: no skin markers among its points (only a model's outputs)")
    labels = [c3d.labels[i] for i in keep]
    markers = torch.from_numpy(c3d.positions[frames][:, keep]).double()
    markers[..., :2] += place - torch.from_numpy(shift)
    with torch.no_grad():
        fk = body(ret.angles.double())
        centres, R = blobs.ellipsoids(fk.bone_frames)
    centres = centres + place.new_tensor([*place.tolist(), 0.0])
    joints = fk.output_points + place.new_tensor([*place.tolist(), 0.0])
    uv, visible = marker_visibility(markers, rig, centres, R, blobs.semi_axes.double(), skin_m)
    T = visible.shape[0]
    angles = ret.angles.clone()
    for i, n in enumerate(("root_tx", "root_ty")):  # the body placed with the markers
        angles[:, body.dof_names.index(n)] += float(place[i])
    truth = Poses(fps=fps, frame_index=np.arange(T), joint_names=list(body.output_names),
                  joints3d=joints.float().numpy(), dof_names=list(body.dof_names), angles=angles.float().numpy(),
                  valid=np.ones(T, dtype=bool), confidence=np.ones((T, len(body.output_names)), dtype=np.float32),
                  marker_names=labels, markers3d=markers.float().numpy())
    log.info("%s: placed in the rig", Path(path).name)
    return MarkerScene(fps, list(rig.names), rig.image_size_wh, uv, visible, float(skin_m), truth)


def simulated_capture(path: str | Path, rig: nn.Module, fps: float | None = None, duration_s: float | None = None,
                      model: DetectorModel = DetectorModel(), seed: int = 0) -> tuple[Markers2D, Poses]:
    """The markers of the C3D file ``path`` seen by ``rig`` through the detector ``model``: :func:`marker_scene`,
    then its :meth:`~MarkerScene.detections` with ``seed``.

    Returns:
        the detections (``extra``: ``true_index (T, C, M)`` and ``visible (T, C, M)``) and the truth as poses
        (joints of the retargeted body, ``marker_names`` and ``markers3d``).
    """
    scene = marker_scene(path, rig, fps, duration_s, model.skin_m)
    return scene.detections(model, seed), scene.truth


def write_marker_capture(folder: str | Path, rig: nn.Module, detections: Markers2D, truth: Poses) -> Path:
    """A simulated capture's folder, as ``torchtrack track`` reads it: ``calibration.toml``, ``markers2d.npz`` and
    the truth as ``gt.npz`` (each file written atomically). Returns the folder."""
    from torchtrack.cameras import save_calibration
    from torchtrack.io.markers2d import save_markers2d
    from torchtrack.io.poses import save_poses

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    save_calibration(rig, folder / "calibration.toml")
    save_markers2d(detections, folder / "markers2d.npz")
    save_poses(truth, folder / "gt.npz")
    return folder
