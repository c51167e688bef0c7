import pytest
from pydantic import ValidationError

from flows.cli import build_parser, main
from storage.errors import InputError
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
    with pytest.raises(InputError, match="unknown field 'tiling.tile_sise_m' .did you mean 'tile_size_m'"):
        CampusConfig.from_yaml(p)
    with pytest.raises(ValidationError):
        CampusConfig.model_validate({"partition": {"patch_size_m": [0, 1, 1]}})


@pytest.mark.parametrize("text, problem", [
    ("tilng: {tile_size_m: 5}\n", "unknown field 'tilng' (did you mean 'tiling'?)"),
    ("partition: {patch_size_m: [-1, 1, 1]}\n", "patch sizes must be positive"),
    ("tiling: {tile_size_m: -5}\n", "tiling.tile_size_m"),
    ("inputs: [a\n", "not valid YAML at line 2"),
    ("- just\n- a list\n", "must be a YAML mapping"),
    ("registration: {mode: sometimes}\n", "registration.mode"),
])
def test_config_errors_are_one_clear_line(tmp_path, capsys, text, problem):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    assert main(["run", str(p)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ms3d: error: ") and problem in err and str(p) in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_missing_config_and_folder_as_config(tmp_path, capsys):
    assert main(["run", str(tmp_path / "nope.yaml")]) == 2
    assert "config file not found" in capsys.readouterr().err
    assert main(["run", str(tmp_path)]) == 2
    assert "is a folder" in capsys.readouterr().err
    assert main(["status", str(tmp_path / "nowhere")]) == 2
    assert "no such work dir" in capsys.readouterr().err


def test_v1_registration_switch_still_reads(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("registration: {enabled: false}\n")
    assert CampusConfig.from_yaml(p).registration.mode == "off"


def test_cli_parses_the_documented_commands():
    ap = build_parser()
    a = ap.parse_args(["run", "c.yaml", "--dask-address", "tcp://h:8786", "--set", "tiling.tile_size_m=50"])
    assert a.dask_address == "tcp://h:8786" and a.set == ["tiling.tile_size_m=50"]
    assert ap.parse_args(["synth", "--preset", "demo", "--seed", "3", "--out", "x"]).seed == 3


def test_serve_and_view_errors_are_one_line(tmp_path, capsys):
    p = tmp_path / "c.yaml"
    p.write_text(f"work_dir: {tmp_path / 'w'}\n")
    assert main(["serve", str(p), "--cron", "every night please"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ms3d: error: ") and "not a cron expression" in err and len(err.strip().splitlines()) == 1
    (tmp_path / "w").mkdir()
    assert main(["view", str(tmp_path / "w")]) == 2
    assert "no output/tileset.json" in capsys.readouterr().err


def test_a_second_run_on_a_busy_work_dir_is_refused(tmp_path):
    from storage.workdir.housekeeping import work_dir_lock
    from storage.workdir.layout import WorkDir

    wd = WorkDir(tmp_path / "w")
    with work_dir_lock(wd), pytest.raises(InputError, match="in use by another ms3d run"):
        with work_dir_lock(wd):
            pass
