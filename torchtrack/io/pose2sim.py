"""The real Pose2Sim demo (../shared/data/pose2sim_demo) as a torchtrack sequence folder.

The demo's files are laid out Pose2Sim's way (``videos/cam01.mp4``, a calibration TOML whose cameras are
``cam_01``..): :func:`pose2sim_sequence` links them into the sequence-folder layout (docs/formats.md) without copying the videos,
and :func:`reference_keypoints` reads Pose2Sim's own 3D keypoints (BODY_25B names, TRC, Y up) in our world,
raw or filtered.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from torchtrack.checks import InputError
from torchtrack.io.trc import read_trc, y_up_to_world

CALIBRATION = "calibration/Calib_qualisys_pose2sim.toml"
REFERENCE = "reference_3d/S00_P00_T01_BalancingTrial_0-100.trc"
#: The same keypoints after Pose2Sim's own filtering step (a zero-phase Butterworth low-pass): its final output.
#: The raw triangulation jitters from frame to frame and has single-frame outliers (a toe off the foot in two
#: views; ``scripts/eval_pose2sim_occupancy.py --reference-noise``; docs/results.md, "The real Pose2Sim demo").
REFERENCE_FILTERED = "reference_3d/S00_P00_T01_BalancingTrial_0-100_filt_butterworth.trc"

#: Pose2Sim BODY_25B keypoints -> our output points (``Skeleton.output_names``), where the two define the same
#: point. BODY_25B's ``Head`` is the top of the head (0.29 m from its ``Neck`` in the demo; our template's
#: neck -> head_top is 0.27 m at the subject's height, neck -> head centre 0.15), so it is our ``head_top``; our
#: ``head`` landmark (the head centre) and ``spine`` (the thorax) have no BODY_25B counterpart.
LANDMARK_MAP: dict[str, tuple[str, ...]] = {
    "pelvis": ("RHip", "LHip"), "neck": ("Neck",), "head_top": ("Head",),
    "l_shoulder": ("LShoulder",), "l_elbow": ("LElbow",), "l_wrist": ("LWrist",),
    "r_shoulder": ("RShoulder",), "r_elbow": ("RElbow",), "r_wrist": ("RWrist",),
    "l_hip": ("LHip",), "l_knee": ("LKnee",), "l_ankle": ("LAnkle",),
    "r_hip": ("RHip",), "r_knee": ("RKnee",), "r_ankle": ("RAnkle",),
}


def pose2sim_sequence(demo: str | Path, out: str | Path) -> Path:
    """Make ``out`` a sequence folder of the demo: calibration.toml (a copy), video/<cam>.mp4 (symlinks)."""
    demo, out = Path(demo), Path(out)
    videos = sorted((demo / "videos").glob("cam*.mp4"))
    if not videos or not (demo / CALIBRATION).is_file():
        raise InputError(f"{demo}: not the Pose2Sim demo folder (needs videos/cam*.mp4 and {CALIBRATION})")
    (out / "video").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(demo / CALIBRATION, out / "calibration.toml")
    for v in videos:
        link = out / "video" / v.name
        if not link.exists():
            link.symlink_to(v.resolve())
    (out / "meta.toml").write_text("fps = 60.0\nnotes = \"Pose2Sim demo (BalancingTrial), linked\"\n")
    return out


def reference_keypoints(demo: str | Path, filtered: bool = False) -> tuple[list[str], np.ndarray]:
    """Pose2Sim's 3D keypoints: names (21,) and (T, 21, 3) world positions in metres (Z up); the raw
    triangulation (:data:`REFERENCE`) or, with ``filtered``, Pose2Sim's filtered output (:data:`REFERENCE_FILTERED`)."""
    trc = read_trc(Path(demo) / (REFERENCE_FILTERED if filtered else REFERENCE))
    return trc.marker_names, y_up_to_world(trc.positions_m())


def landmarks_from_keypoints(names: list[str], points: np.ndarray, known: tuple[str, ...] = ()
                             ) -> tuple[list[str], np.ndarray]:
    """Keypoints ``points (..., M, 3)`` named ``names`` as our output points: names in ``known`` (e.g.
    ``Skeleton.output_names``) as they are, BODY_25B names through :data:`LANDMARK_MAP` (a point made of several
    keypoints needs all of them); a subject prefix such as ``Male:`` is ignored. Returns the output names found
    (L,) and ``(..., L, 3)``."""
    bare = [n.split(":")[-1] for n in names]
    out_names, cols = [], []
    for i, n in enumerate(bare):
        if n in known and n not in out_names:
            out_names.append(n)
            cols.append(points[..., i, :])
    for ours, sources in LANDMARK_MAP.items():
        if ours not in out_names and all(s in bare for s in sources):
            out_names.append(ours)
            cols.append(np.mean([points[..., bare.index(s), :] for s in sources], axis=0))
    return out_names, (np.stack(cols, axis=-2) if cols else points[..., :0, :])


def reference_landmarks(demo: str | Path, filtered: bool = False) -> tuple[list[str], np.ndarray]:
    """The reference (:func:`reference_keypoints`) mapped onto our output points (:data:`LANDMARK_MAP`): names (L,),
    (T, L, 3)."""
    return landmarks_from_keypoints(*reference_keypoints(demo, filtered))
