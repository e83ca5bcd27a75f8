"""`simulate --raw-out`'s writer: the point cloud goes beside the raw samples, so the import has what RF-LSCM needs."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from rflscm.cli.simulate import RawCloud
from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.data.ingest import import_raw, load_spec
from rflscm.errors import ConfigError
from rflscm.sim.raw_writer import CLOUD_FORMATS, write_raw


@pytest.mark.parametrize(("how", "name"), [("same", "point_cloud.ply"), ("laz", "point_cloud.laz"), ("none", None)])
def test_raw_out_writes_the_point_cloud_and_the_import_takes_it(tmp_path: Path, how: str, name: str | None) -> None:
    source = load_scenario(tiny_scenario(tmp_path / "sim"))
    info = write_raw(source, tmp_path / "raw", samples_per_beam=3, point_cloud=how)
    spec = yaml.safe_load((tmp_path / "raw" / "import.yaml").read_text())
    assert spec.get("point_cloud") == name and info["cloud_points"] == (0 if name is None else 3)
    import_raw(load_spec(tmp_path / "raw" / "import.yaml", {}), tmp_path / "imported")
    got = load_scenario(tmp_path / "imported")
    if name is None:
        assert got.point_cloud is None and got.meta.point_cloud is None
    else:
        assert got.meta.point_cloud == name and got.point_cloud == source.point_cloud  # LAZ: mm steps, exact here


def test_raw_cloud_choices_are_the_writers() -> None:
    assert sorted(c.value for c in RawCloud) == sorted(CLOUD_FORMATS)
    with pytest.raises(ConfigError, match="raw point cloud format must be one of"):
        write_raw(None, Path("unused"), point_cloud="xyz")  # type: ignore[arg-type]
