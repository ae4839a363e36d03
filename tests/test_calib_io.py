"""Calibration files: every real file loads, native TOML and EasyMocap YAML round trips, the Qualisys
convention against Pose2Sim's conversion of the same rig, the ``calib`` CLI, and bad files."""

from __future__ import annotations

import tomllib

import cv2
import numpy as np
import pytest
import torch
from conftest import shared_data

import torchtrack.cli
from torchtrack.cameras import CameraRig, load_calibration, save_calibration
from torchtrack.cameras.calib_formats import read_qualisys_qca, write_easymocap_yaml
from torchtrack.cameras.calib_io import detect_format, read_native_toml
from torchtrack.checks import InputError

QCA = ("pose2sim_demo", "calibration", "Calib.qca.txt")
P2S_TOML = ("pose2sim_demo", "calibration", "Calib_qualisys_pose2sim.toml")
ALL_FILES = [  # (path parts, format, number of cameras)
    (("calibrations", "anipose", "7cam-allen-mouse_calibration.toml"), "native", 7),
    (("calibrations", "anipose", "12cam-allen-mouse_calibration.toml"), "native", 12),
    (("calibrations", "anipose", "calib_motobs_7cam.toml"), "native", 7),
    (("calibrations", "caliscope", "4_cam_recording_camera_array.toml"), "caliscope", 4),
    (("calibrations", "caliscope", "post_optimization_camera_array.toml"), "caliscope", 4),
    (QCA, "qualisys", 4),
    (P2S_TOML, "native", 4),
]
_ids = [p[0][-1] for p in ALL_FILES]


def _assert_same_rig(a: CameraRig, b: CameraRig, r_atol: float = 0.0) -> None:
    assert a.names == b.names and a.fisheye == b.fisheye
    assert torch.equal(a.image_size_wh, b.image_size_wh)
    for key in ("K", "dist", "t_cam_world"):
        assert getattr(a, key).dtype == getattr(b, key).dtype
        assert torch.equal(getattr(a, key), getattr(b, key)), key
    torch.testing.assert_close(a.R_cam_world, b.R_cam_world, rtol=0, atol=r_atol)


@pytest.fixture
def cli(monkeypatch, capsys):
    """``torchtrack.cli.main`` with only the calib sub-command registered (other stages' CLIs are built in
    parallel and may not import yet); returns (exit code, stdout, stderr)."""
    monkeypatch.setattr(torchtrack.cli, "COMMAND_MODULES", ("torchtrack.cameras.cli",))

    def run(*argv):
        code = torchtrack.cli.main([str(a) for a in argv])
        out = capsys.readouterr()
        return code, out.out, out.err
    return run


# ---------------------------------------------------------------------------------------------- real files
@pytest.mark.parametrize("parts, fmt, n", ALL_FILES, ids=_ids)
def test_every_real_file_loads(parts, fmt, n):
    path = shared_data(*parts)
    assert detect_format(path) == fmt
    rig = load_calibration(path)
    assert len(rig) == n and rig.K.dtype == torch.float32 and rig.image_size_wh.dtype == torch.int64
    assert len(set(rig.names)) == n


@pytest.mark.parametrize("parts", [p for p, f, _ in ALL_FILES if f == "native"], ids=lambda p: p[-1])
def test_native_values_match_the_file(parts):
    """Against the raw TOML with an independent Rodrigues (OpenCV)."""
    path = shared_data(*parts)
    rig = load_calibration(path, dtype=torch.float64)
    tables = [t for k, t in tomllib.loads(path.read_text()).items() if k != "metadata"]
    for i, t in enumerate(tables):
        assert rig.names[i] == t["name"]
        assert rig.image_size_wh[i].tolist() == [int(s) for s in t["size"]]
        assert rig.K[i].tolist() == t["matrix"]
        assert rig.dist[i, :len(t["distortions"])].tolist() == t["distortions"]
        assert rig.t_cam_world[i].tolist() == t["translation"]
        R_cv = cv2.Rodrigues(np.array(t["rotation"]))[0]
        np.testing.assert_allclose(rig.R_cam_world[i].numpy(), R_cv, rtol=0, atol=1e-12)


def test_caliscope_values_match_the_file():
    path = shared_data("calibrations", "caliscope", "4_cam_recording_camera_array.toml")
    rig = load_calibration(path, dtype=torch.float64)
    cams = tomllib.loads(path.read_text())["cameras"]
    assert rig.names == [f"port_{k}" for k in cams]
    for i, t in enumerate(cams.values()):
        assert rig.R_cam_world[i].tolist() == t["rotation"] and rig.t_cam_world[i].tolist() == t["translation"]
        assert rig.dist[i].tolist() == t["distortions"] and rig.image_size_wh[i].tolist() == t["size"]


def test_anipose_units_are_kept():
    """The mouse rigs are calibrated in mm: loaded as-is (centres ~1 m away, i.e. ~1000 units)."""
    rig = load_calibration(shared_data("calibrations", "anipose", "7cam-allen-mouse_calibration.toml"))
    assert rig.centers().norm(dim=-1).max() > 500


# --------------------------------------------------------------------------------------- Qualisys vs Pose2Sim
def _volume_points() -> torch.Tensor:
    """A grid over the capture volume: x, y in [-2, 1] m (the subject stands near x = -1.4), z in [0, 2] m."""
    axes = [torch.linspace(-2, 1, 16, dtype=torch.float64), torch.linspace(-1.5, 1.5, 16, dtype=torch.float64),
            torch.linspace(0, 2, 11, dtype=torch.float64)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def test_qualisys_convention_matches_pose2sim_toml():
    """R = diag(1,-1,-1) M, t = -R C (m), K / 64: the same rig as Pose2Sim's TOML; the only difference is
    Pose2Sim's extra division of the distortion coefficients by 64."""
    qca = load_calibration(shared_data(*QCA), dtype=torch.float64)
    p2s = load_calibration(shared_data(*P2S_TOML), dtype=torch.float64)
    assert qca.names == ["cam01", "cam02", "cam03", "cam04"] and p2s.names == ["cam_01", "cam_02", "cam_03", "cam_04"]
    assert torch.equal(qca.image_size_wh, p2s.image_size_wh)
    torch.testing.assert_close(qca.K, p2s.K, rtol=0, atol=1e-9)
    torch.testing.assert_close(qca.R_cam_world, p2s.R_cam_world, rtol=0, atol=1e-9)
    torch.testing.assert_close(qca.t_cam_world, p2s.t_cam_world, rtol=0, atol=1e-9)
    torch.testing.assert_close(qca.dist / 64, p2s.dist, rtol=0, atol=1e-12)

    pts = _volume_points()
    qca_p2s = read_qualisys_qca(shared_data(*QCA), dtype=torch.float64, distortion_scale=1 / 64)
    uv_q, valid_q = qca_p2s.project(pts)
    uv_t, valid_t = p2s.project(pts)
    both = valid_q & valid_t
    assert both.float().mean() > 0.5
    assert (uv_q - uv_t).norm(dim=-1)[both].max() < 0.5  # measured: ~1e-11 px

    # With the coefficients as written (the default), projections differ by the distortion alone: a few px
    # towards the image borders (measured: up to ~7 px in this volume, ~2.6 px on the subject).
    uv_raw, valid_raw = qca.project(pts)
    diff = (uv_raw - uv_t).norm(dim=-1)[valid_raw & valid_t]
    assert 0.5 < diff.max() < 10


# -------------------------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("parts, fmt, n", ALL_FILES, ids=_ids)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_native_round_trip_is_exact(parts, fmt, n, dtype, tmp_path):
    """read(write(rig)): names, sizes, K, dist, t bit-exact in the rig's dtype. R is stored as a Rodrigues
    vector (the format): within 1e-15 for float64 rigs; for float32 rigs within one float32 ulp (a float32 R
    is the rounding of a rotation, not itself one, so vector -> matrix -> float32 may land 1 ulp away)."""
    rig = load_calibration(shared_data(*parts), dtype=dtype)
    out = tmp_path / "calibration.toml"
    save_calibration(rig, out)
    back = read_native_toml(out, dtype=dtype)
    _assert_same_rig(rig, back, r_atol=1e-15 if dtype == torch.float64 else 6e-8)
    assert [p.name for p in tmp_path.iterdir()] == ["calibration.toml"]  # no temporary files left


def test_native_rotation_vectors_survive_a_round_trip(tmp_path):
    src = shared_data("calibrations", "anipose", "12cam-allen-mouse_calibration.toml")
    save_calibration(load_calibration(src, dtype=torch.float64), tmp_path / "c.toml")
    a = [t for k, t in tomllib.loads(src.read_text()).items() if k != "metadata"]
    b = list(tomllib.loads((tmp_path / "c.toml").read_text()).values())
    for ta, tb in zip(a, b):
        np.testing.assert_allclose(tb["rotation"], ta["rotation"], rtol=0, atol=1e-12)
        assert tb["matrix"] == ta["matrix"] and tb["translation"] == ta["translation"]


def test_fisheye_round_trip(tmp_path):
    K = torch.tensor([[[400.0, 0, 639.5], [0, 400.0, 479.5], [0, 0, 1]]] * 2, dtype=torch.float64)
    R = torch.from_numpy(np.stack([cv2.Rodrigues(np.array(v))[0] for v in ([0.1, 2.0, 0.3], [3.1, 0.0, 0.1])]))
    rig = CameraRig(["fish eye", "metadata"], K, R, torch.tensor([[0.1, 0.2, 3.0], [0.0, 0.0, 2.0]]).double(),
                    torch.tensor([[1280, 960]] * 2), torch.tensor([[0.02, -0.005, 0.001, -0.0002, 0.0]] * 2).double(),
                    [True, False])
    save_calibration(rig, tmp_path / "f.toml")
    _assert_same_rig(rig, load_calibration(tmp_path / "f.toml", dtype=torch.float64), r_atol=1e-15)
    text = (tmp_path / "f.toml").read_text()
    assert "fisheye = true" in text and 'name = "fish eye"' in text and "[metadata]" not in text


def test_easymocap_round_trip(tmp_path):
    rig = load_calibration(shared_data("calibrations", "caliscope", "post_optimization_camera_array.toml"),
                           dtype=torch.float64)
    intri, extri = write_easymocap_yaml(rig, tmp_path / "em")
    assert intri.name == "intri.yml" and extri.name == "extri.yml"
    for path in (tmp_path / "em", intri, extri):  # folder or either file
        assert detect_format(path) == "easymocap"
        _assert_same_rig(rig, load_calibration(path, dtype=torch.float64), r_atol=1e-15)


EASYMOCAP_INTRI = """%YAML:1.0\r
---\r
names:\r
  - "01"\r
  - "02"\r
K_01: !!opencv-matrix\r
  rows: 3\r
  cols: 3\r
  dt: d\r
  data: [1000.5, 0.0, 639.5, 0.0, 1001.25, 359.5, 0.0, 0.0, 1.0]\r
dist_01: !!opencv-matrix\r
  rows: 1\r
  cols: 5\r
  dt: d\r
  data: [-0.1, 0.01, 0.001, -0.002, 0.0]\r
K_02: !!opencv-matrix\r
  rows: 3\r
  cols: 3\r
  dt: d\r
  data: [800.0, 0.0, 319.5, 0.0, 800.0, 239.5, 0.0, 0.0, 1.0]\r
D_02: !!opencv-matrix\r
  rows: 4\r
  cols: 1\r
  dt: d\r
  data: [0.05, 0.0, 0.0, 0.0]\r
H_02: 480\r
W_02: 640\r
"""
EASYMOCAP_EXTRI = """%YAML:1.0\r
---\r
names:\r
  - "01"\r
  - "02"\r
R_01: !!opencv-matrix\r
  rows: 3\r
  cols: 1\r
  dt: d\r
  data: [0.1, -0.2, 0.3]\r
T_01: !!opencv-matrix\r
  rows: 3\r
  cols: 1\r
  dt: d\r
  data: [0.5, 0.25, 3.0]\r
Rot_02: !!opencv-matrix\r
  rows: 3\r
  cols: 3\r
  dt: d\r
  data: [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\r
T_02: !!opencv-matrix\r
  rows: 3\r
  cols: 1\r
  dt: d\r
  data: [0.0, 0.0, 2.0]\r
"""


def test_easymocap_files_as_easymocap_writes_them(tmp_path, caplog):
    """EasyMocap's own layout: %YAML:1.0, CRLF, quoted names, R_ Rodrigues or Rot_ matrix, dist_ or D_,
    W_/H_ optional (estimated from the principal point, with a warning)."""
    (tmp_path / "intri.yml").write_bytes(EASYMOCAP_INTRI.encode())
    (tmp_path / "extri.yml").write_bytes(EASYMOCAP_EXTRI.encode())
    rig = load_calibration(tmp_path, dtype=torch.float64)
    assert rig.names == ["01", "02"]
    assert rig.image_size_wh.tolist() == [[1280, 720], [640, 480]]
    assert "no W_/H_" in caplog.text
    assert rig.K[0, 1, 1].item() == 1001.25 and rig.dist.tolist()[1] == [0.05, 0, 0, 0, 0]
    np.testing.assert_allclose(rig.R_cam_world[0].numpy(), cv2.Rodrigues(np.array([0.1, -0.2, 0.3]))[0], atol=1e-15)
    assert rig.R_cam_world[1].tolist() == [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    assert rig.t_cam_world.tolist() == [[0.5, 0.25, 3.0], [0, 0, 2.0]]


# ---------------------------------------------------------------------------------------------------- CLI
def test_cli_convert_and_show(cli, tmp_path):
    src = shared_data("calibrations", "anipose", "7cam-allen-mouse_calibration.toml")
    code, out, _ = cli("calib", "convert", src, tmp_path / "m.toml", "--translation-scale", "0.001")
    assert code == 0 and "7 cameras" in out
    mm = load_calibration(src, dtype=torch.float64)
    m = load_calibration(tmp_path / "m.toml", dtype=torch.float64)
    torch.testing.assert_close(m.t_cam_world, mm.t_cam_world * 0.001, rtol=1e-15, atol=0)
    torch.testing.assert_close(m.centers(), mm.centers() * 0.001, rtol=1e-12, atol=1e-15)
    assert torch.equal(m.K, mm.K)

    code, _, _ = cli("calib", "convert", shared_data(*QCA), tmp_path / "q.toml")
    assert code == 0 and read_native_toml(tmp_path / "q.toml").names == ["cam01", "cam02", "cam03", "cam04"]
    code, _, _ = cli("calib", "convert", tmp_path / "q.toml", tmp_path / "em")
    assert code == 0 and (tmp_path / "em" / "intri.yml").is_file()
    _assert_same_rig(load_calibration(tmp_path / "q.toml", torch.float64),
                     load_calibration(tmp_path / "em", torch.float64), r_atol=1e-15)

    code, out, _ = cli("calib", "show", shared_data(*QCA))
    assert code == 0 and "qualisys" in out and "cam04" in out and "1088x1920" in out


def test_cli_bad_input_exit_code(cli, tmp_path):
    code, _, err = cli("calib", "convert", tmp_path / "missing.toml", tmp_path / "out.toml")
    assert code == 2 and "missing.toml" in err
    src = shared_data("calibrations", "anipose", "7cam-allen-mouse_calibration.toml")
    code, _, err = cli("calib", "convert", src, tmp_path / "out.toml", "--translation-scale", "-1")
    assert code == 2 and "translation-scale" in err
    assert not (tmp_path / "out.toml").exists()


def test_a_rig_in_millimetres_is_refused_for_tracking_and_converted_on_request(tmp_path, cli, caplog):
    """A 3.5 m ring calibrated in mm (centres 3500 "m" away): loaded as written with a warning, refused by a
    sequence folder with the conversion named, and brought back to metres by `calib convert --translation-scale`."""
    from torchtrack.io.sequence import SequenceFolder
    from torchtrack.synth.sequence import RigConfig, make_ring_rig

    rig = make_ring_rig(RigConfig(num_cameras=4))
    mm = CameraRig(rig.names, rig.K, rig.R_cam_world, rig.t_cam_world * 1000, rig.image_size_wh, rig.dist,
                   rig.fisheye)
    seq = tmp_path / "seq"
    seq.mkdir()
    save_calibration(mm, seq / "calibration.toml")
    with caplog.at_level("WARNING"):
        assert torch.equal(load_calibration(seq / "calibration.toml", torch.float64).t_cam_world, mm.t_cam_world)
    assert "the translations look like millimetres" in caplog.text and "--translation-scale 0.001" in caplog.text
    with pytest.raises(InputError, match=r"calibration.toml: camera 'cam\d' is [\d,]+ units from the world origin.*"
                                         r"--translation-scale 0.001"):
        SequenceFolder(seq)
    code, _, _ = cli("calib", "convert", seq / "calibration.toml", tmp_path / "m.toml", "--translation-scale",
                     "0.001")
    assert code == 0
    torch.testing.assert_close(load_calibration(tmp_path / "m.toml", torch.float64).centers(), rig.centers(),
                               rtol=0, atol=1e-9)


def test_convert_names_the_formats_it_knows(cli, tmp_path):
    text = tmp_path / "cameras.txt"
    text.write_text("these are my cameras\nfour of them, in a ring\n")
    code, _, err = cli("calib", "convert", text, tmp_path / "out.toml")
    assert code == 2 and "cameras.txt: not a calibration format torchtrack reads; it knows" in err
    for fmt in ("Pose2Sim TOML", "caliscope", "Qualisys", "EasyMocap"):
        assert fmt in err
    assert not (tmp_path / "out.toml").exists()


# ---------------------------------------------------------------------------------------------- bad files
def _replace(parts, old, new, count=1):
    def make(tmp_path):
        src = shared_data(*parts)
        text = src.read_text()
        assert old in text, f"fixture out of date: {old!r} not in {src.name}"
        out = tmp_path / src.name
        out.write_text(text.replace(old, new, count))
        return out
    return make


ANIPOSE = ("calibrations", "anipose", "7cam-allen-mouse_calibration.toml")
CALISCOPE = ("calibrations", "caliscope", "4_cam_recording_camera_array.toml")
BAD_FILES = {  # name: (make the file, expected fragments of the message: camera and field)
    "missing_matrix": (_replace(ANIPOSE, 'matrix = [ [ 1935.9928441823383, 0.0, 719.5,], [ 0.0, 1935.9928441823383, '
                                         '539.5,], [ 0.0, 0.0, 1.0,],]\n', ""), ["camera 'cam091'", "'matrix'", "missing"]),
    "matrix_2x3": (_replace(ANIPOSE, "[ 0.0, 0.0, 1.0,],]", "]", 1), ["camera 'cam088'", "'matrix'", "(3, 3)"]),
    "rotation_text": (_replace(ANIPOSE, "rotation = [ -0.22567280935134637,", 'rotation = [ "x",'),
                      ["camera 'cam091'", "'rotation'", "numbers"]),
    "translation_nan": (_replace(ANIPOSE, "translation = [ 117.3672986155046,", "translation = [ nan,"),
                        ["camera 'cam091'", "'translation'", "finite"]),
    "negative_size": (_replace(ANIPOSE, "size = [ 1440, 1080,]", "size = [ -1440, 1080,]"),
                      ["camera 'cam088'", "'size'", "positive"]),
    "zero_focal": (_replace(ANIPOSE, "[ [ 1852.4059883563652, 0.0", "[ [ 0.0, 0.0"),
                   ["camera 'cam088'", "'matrix'", "focal"]),
    "six_distortions": (_replace(ANIPOSE, "distortions = [ -0.03617269969805811, 0.0,",
                                 "distortions = [ -0.03617269969805811, 0.0, 0.0,"), ["camera 'cam088'", "'distortions'"]),
    "fisheye_not_bool": (_replace(ANIPOSE, 'name = "cam088"', 'name = "cam088"\nfisheye = "no"'),
                         ["camera 'cam088'", "'fisheye'"]),
    "toml_syntax": (_replace(ANIPOSE, "size = [ 1440, 1080,]", "size = [ 1440, 1080,", 1), ["not valid TOML"]),
    "caliscope_not_rotation": (_replace(CALISCOPE, "[[0.028454458274723926,", "[[1.028454458274723926,"),
                               ["camera 'port_0'", "'rotation'", "not a rotation"]),
    "caliscope_missing_translation": (_replace(CALISCOPE, "translation = [0.00043375420342479525, "
                                               "-0.0019919458836723174, 0.0025865337259615363]\n", ""),
                                      ["camera 'port_1'", "'translation'", "missing"]),
    "qca_missing_attribute": (_replace(QCA, 'focalLengthU="107118.695313" ', ""),
                              ["camera 'cam02'", "'intrinsic.focalLengthU'", "missing"]),
    "qca_not_a_number": (_replace(QCA, 'r22="-0.24310718522469382"', 'r22="abc"'),
                         ["camera 'cam04'", "'transform.r22'", "not a number"]),
    "qca_not_rotation": (_replace(QCA, 'r33="0.3825762057979294"', 'r33="0.9825762057979294"'),
                         ["camera 'cam01'", "'transform.r11..r33'", "not a rotation"]),
    "qca_broken_xml": (_replace(QCA, "</cameras>", "</camera>"), ["not valid XML"]),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_bad_files_name_file_camera_field(case, tmp_path, cli):
    make, fragments = BAD_FILES[case]
    path = make(tmp_path)
    with pytest.raises(InputError) as info:
        load_calibration(path)
    message = str(info.value)
    for fragment in [str(path)] + fragments:
        assert fragment in message, f"{fragment!r} not in {message!r}"
    code, _, err = cli("calib", "convert", path, tmp_path / "out.toml")
    assert code == 2 and str(path) in err and "Traceback" not in err
    assert not (tmp_path / "out.toml").exists()


@pytest.mark.parametrize("content", ["", "# only a comment\n[metadata]\nadjusted = true\n"])
def test_empty_files(tmp_path, content, cli):
    path = tmp_path / "calibration.toml"
    path.write_text(content)
    with pytest.raises(InputError, match="no cameras"):
        load_calibration(path)
    assert cli("calib", "show", path)[0] == 2


def test_bad_easymocap_files(tmp_path):
    (tmp_path / "intri.yml").write_bytes(EASYMOCAP_INTRI.encode())
    (tmp_path / "extri.yml").write_bytes(EASYMOCAP_EXTRI.replace("T_02:", "X_02:").encode())
    with pytest.raises(InputError, match=r"extri.yml: camera '02': field 'T_02': missing"):
        load_calibration(tmp_path / "intri.yml")
    (tmp_path / "extri.yml").write_text("names: [a\n  ::: broken")
    with pytest.raises(InputError, match="extri.yml: not a readable OpenCV YAML"):
        load_calibration(tmp_path)
    (tmp_path / "extri.yml").unlink()
    with pytest.raises(InputError, match="missing extri.yml"):
        load_calibration(tmp_path)

