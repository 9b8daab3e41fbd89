"""``anisdf reproduce``: the paper's tables, scene discovery, one row per (scene, config), resume, errors."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
import yaml
from scenes import write_test_scene
from test_training import TINY

from anisdf.cli import main
from anisdf.config import load_config
from anisdf.errors import AnisdfError
from anisdf.eval.paper_tables import METRICS, TABLES, find_scenes, get_table
from anisdf.orchestration import reproduce
from anisdf.tasks import train as train_task
from anisdf.training.trainer import Trainer

PAPER_TEX = Path(__file__).resolve().parents[2] / "shared" / "reference" / "anisdf-paper.tex"
FAST = {"scale": "cpu", "minutes": 0.0, "max_steps": 2, "overrides": TINY, "max_views": 1, "mesh_resolution": 32,
        "chamfer_points": 2000, "progress": False}
ROW_KEYS = {"scene", "config", "seed", *METRICS, "paper", "seconds"}


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


@pytest.fixture(scope="module")
def lego_root(toy_scene, tmp_path_factory) -> Path:
    """A dataset root holding a toy scene named as a paper scene ("lego"), one it does not list and a non-scene."""
    root = tmp_path_factory.mktemp("nerf_synthetic")
    _copy(toy_scene, root / "lego")
    _copy(toy_scene, root / "my_object")
    (root / "notes").mkdir()
    return root


def _ours_row(tex: str, label: str) -> list[float]:
    """The numbers of the row starting with "Ours" in the table labelled ``label`` (Chamfer part: the last one)."""
    body = tex[:tex.index(f"\\label{{{label}}}")]
    body = body[body.rindex("\\begin{tabular}"):]
    rows = [r for r in re.split(r"\\\\", body) if re.search(r"(^|&|\s)Ours\s*&", r)]
    return [float(x) for x in re.findall(r"(?<![\w.])\d+\.\d+", rows[-1])]


@pytest.mark.skipif(not PAPER_TEX.is_file(), reason="the paper's tex is not beside the repository")
def test_paper_numbers_match_the_tex():
    tex = PAPER_TEX.read_text()
    syn, shiny, dtu = TABLES["nerf-synthetic"], TABLES["shiny"], TABLES["dtu"]
    body = tex[:tex.index("\\label{tab_syn}")]
    psnr_row, cd_row = [[float(x) for x in re.findall(r"(?<![\w.])\d+\.\d+", r)]
                        for r in re.split(r"\\\\", body[body.rindex("\\begin{tabular}"):]) if "&Ours" in r
                        or "& &Ours" in r or "&&Ours" in r]
    assert psnr_row == [*(syn.scenes[s]["psnr"] for s in syn.scenes), syn.means["all"]["psnr"]]
    assert cd_row == pytest.approx([*(syn.scenes[s]["chamfer"] * 1e3 for s in syn.scenes),
                                    syn.means["all"]["chamfer"] * 1e3])
    flat = [v for s in shiny.scenes.values() for v in (s["psnr"], s["normal_mae_deg"])]
    assert _ours_row(tex, "tab_shiny") == [*flat, shiny.means["all"]["psnr"], shiny.means["all"]["normal_mae_deg"]]
    assert _ours_row(tex, "dtu") == [*(s["chamfer"] for s in dtu.scenes.values()), dtu.means["all"]["chamfer"]]
    m360 = TABLES["mipnerf360"]
    p = [s["psnr"] for s in m360.scenes.values()]
    assert _ours_row(tex, "tab_360") == [*p[:5], m360.means["outdoor"]["psnr"], *p[5:], m360.means["indoor"]["psnr"]]
    abl = tex[tex.rindex("\\begin{tabular}", 0, tex.index("\\label{ab_tab}")):tex.index("\\label{ab_tab}")]
    got = {}
    for line in re.split(r"\\\\", abl):
        nums = [float(x) for x in re.findall(r"(?<![\w.])\d+\.\d+", line)]
        if len(nums) == 2:
            asg, fused = "w/o ASG" not in line, "w/o Fused" not in line
            got[{(1, 1): "full", (0, 1): "no-asg", (1, 0): "no-fusion", (0, 0): "no-asg-no-fusion"}[asg, fused]] = nums
    means = TABLES["ablation"].means
    assert got == {c: pytest.approx([v["psnr"], v["chamfer"] * 1e3]) for c, v in means.items()}


def test_run_settings_follow_each_tables_protocol():
    dtu = get_table("dtu")
    preset, ovr = reproduce.run_settings(dtu, "dtu_scan65", "full", "cpu", 0)
    assert preset == "cpu-quick" and "data.train_split=all" in ovr and "train.seed=0" in ovr
    assert not any(o.startswith("data.downscale") for o in ovr)
    assert load_config(preset, ovr).data.train_split == "all"
    m360 = get_table("mipnerf360")
    for scene, folder in (("bicycle", "images_4"), ("room", "images_2"), ("Kitchen", "images_2")):
        preset, ovr = reproduce.run_settings(m360, scene, "full", "cpu", 0)
        assert load_config(preset, ovr).data.images_dir == folder, scene
        preset, ovr = reproduce.run_settings(m360, scene, "full", "paper", 0)
        assert preset == "mipnerf360" and load_config(preset, ovr).data.images_dir == folder, scene
    abl = get_table("ablation")
    kinds = {c: (cfg.geometry.kind, cfg.appearance.kind) for c in abl.configs
             for cfg in [load_config(*reproduce.run_settings(abl, "lego", c, "paper", 3))]}
    assert kinds == {"full": ("fused", "blend"), "no-asg": ("fused", "pe"), "no-fusion": ("single", "blend"),
                     "no-asg-no-fusion": ("single", "pe")}
    assert load_config(*reproduce.run_settings(abl, "lego", "full", "paper", 3)).train.seed == 3
    assert get_table("dtu").scene_key("DTU_scan065") == "scan65" and get_table("dtu").scene_key("scan7") is None
    with pytest.raises(AnisdfError, match="unknown table 'lego'"):
        get_table("lego")


def test_table_run_writes_rows_beside_the_papers_and_resumes(lego_root, tmp_path, monkeypatch):
    out = tmp_path / "out"
    res = reproduce.reproduce("nerf-synthetic", lego_root, out, seeds=[0, 1], **FAST)
    on_disk = json.loads((out / "reproduce.json").read_text())
    assert on_disk["table"] == "nerf-synthetic" and on_disk["rows"] == res["rows"]
    rows = on_disk["rows"]
    assert [(r["scene"], r["config"], r["seed"]) for r in rows] == [("lego", "full", 0), ("lego", "full", 1)]
    for r in rows:
        assert ROW_KEYS <= set(r) and r["status"] == "done" and r["steps"] == 2 and r["seconds"] > 0
        assert r["psnr"] > 5 and 0 < r["ssim"] <= 1 and r["chamfer"] > 0 and r["normal_mae_deg"] >= 0
        assert r["paper"]["psnr"] == 35.69 and r["paper"]["chamfer"] == pytest.approx(5.16e-3)
    assert yaml.safe_load((out / "lego" / "full-seed1" / "config.yaml").read_text())["train"]["seed"] == 1
    assert on_disk["machine"]["torch"] and on_disk["machine"]["cpu"]
    assert on_disk["means"]["full"]["n_rows"] == 2
    md = (out / "reproduce.md").read_text()
    assert "35.69" in md and "5.16" in md and "anisdf reproduce" in md and on_disk["machine"]["torch"] in md

    def no_training(*a, **k):
        raise AssertionError("a finished row was trained again")

    monkeypatch.setattr(train_task, "train", no_training)
    monkeypatch.setattr("anisdf.tasks.evaluate.evaluate", no_training)
    again = reproduce.reproduce("nerf-synthetic", lego_root, out, seeds=[0, 1], **FAST)
    assert again["rows"] == rows
    with pytest.raises(AnisdfError, match="table 'nerf-synthetic', not 'ablation'"):
        reproduce.reproduce("ablation", lego_root, out, **FAST)


def test_interrupted_run_is_resumed(lego_root, tmp_path, monkeypatch):
    out = tmp_path / "out"
    step = Trainer.train_step

    def interrupt_at_2(self):
        if self.state.step == 1:
            raise KeyboardInterrupt
        return step(self)

    monkeypatch.setattr(Trainer, "train_step", interrupt_at_2)
    with pytest.raises(KeyboardInterrupt):
        reproduce.reproduce("nerf-synthetic", lego_root, out, **FAST)
    run = out / "lego" / "full"
    assert json.loads((run / "run.json").read_text())["status"] == "interrupted"
    assert json.loads((out / "reproduce.json").read_text())["rows"] == []
    monkeypatch.setattr(Trainer, "train_step", step)
    calls: list[dict] = []
    train = train_task.train
    monkeypatch.setattr(train_task, "train", lambda *a, **k: calls.append(k) or train(*a, **k))
    rows = reproduce.reproduce("nerf-synthetic", lego_root, out, **FAST)["rows"]
    assert [c["resume"] for c in calls] == [True]
    assert len(rows) == 1 and rows[0]["status"] == "done" and rows[0]["steps"] == 2
    assert json.loads((run / "run.json").read_text())["status"] == "done"


def test_max_steps_alone_makes_cpu_runs_step_based(lego_root, tmp_path, monkeypatch):
    """At cpu scale the 10-minute budget is the default only without --max-steps: a step count is a step count."""
    seen: list[tuple] = []

    def record(data, run, preset, overrides, max_minutes, max_steps, device, progress):
        seen.append((max_minutes, max_steps))
        raise AnisdfError("recorded")

    monkeypatch.setattr("anisdf.orchestration.cluster.train_or_resume", record)
    opts = {k: v for k, v in FAST.items() if k not in ("minutes", "max_steps")}
    cases = (({"max_steps": 1500}, (None, 1500)), ({}, (10.0, None)), ({"minutes": 3.0, "max_steps": 7}, (3.0, 7)),
             ({"minutes": 0.0}, (None, None)))
    for kw, want in cases:
        with pytest.raises(AnisdfError, match="recorded"):
            reproduce.reproduce("nerf-synthetic", lego_root, tmp_path / f"o{len(seen)}", **opts, **kw)
        assert seen[-1] == want, kw


def test_ablation_on_a_scene_folder_not_in_the_paper(lego_root, tmp_path, capsys):
    out = tmp_path / "abl"
    scene = lego_root / "my_object"
    assert main(["reproduce", "ablation", "--data", str(scene), "--out", str(out), "--scale", "cpu",
                 "--minutes", "0", "--max-steps", "1", "--max-views", "1", "--mesh-resolution", "32",
                 "--chamfer-points", "2000",
                 "--no-progress", *TINY]) == 0
    assert capsys.readouterr().out.strip().endswith("reproduce.md")
    result = json.loads((out / "reproduce.json").read_text())
    assert [(r["scene"], r["config"]) for r in result["rows"]] == [
        ("my_object", c) for c in ("full", "no-asg", "no-fusion", "no-asg-no-fusion")]
    assert all(r["paper"] is None and r["psnr"] is not None for r in result["rows"])
    cfg = yaml.safe_load((out / "my_object" / "no-asg-no-fusion" / "config.yaml").read_text())
    assert (cfg["geometry"]["kind"], cfg["appearance"]["kind"]) == ("single", "pe")
    assert set(result["means"]) == set(TABLES["ablation"].configs)
    assert result["means"]["no-asg"]["paper_table_mean"]["psnr"] == 32.38
    md = (out / "reproduce.md").read_text()
    assert "32.38" in md and "anisdf reproduce ablation --data" in md and "--max-steps 1" in md


def test_configs_selects_the_table_configurations_in_its_order(lego_root, tmp_path, capsys):
    out = tmp_path / "some"
    res = reproduce.reproduce("ablation", lego_root / "my_object", out, configs=["no-fusion", "full"], **FAST)
    assert [r["config"] for r in res["rows"]] == ["full", "no-fusion"]
    assert not (out / "my_object" / "no-asg").exists()
    assert main(["reproduce", "ablation", "--data", str(lego_root), "--out", str(tmp_path / "o"),
                 "--configs", "full,no-curvature"]) == 2
    err = capsys.readouterr().err
    assert "no-curvature not in table ablation" in err and "no-asg-no-fusion" in err


def test_dtu_scene_without_official_files_gets_a_note(tmp_path):
    write_test_scene(tmp_path / "dtu" / "scan65", "neus", n_images=8)
    res = reproduce.reproduce("dtu", tmp_path / "dtu", tmp_path / "out", **FAST)
    (row,) = res["rows"]
    assert row["scene"] == "scan65" and row["chamfer"] is None and row["paper"]["chamfer"] == 0.64
    assert any("DTU Chamfer not measured" in n for n in row["notes"])
    assert "DTU Chamfer not measured" in (tmp_path / "out" / "reproduce.md").read_text()


def test_scene_discovery_and_errors(lego_root, tmp_path, capsys):
    syn = get_table("nerf-synthetic")
    assert [n for n, _ in find_scenes(syn, lego_root)] == ["lego"]
    assert [n for n, _ in find_scenes(syn, lego_root, ["my_object"])] == ["my_object"]
    assert [n for n, _ in find_scenes(syn, lego_root / "my_object")] == ["my_object"]
    with pytest.raises(AnisdfError, match="no nerf-synthetic scene folder called chair"):
        find_scenes(syn, lego_root, ["chair"])
    with pytest.raises(AnisdfError, match="table dtu wants neus"):
        find_scenes(get_table("dtu"), lego_root / "lego")
    empty = tmp_path / "empty"
    (empty / "stuff").mkdir(parents=True)
    assert main(["reproduce", "shiny", "--data", str(empty), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds no scene of Table 2" in err[0] and "helmet" in err[0]
    assert main(["reproduce", "shiny", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["reproduce", "shiny", "--data", str(lego_root), "--out", str(tmp_path / "o"), "--seeds", "0,x"]) == 2
    assert "--seeds" in capsys.readouterr().err
