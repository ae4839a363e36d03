"""TRC reader on real files."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import shared_data
from torchtrack.checks import InputError
from torchtrack.io.trc import read_trc, y_up_to_world


def test_pose2sim_reference():
    trc = read_trc(shared_data("pose2sim_demo", "reference_3d", "S00_P00_T01_BalancingTrial_0-100.trc"))
    assert trc.positions.shape == (100, 21, 3) and trc.units == "m" and trc.rate_hz == 60
    assert trc.marker_names[:3] == ["RHip", "RKnee", "RAnkle"]
    # first value of the first data row, as written in the file
    assert trc.positions[0, 0, 0] == pytest.approx(-0.06497214796810755, abs=0)
    world = y_up_to_world(trc.positions_m())
    head, ankle = trc.marker_names.index("Head"), trc.marker_names.index("RAnkle")
    assert (world[:, head, 2] > world[:, ankle, 2] + 1.0).all()  # Z is up after the conversion


def test_cmu_marker_trc_in_mm():
    trc = read_trc(shared_data("mocap", "btk", "trc", "T.trc"))
    assert trc.units == "mm" and trc.positions.shape[1] == 41
    assert 1.0 < np.nanmax(trc.positions_m()) < 2.0


def test_rows_of_different_lengths_warn_and_pad():
    with pytest.warns(UserWarning, match="NumMarkers = 66"):
        trc = read_trc(shared_data("mocap", "btk", "trc", "Gait.trc"))
    assert trc.positions.shape[0] == 487 and np.isnan(trc.positions).any()
    assert trc.marker_names[0] == "R.Shoulder"


def test_bad_files(tmp_path):
    p = tmp_path / "x.trc"
    p.write_text("hello\n")
    with pytest.raises(InputError, match="not a TRC file"):
        read_trc(p)
    p.write_text("PathFileType\t4\nDataRate\tNumMarkers\tUnits\n60\t1\tm\nFrame#\tTime\tA\n\tX1\tY1\tZ1\n1\t0.0\t1\tx\t3\n")
    with pytest.raises(InputError, match="line 6"):
        read_trc(p)
    with pytest.raises(InputError, match="not found"):
        read_trc(tmp_path / "missing.trc")
