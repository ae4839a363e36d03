"""Command-line overrides of config dataclasses (``torchtrack.checks.with_overrides``)."""

from __future__ import annotations

import dataclasses
from typing import Optional

import pytest

from torchtrack.background import BackgroundConfig
from torchtrack.checks import InputError, with_overrides
from torchtrack.occupancy import HullConfig


@dataclasses.dataclass(frozen=True)
class _Example:
    ratio: float = 0.5
    count: int = 3
    flag: bool = False
    name: str = "x"
    limit: float | None = None
    when: Optional[int] = None  # noqa: UP007 (the older spelling of the same type)
    span: tuple[float, float] = (0.0, 1.0)


def test_overrides_parse_each_field_as_its_declared_type():
    got = with_overrides(_Example(), ["ratio=2", "count=7", "flag=true", "name=shape"], "--opt")
    assert got == _Example(ratio=2.0, count=7, flag=True, name="shape") and isinstance(got.ratio, float)
    assert with_overrides(_Example(flag=True), ["flag=0"], "--opt").flag is False
    assert with_overrides(_Example(), [], "--opt") == _Example()
    hull = with_overrides(HullConfig(), ["t_low=3", "footprint_early_out=false"], "--hull")
    assert (hull.t_low, hull.footprint_early_out) == (3.0, False)
    assert with_overrides(_Example(), ["limit=0.9"], "--opt").limit == 0.9  # an optional field: its type or None
    assert with_overrides(_Example(limit=0.9), ["limit=none"], "--opt").limit is None
    assert with_overrides(_Example(), ["when=2"], "--opt").when == 2  # Optional[int]: the same


@pytest.mark.parametrize("items, match", [(["ratio"], "FIELD=VALUE"), (["nope=1"], "FIELD=VALUE"),
                                          (["count=2.5"], "count='2.5' is not a int"),
                                          (["flag=yes"], "flag='yes' is not a bool"),
                                          (["limit=lots"], "limit='lots' is not a float"),
                                          (["span=1"], "'span' .* cannot be set")])
def test_bad_overrides_name_the_option_and_field(items, match):
    with pytest.raises(InputError, match=match) as info:
        with_overrides(_Example(), items, "--opt")
    assert "--opt" in str(info.value)


def test_overrides_go_through_the_config_checks():
    with pytest.raises(InputError, match="shadow_min_ratio"):
        with_overrides(BackgroundConfig(), ["shadow_min_ratio=1.5"], "--background")
