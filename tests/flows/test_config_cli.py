import pytest
from pydantic import ValidationError

from flows.cli import build_parser
from tasks.config import CampusConfig


def test_yaml_paths_are_relative_to_the_config_and_overrides_apply(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("inputs:\n  mesh: [mesh]\n  points: [mls/a.laz]\nwork_dir: work\n")
    cfg = CampusConfig.from_yaml(p, {"tiling.tile_size_m": 50, "partition.patch_size_m": [1, 1, 1]})
    assert cfg.inputs.mesh == [str(tmp_path / "mesh")] and cfg.work_dir == str(tmp_path / "work")
    assert cfg.tiling.tile_size_m == 50 and cfg.partition.patch_size_m == (1, 1, 1)
    assert type(cfg.partition).model_fields["patch_size_m"].default == (2.3, 1.0, 0.7)  # the paper's cuboid


def test_bad_config_is_rejected(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("tiling:\n  tile_sise_m: 50\n")  # typo: unknown fields are errors, not ignored
    with pytest.raises(ValidationError):
        CampusConfig.from_yaml(p)
    with pytest.raises(ValidationError):
        CampusConfig.model_validate({"partition": {"patch_size_m": [0, 1, 1]}})


def test_cli_parses_the_documented_commands():
    ap = build_parser()
    a = ap.parse_args(["run", "c.yaml", "--dask-address", "tcp://h:8786", "--set", "tiling.tile_size_m=50"])
    assert a.dask_address == "tcp://h:8786" and a.set == ["tiling.tile_size_m=50"]
    assert ap.parse_args(["synth", "--preset", "demo", "--seed", "3", "--out", "x"]).seed == 3
