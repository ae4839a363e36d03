"""Where configs are found: a path as given, a bare name in configs/, and the built-in files whatever the working
directory holds."""

import pytest

from torchtrack import resources
from torchtrack.checks import InputError
from torchtrack.resources import builtin_config, config_path


def test_a_bare_name_in_the_working_directory_wins_over_the_built_in_one_but_not_for_builtin_config(
        tmp_path, monkeypatch):
    (tmp_path / "blobs.yaml").write_text("blobs: []\n")
    monkeypatch.chdir(tmp_path)
    assert config_path("blobs.yaml").resolve() == (tmp_path / "blobs.yaml").resolve()
    assert builtin_config("blobs.yaml") == resources.CONFIG_DIR / "blobs.yaml"
    assert config_path("markerless.yaml") == resources.CONFIG_DIR / "markerless.yaml"  # none here: configs/'s


def test_missing_configs_name_where_they_were_looked_for(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match=r"config file not found: nope\.yaml \(nor .*configs/nope\.yaml; "):
        config_path("nope.yaml")
    with pytest.raises(InputError, match=r"config file not found: sub/blobs\.yaml$"):
        config_path("sub/blobs.yaml")  # a path is not looked for in configs/, even where the name is there
    with pytest.raises(InputError, match=r"built-in config not found: .*configs/nope\.yaml \(torchtrack is meant"):
        builtin_config("nope.yaml")
