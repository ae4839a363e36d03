"""C3D reading (torchtrack.io.c3d) and C3D captures as synthetic motions (torchtrack.synth.c3d_motion)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ezc3d = pytest.importorskip("ezc3d")

from torchtrack.checks import InputError  # noqa: E402
from torchtrack.io.c3d import read_c3d, strip_prefix  # noqa: E402

MOCAP = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "mocap"
needs_mocap = pytest.mark.skipif(not MOCAP.is_dir(), reason="../shared/data/mocap is not there")


def _write_c3d(path: Path, labels: list[str], xyz_mm: np.ndarray, rate: float = 100.0) -> None:
    """A C3D file of ``xyz_mm (T, M, 3)`` in millimetres, written by ezc3d (an independent writer)."""
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [rate]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(labels)
    c["parameters"]["POINT"]["UNITS"]["value"] = ["mm"]
    pts = np.ones((4, len(labels), xyz_mm.shape[0]))
    pts[:3] = xyz_mm.transpose(2, 1, 0)
    c["data"]["points"] = pts
    c.write(str(path))


def test_strip_prefix():
    assert strip_prefix("Male:LFWT") == "LFWT" and strip_prefix("LFWT") == "LFWT"
    assert strip_prefix("a:b:RKNE ") == "RKNE"


def test_y_up_file_in_millimetres_is_read_z_up_in_metres(tmp_path):
    # a standing subject in a Y-up lab (x forward, y up, z right): head markers 1.6 m up, ankles at 0.08 m
    labels = ["LFHD", "RFHD", "LANK", "RANK", "LTOE"]
    yup = np.array([[100.0, 1600.0, -80.0], [100.0, 1600.0, 80.0], [0.0, 80.0, -100.0], [0.0, 80.0, 100.0],
                    [150.0, 30.0, -100.0]])
    frames = np.stack([yup + [10.0 * t, 0.0, 0.0] for t in range(5)])  # (5, 5, 3)
    _write_c3d(tmp_path / "yup.c3d", labels, frames)
    c = read_c3d(tmp_path / "yup.c3d")
    assert c.labels == labels and c.rate_hz == pytest.approx(100.0)
    # Y up -> Z up by the cyclic turn (x, y, z) -> (z, x, y): a proper rotation, heights kept
    expect = frames[..., [2, 0, 1]] * 1e-3
    np.testing.assert_allclose(c.positions, expect, atol=1e-6)


def test_missing_samples_are_nan(tmp_path):
    frames = np.tile(np.array([[0.0, 0.0, 1500.0], [0.0, 0.0, 50.0]]), (3, 1, 1))
    frames[1, 0] = 0.0  # a (0, 0, 0) gap, as many writers mark one
    _write_c3d(tmp_path / "gap.c3d", ["C7", "LANK"], frames)
    c = read_c3d(tmp_path / "gap.c3d")
    assert np.isnan(c.positions[1, 0]).all() and np.isfinite(c.positions[[0, 2]]).all()


@needs_mocap
@pytest.mark.parametrize("name", ["Dance.c3d", "golfswing.c3d"])
def test_malformed_c3d_names_the_file(name):
    with pytest.raises(InputError, match=name):
        read_c3d(MOCAP / "btk" / "c3d" / name)


def test_not_a_file_names_it(tmp_path):
    with pytest.raises(InputError, match="nothing.c3d"):
        read_c3d(tmp_path / "nothing.c3d")
    (tmp_path / "text.c3d").write_text("not a c3d file")
    with pytest.raises(InputError, match="text.c3d"):
        read_c3d(tmp_path / "text.c3d")


@needs_mocap
def test_cmu_capture_is_read_in_metres_z_up():
    c = read_c3d(MOCAP / "cmu" / "85_02.c3d")
    assert len(c.labels) == 41 and "LFWT" in c.labels and not any(":" in n for n in c.labels)
    head = c.positions[:, [c.index(n) for n in ("LFHD", "RFHD", "LBHD", "RBHD")]].mean(1)
    ankle = c.positions[:, [c.index("LANK"), c.index("RANK")]].mean(1)
    rise = np.median(head[:, 2] - ankle[:, 2])
    assert 1.2 < rise < 1.8  # a person's ankle-to-head height, in metres, along +Z


@needs_mocap
def test_joint_centres_against_plug_in_gait_model_outputs():
    """The hips from the pelvis markers (Bell's regression) against Vicon's own pelvis origin (between its hip
    centres, from Davis' regression): the two regressions agree within a few centimetres."""
    from torchtrack.synth.c3d_motion import _bell_hips

    c = read_c3d(MOCAP / "btk" / "c3d" / "PiG_Motion-FlatFoot-Full.c3d")
    P = lambda n: c.positions[:, c.index(n)]  # noqa: E731
    left, right = _bell_hips(P("LASI"), P("RASI"), P("LPSI"), P("RPSI"))
    gap = np.linalg.norm(0.5 * (left + right) - P("PELO"), axis=-1)
    assert np.nanmedian(gap) < 0.04
    width = np.nanmedian(np.linalg.norm(left - right, axis=-1))
    assert 0.12 < width < 0.22  # an adult's hip centres


@needs_mocap
@pytest.mark.parametrize("name", ["cmu/85_02.c3d", "btk/c3d/PiG_Motion-FlatFoot-Full.c3d"])
def test_c3d_captures_retarget_onto_the_skeleton(name):
    from torchtrack.skeleton import Skeleton
    from torchtrack.synth.c3d_motion import retarget_c3d

    r = retarget_c3d(MOCAP / name, Skeleton.from_urdf(), fps=30.0, duration_s=1.0)
    assert r.angles.shape[0] == 30
    assert 1.45 < r.skeleton.height() < 2.0
    assert float(r.residual_m.mean()) < 0.03  # our joints within 3 cm of the capture's centres on average


@needs_mocap
def test_c3d_without_a_full_body_is_refused_naming_what_is_missing():
    from torchtrack.synth.c3d_motion import joint_centres

    with pytest.raises(InputError, match="Gait.c3d.*joint centres"):
        joint_centres(read_c3d(MOCAP / "btk" / "c3d" / "Gait.c3d"))
