"""Config: defaults, preset then overrides, the spellings accepted, one-line errors, the checkpoint round trip; the
budget a run says it ends with; every command's options on the command line."""

from __future__ import annotations

import logging
import pickle
import subprocess
import sys
from importlib import resources

import pytest
import yaml
from scenes import write_test_scene

from anisdf.config import Config, config_from_dict, load_config, preset_names, set_key
from anisdf.errors import AnisdfError


def _error(preset: str | None = None, overrides: list[str] | None = None) -> str:
    with pytest.raises(AnisdfError) as info:
        load_config(preset, overrides)
    msg = str(info.value)
    assert "\n" not in msg, msg
    return msg


def test_defaults_are_a_plain_config():
    cfg = load_config()
    assert type(cfg) is Config and type(cfg.geometry).__name__ == "GeometryConfig"
    assert cfg == Config() == load_config("default")
    assert cfg.preset == "default" and cfg.geometry.kind == "fused" and cfg.appearance.kind == "blend"
    assert cfg.train.samples_per_step == 2**18 and cfg.optim.betas == (0.9, 0.99)
    assert pickle.loads(pickle.dumps(cfg)) == cfg


def test_preset_then_overrides_in_order(tmp_path):
    cfg = load_config("cpu-quick")
    assert cfg.preset == "cpu-quick" and cfg.data.downscale == 2.0 and cfg.geometry.n_levels == 12
    assert cfg.appearance.asg_theta == 4 and cfg.geometry.kind == "fused"  # untouched keys keep their defaults
    cfg = load_config("cpu-quick", ["data.downscale=1", "geometry.n_levels=9", "geometry.n_levels=7"])
    assert cfg.data.downscale == 1.0 and isinstance(cfg.data.downscale, float)
    assert cfg.geometry.n_levels == 7  # the last override wins
    assert cfg.geometry.coarse_levels == 8  # from the preset
    path = tmp_path / "mine.yaml"
    path.write_text("geometry:\n  kind: single\nloss:\n  rgb: l1\n")
    cfg = load_config(str(path), ["loss.rgb=mse"])
    assert cfg.preset == "mine" and cfg.geometry.kind == "single" and cfg.loss.rgb == "mse"


@pytest.mark.parametrize("name", preset_names())
def test_every_preset_file_loads(name):
    files = [p.name for p in resources.files("anisdf").joinpath("presets").iterdir() if p.name.endswith(".yaml")]
    assert sorted(f[: -len(".yaml")] for f in files) == preset_names()
    text = resources.files("anisdf").joinpath("presets", f"{name}.yaml").read_text()
    cfg = load_config(name)
    assert cfg.preset == name and cfg != Config()
    for section, values in yaml.safe_load(text).items():
        for key, value in values.items():
            assert getattr(getattr(cfg, section), key) == value, f"{section}.{key}"


def test_choices_round_trip_as_plain_strings():
    cfg = load_config(None, ["data.background=random", "geometry.kind=single", "geometry.fusion=mean",
                             "geometry.normals=finite_difference", "geometry.encoding_backend=torch",
                             "appearance.kind=pe", "renderer.background_model=environment", "loss.rgb=mse+l1",
                             "optim.betas=(0.8, 0.95)"])
    d = cfg.to_dict()
    assert d["geometry"]["kind"] == "single" and type(d["geometry"]["kind"]) is str
    assert d["appearance"]["kind"] == "pe" and d["loss"]["rgb"] == "mse+l1" and d["optim"]["betas"] == (0.8, 0.95)
    assert config_from_dict(d) == cfg
    assert config_from_dict(yaml.safe_load(yaml.safe_dump(d))) == cfg  # through the run's config.yaml
    assert cfg.geometry.kind == "single" and cfg.geometry.kind != "fused"


@pytest.mark.parametrize("spelling", ["(0.8,0.95)", "( 0.8, 0.95 )", "[0.8, 0.95]"])
def test_a_tuple_field_reads_parentheses_and_lists(spelling):
    assert load_config(None, [f"optim.betas={spelling}"]).optim.betas == (0.8, 0.95)
    cfg = Config()
    set_key(cfg, "optim.betas", spelling)  # the resume path hands over the raw text
    assert cfg.optim.betas == (0.8, 0.95)


@pytest.mark.parametrize(("text", "value"), [("true", True), ("false", False), ("True", True), ("yes", True),
                                             ("off", False), ("1", True), ("0", False)])
def test_bool_strings(text, value):
    assert load_config(None, [f"train.amp={text}"]).train.amp is value
    cfg = Config()
    set_key(cfg, "train.amp", text)
    assert cfg.train.amp is value


@pytest.mark.parametrize(("text", "value"), [("1e3", 1000), ("2**14", 16384), ("2.0", 2), ("4096", 4096)])
def test_int_spellings(text, value):
    cfg = load_config(None, [f"train.samples_per_step={text}"])
    assert cfg.train.samples_per_step == value and type(cfg.train.samples_per_step) is int


def test_int_spellings_in_a_preset_file(tmp_path):
    path = tmp_path / "big.yaml"
    path.write_text("train:\n  samples_per_step: 2**19\n  max_rays: 1.6e4\n")
    cfg = load_config(str(path))
    assert cfg.train.samples_per_step == 2**19 and cfg.train.max_rays == 16000


def test_set_key_changes_one_value_in_place():
    cfg = load_config("cpu-quick")
    train = cfg.train
    set_key(cfg, "train.max_minutes", "5")
    set_key(cfg, "train.max_steps", "2e3")
    assert train.max_minutes == 5.0 and train.max_steps == 2000 and cfg.train is train
    assert cfg.geometry == load_config("cpu-quick").geometry
    with pytest.raises(AnisdfError, match="unknown config key 'train.bogus'"):
        set_key(cfg, "train.bogus", "1")
    with pytest.raises(AnisdfError, match="must be one of fused, single"):
        set_key(cfg, "geometry.kind", "double")
    assert cfg.geometry.kind == "fused"


def test_unknown_key():
    msg = _error(None, ["geometry.nope=1"])
    assert msg == "unknown config key 'geometry.nope'"  # no pointer to a --help-config that does not exist
    assert _error(None, ["nope.x=1"]) == "unknown config key 'nope'"
    assert "geometry.kind=" in _error(None, ["geometry=1"])  # a section is not a value


def test_value_that_cannot_be_converted_names_key_value_and_type():
    assert _error(None, ["geometry.n_levels=many"]) == "config key 'geometry.n_levels': cannot read 'many' as int"
    assert _error(None, ["geometry.n_levels=1.5"]) == "config key 'geometry.n_levels': cannot read 1.5 as int"
    assert _error(None, ["loss.eikonal=abc"]) == "config key 'loss.eikonal': cannot read 'abc' as float"
    assert _error(None, ["train.amp=maybe"]) == "config key 'train.amp': cannot read 'maybe' as bool"
    msg = _error(None, ["optim.betas=(0.9,0.99,0.999)"])
    assert msg == "config key 'optim.betas': cannot read [0.9, 0.99, 0.999] as tuple[float, float]"


def test_value_outside_the_choices_lists_them():
    msg = _error(None, ["appearance.kind=asg2"])
    assert msg == "config key 'appearance.kind' must be one of blend, pe, view, not 'asg2'"
    assert "mse, l1, mse+l1" in _error(None, ["loss.rgb=l2"])


def test_override_without_equals():
    assert _error(None, ["geometry.kind"]) == "override 'geometry.kind' is not of the form key=value"


def test_unknown_preset_lists_the_presets():
    msg = _error("nope")
    assert msg.startswith("unknown preset 'nope'") and all(name in msg for name in preset_names())
    assert "not found" in _error("/nonexistent/mine.yaml")


def test_bad_preset_files_name_the_preset(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("geometry:\n  kind: [single\n")
    assert "invalid YAML" in _error(str(bad))
    bad.write_text("- geometry\n")
    assert "expected a mapping" in _error(str(bad))
    bad.write_text("geometry:\n  kind: double\n")
    assert _error(str(bad)) == f"preset {bad}: config key 'geometry.kind' must be one of fused, single, not 'double'"
    bad.write_text("geometry:\n  bogus: 1\n")
    assert "unknown config key 'geometry.bogus'" in _error(str(bad))


def test_a_saved_config_with_a_bad_value_is_refused():
    d = Config().to_dict()
    d["loss"]["rgb"] = "l2"
    with pytest.raises(AnisdfError, match="config key 'loss.rgb' must be one of"):
        config_from_dict(d)


@pytest.mark.parametrize(("fmt", "masks", "kind"), [("nerf-synthetic", False, "object"), ("neus", False, "object"),
                                                    ("instant-ngp", True, "object"), ("llff", False, "unbounded"),
                                                    ("colmap", False, "unbounded")])
def test_auto_preset_follows_the_kind_of_data(tmp_path, fmt, masks, kind):
    """``--preset auto`` (train's default): objects (alpha or masks) get the NeRF-synthetic preset, opaque photos
    without masks the unbounded Mip-NeRF 360 one, reading its own images when there is no images_4 folder."""
    from anisdf.tasks.train import AUTO_PRESETS, auto_preset, data_kind

    write_test_scene(tmp_path, fmt, masks=masks)
    assert data_kind(tmp_path) == kind
    preset, extra = auto_preset(tmp_path)
    assert preset == AUTO_PRESETS[kind]
    cfg = load_config(preset, extra)
    assert cfg.data.images_dir == ""
    if kind == "unbounded":
        assert cfg.renderer.background_model == "nerf" and cfg.preset == "mipnerf360"
        (tmp_path / "images_4").mkdir()
        assert auto_preset(tmp_path) == ("mipnerf360", [])


def test_a_run_says_which_budget_ends_it(toy_scene, tmp_path, caplog):
    """``train.max_steps`` under a time budget is the schedule's length, not a step budget: the run says which
    budget ends it, and warns when that override reads like a step budget."""
    from test_training import TINY

    from anisdf.tasks.train import train

    with caplog.at_level(logging.INFO, logger="anisdf"):
        summary = train(toy_scene, tmp_path / "steps", preset="cpu-quick", overrides=TINY, max_steps=2,
                        progress=False)
    assert summary["step"] == 2 and "budget: 2 steps" in caplog.messages
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING and "budget" in r.getMessage()]
    caplog.clear()

    def stop_after_2_steps(trainer):  # train()'s setup: stop the 10-minute run after two steps
        def hook(tr, stats):
            if tr.state.step >= 2:
                raise KeyboardInterrupt

        trainer.step_hooks.append(hook)

    timed = [o for o in TINY if not o.startswith("train.max_minutes")]  # cpu-quick's 10 minutes stand
    with caplog.at_level(logging.INFO, logger="anisdf"):
        summary = train(toy_scene, tmp_path / "timed", preset="cpu-quick", overrides=[*timed, "train.max_steps=60"],
                        progress=False, setup=stop_after_2_steps)
    assert summary["status"] == "interrupted" and summary["step"] == 2
    assert "budget: 10 min (the schedule's 60 steps laid on it); --max-steps N for a step count" in caplog.messages
    (warning,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and "budget" in r.getMessage()]
    assert "train.max_steps=60 sets the length of the schedule" in warning and "not a step budget" in warning
    assert "--max-steps 60" in warning and "train.max_minutes=0" in warning


def test_every_command_has_a_help(capsys):
    from anisdf.cli import COMMANDS, command_module, main

    for name in COMMANDS:
        mod = command_module(name)
        assert mod.NAME == name and COMMANDS[name] and callable(mod.run), name
        with pytest.raises(SystemExit) as info:
            main([name, "--help"])
        assert info.value.code == 0 and capsys.readouterr().out.startswith(f"usage: anisdf {name} "), name
    with pytest.raises(SystemExit):
        main(["--help"])
    listing = capsys.readouterr().out
    assert [line.split()[0] for line in listing.split("COMMAND\n")[1].split("options:")[0].splitlines()
            if line.startswith("    ") and not line.startswith("     ")] == list(COMMANDS)
    done = subprocess.run([sys.executable, "-m", "anisdf", "--help"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "extract-mesh" in done.stdout


def test_options_come_from_the_task_dataclasses(capsys):
    """A command's options are its task's: the defaults the library uses are the command line's."""
    from anisdf.cli import main, parse
    from anisdf.orchestration.reproduce import ReproduceOptions
    from anisdf.tasks.evaluate import EvalOptions
    from anisdf.tasks.mesh import MeshOptions

    def parsed(argv):
        return parse(argv)[1]

    mesh = parsed(["extract-mesh", "RUN"])
    assert (mesh.resolution, mesh.format, mesh.remove_floaters) == (MeshOptions().resolution, "ply", False)
    ev = parsed(["eval", "RUN", "--remove-inner"])
    assert ev.remove_inner is True and ev.remove_floaters is None and ev.chamfer_points == EvalOptions().chamfer_points
    rep = parsed(["reproduce", "dtu", "--data", "D", "--out", "O", "--ray", "--seeds", "0,1", "a.b=1"])
    assert (rep.ray, rep.seeds, rep.overrides, rep.mesh_resolution) == ("local", "0,1", ["a.b=1"],
                                                                        ReproduceOptions().mesh_resolution)
    train = parsed(["train", "DATA", "--out", "RUN", "--max-steps", "3", "x.y=1"])
    assert (train.preset, train.max_steps, train.overrides, train.argv[0]) == ("auto", 3, ["x.y=1"], "train")
    with pytest.raises(SystemExit):
        main(["reproduce", "lego", "--data", "D", "--out", "O"])
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("anisdf reproduce: error: argument table: invalid choice: 'lego'")
    assert err[0].endswith("(see anisdf reproduce --help)")
