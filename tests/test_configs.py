"""Every YAML in the repository loads, so none can rot: recipes and ablations parse through
Lightning's CLI, model sets and methods build."""

from pathlib import Path

import pytest
import yaml

from immnet.config import REPO_ROOT
from immnet.training.cli import _cli, stage_entry

RECIPES = sorted((REPO_ROOT / "recipes").glob("*.yaml"))
STAGE_RECIPES = [p for p in RECIPES if "stages" not in yaml.safe_load(p.read_text())]
CHAINS = [p for p in RECIPES if p not in STAGE_RECIPES]
ABLATIONS = sorted((REPO_ROOT / "configs" / "ablations").glob("*.yaml"))
KALMANNET_GAIN_ABLATIONS = {"single-expert", "kalmannet-experts"}  # the ablations whose point is KalmanNet's own gain


def _print_config(args, capsys) -> dict:
    with pytest.raises(SystemExit) as exit_:
        _cli(["fit", *args, "--print_config"])
    assert exit_.value.code in (0, None)
    return yaml.safe_load(capsys.readouterr().out)


def test_every_yaml_is_valid_yaml():
    for path in REPO_ROOT.glob("**/*.yaml"):
        if ".venv" in path.parts or "runs" in path.parts:
            continue
        yaml.safe_load(path.read_text())


@pytest.mark.parametrize("recipe", STAGE_RECIPES, ids=lambda p: p.name)
def test_recipe_parses_with_lightning_cli(recipe, capsys):
    first = recipe.read_text().splitlines()[0:3]
    assert any("Run:" in line or "immnet fit" in line for line in recipe.read_text().splitlines()[:8]), \
        f"{recipe.name} must start with a comment giving the command that runs it"
    cfg = _print_config(["--config", str(recipe)], capsys)
    assert cfg["model"]["class_path"].startswith("immnet.training.")
    assert first


@pytest.mark.parametrize("chain", CHAINS, ids=lambda p: p.name)
def test_chained_recipes_name_existing_stages(chain):
    stages = yaml.safe_load(chain.read_text())["stages"]
    assert len(stages) >= 2
    for i, s in enumerate(stages):
        path, _ = stage_entry(s, i)  # PATH or {config: PATH, checkpoint_as: ...}
        assert (REPO_ROOT / path).is_file(), path


@pytest.mark.parametrize("ablation", ABLATIONS, ids=lambda p: p.stem)
def test_ablation_overrides_a_quick_stage(ablation, capsys):
    base = "quick-stage1.yaml" if "single-expert" in ablation.name else "quick-stage2.yaml"
    cfg = _print_config(["--config", str(REPO_ROOT / "recipes" / base), "--config", str(ablation)], capsys)
    assert cfg["trainer"]["default_root_dir"].startswith("runs/ablations/")
    # a second --config replaces the `net` mapping whole: an ablation that forgot the model set
    # would silently train IMMNet's default experts instead of the recipe's
    net = cfg["model"]["init_args"]["net"] or {}
    assert "model_set" in net, f"{ablation.name} must name its model set"
    # ... and its gain: the quick recipe's experts are filter experts, the default gain is KalmanNet's
    if ablation.stem not in KALMANNET_GAIN_ABLATIONS:
        assert "filtering" in (net.get("gain") or {}).get("class_path", ""), f"{ablation.name} must name the filter-expert gain"
        # ... with the quick recipe's IMM interaction, but where the interaction is the point
        interaction = ((net.get("gain") or {}).get("init_args") or {}).get("interaction")
        assert interaction == ("fused" if ablation.stem == "fused-input" else "imm"), f"{ablation.name}: interaction {interaction}"
        # ... and the quick recipe's range guard, but where the guard is the point (the fused input has none)
        guard = ((net.get("gain") or {}).get("init_args") or {}).get("guard")
        assert bool(guard) == (ablation.stem not in ("no-guard", "fused-input")), f"{ablation.name}: guard {guard}"


def test_a_packaged_ablation_runs_from_another_directory(tmp_path, monkeypatch, capsys):
    """Issue 21, item 4: ``immnet fit --config RECIPE --config configs/ablations/no-guard.yaml`` finds the
    packaged ablation from a directory that does not hold it (docs/configs.md) and configures what the
    ablation's own file does."""
    from immnet.cli import main

    recipe = str(REPO_ROOT / "recipes" / "quick-stage2.yaml")
    want = _print_config(["--config", recipe, "--config", str(REPO_ROOT / "configs/ablations/no-guard.yaml")], capsys)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        main(["fit", "--config", recipe, "--config", "configs/ablations/no-guard.yaml", "--print_config"])
    assert exit_.value.code in (0, None)
    got = yaml.safe_load(capsys.readouterr().out)
    assert got["model"] == want["model"] and not got["model"]["init_args"]["net"]["gain"]["init_args"]["guard"]
