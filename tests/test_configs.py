"""Every YAML in the repository loads, so none can rot: recipes and ablations parse through
Lightning's CLI, model sets and methods build."""

from pathlib import Path

import pytest
import yaml

from immnet.config import REPO_ROOT
from immnet.training.cli import _run, config_args, stage_entry

RECIPES = sorted((REPO_ROOT / "recipes").glob("*.yaml"))
STAGE_RECIPES = [p for p in RECIPES if "stages" not in yaml.safe_load(p.read_text())]
CHAINS = [p for p in RECIPES if p not in STAGE_RECIPES]
ABLATIONS = sorted((REPO_ROOT / "configs" / "ablations").glob("*.yaml"))


def _print_config(args, capsys) -> dict:
    with pytest.raises(SystemExit) as exit_:
        _run(["fit", *args, "--print_config"])
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
        configs, _ = stage_entry(s, i)  # PATH, or {config: PATH or [PATH or INLINE, ...], checkpoint_as: ...}
        for path in configs:
            assert isinstance(path, dict) or (REPO_ROOT / path).is_file(), path


def _ablation_stages(ablation: Path, capsys):
    """Each stage of an ablation's chain as Lightning's CLI configures it, and the IMMNet it builds."""
    from immnet.stages import IMMNet
    from immnet.stages.network import net_arguments

    spec = yaml.safe_load(ablation.read_text())
    out = []
    for i, stage in enumerate(spec["stages"]):
        configs, _ = stage_entry(stage, i)
        cfg = _print_config(config_args(configs), capsys)
        out.append((cfg, IMMNet(**net_arguments(cfg["model"]["init_args"]["net"]))))
    return spec, out


EXPECT = {  # ablation: (gain class, interaction, guard on, classifier class, model set size) of its last stage
    "no-guard": ("KalmanNetFilterGain", "imm", False, "BayesTransformerClassifier", 4),
    "uniform-mix": ("KalmanNetFilterGain", "imm", True, "UniformMix", 4),
    "bayes-mode": ("KalmanNetFilterGain", "imm", True, "BayesianModeUpdate", 4),
    "transformer-mode": ("KalmanNetFilterGain", "imm", True, "TransformerClassifier", 4),
    "fused-input": ("KalmanNetFilterGain", "fused", False, "BayesTransformerClassifier", 4),
    "analytic-gain": ("FilterGain", "imm", True, "BayesTransformerClassifier", 4),
    "single-expert": ("KalmanNetGain", None, False, "TransformerClassifier", 1),
    "fixed-turn-rate": ("KalmanNetFilterGain", "imm", True, "BayesTransformerClassifier", 4),
    "kalmannet-experts": ("KalmanNetGain", None, False, "TransformerClassifier", 4),
}


@pytest.mark.parametrize("ablation", ABLATIONS, ids=lambda p: p.stem)
def test_every_ablation_is_a_self_contained_chain(ablation, capsys):
    """Issue 21, item 4: each ablation is one runnable file (``immnet fit --config configs/ablations/NAME.yaml``):
    a chain whose stages name their base recipe and what changes, merged by Lightning's CLI argument by
    argument; it names its row's label and weights; the network it builds has the parts the ablation says."""
    spec, stages = _ablation_stages(ablation, capsys)
    assert spec["label"] and spec["checkpoint"].startswith(f"runs/ablations/{ablation.stem}/")
    cfg, net = stages[-1]
    assert cfg["trainer"]["default_root_dir"].startswith(f"runs/ablations/{ablation.stem}")
    gain, interaction, guard, classifier, M = EXPECT[ablation.stem]
    assert type(net.gain).__name__ == gain and type(net.classify).__name__ == classifier and net.n_experts == M
    assert getattr(net.gain, "interaction", None) == interaction
    assert (getattr(net.interact, "guard", None) is not None) == guard
    if ablation.stem == "no-guard":  # the recipe's dev-set choice without the guard, set once
        assert net.interact.Pi[0, 0].item() == pytest.approx(0.995) and net.classify.p_stay == pytest.approx(0.995)
    if ablation.stem == "fixed-turn-rate":
        assert [type(m).__name__ for m in net.model_set] == ["ConstantVelocity", "ConstantAcceleration", "CoordinatedTurn", "CoordinatedTurn"]


def test_a_second_config_merges_into_the_network_argument_by_argument(tmp_path, capsys):
    """Issue 21, item 4: the tracker's components are typed arguments: a second ``--config`` that changes one
    of the gain's arguments keeps the rest of the recipe's network (model set, p_stay, guard, classifier), and a
    command-line override reaches one argument."""
    over = tmp_path / "over.yaml"
    over.write_text("model: {init_args: {net: {init_args: {gain: {init_args: {u_max: 7.0}}}}}}\n")
    recipe = str(REPO_ROOT / "recipes" / "quick-stage2.yaml")
    cfg = _print_config(["--config", recipe, "--config", str(over), "--model.init_args.net.init_args.p_stay", "0.99"], capsys)
    net = cfg["model"]["init_args"]["net"]["init_args"]
    assert net["model_set"] == "configs/model_sets/imm4-adaptive.yaml" and net["guard"] is True and net["p_stay"] == 0.99
    assert net["gain"]["class_path"].endswith("KalmanNetFilterGain") and net["gain"]["init_args"]["u_max"] == 7.0
    assert net["classifier"]["class_path"].endswith("BayesTransformerClassifier")


def test_a_packaged_ablation_runs_from_another_directory(tmp_path, monkeypatch, capsys):
    """Issue 21, item 4: an ablation's stages find the packaged recipes' and configs' paths from a directory
    that does not hold them (docs/configs.md) and configure what they do from the checkout."""
    spec = yaml.safe_load((REPO_ROOT / "configs/ablations/no-guard.yaml").read_text())
    configs, _ = stage_entry(spec["stages"][0], 0)
    want = _print_config(config_args(configs), capsys)
    monkeypatch.chdir(tmp_path)
    got = _print_config(config_args(configs), capsys)
    assert got["model"] == want["model"] and got["model"]["init_args"]["net"]["init_args"]["guard"] is False


@pytest.mark.parametrize("stage", ["stage1.yaml", "stage2.yaml"])
def test_the_full_scale_recipe_is_one_config_away_from_the_shipped_network(stage, capsys):
    """Issue 21, item 4: ``configs/nets/filter-experts.yaml`` over the paper's stages gives the shipped recipes'
    network (filter experts, the IMM interaction with the guard, one p_stay) and keeps the paper's budget."""
    from immnet.stages import IMMNet
    from immnet.stages.network import net_arguments

    base = yaml.safe_load((REPO_ROOT / "recipes" / stage).read_text())
    cfg = _print_config(["--config", str(REPO_ROOT / "recipes" / stage), "--config",
                         str(REPO_ROOT / "configs/nets/filter-experts.yaml")], capsys)
    assert cfg["trainer"]["max_epochs"] == base["trainer"]["max_epochs"]
    net = IMMNet(**net_arguments(cfg["model"]["init_args"]["net"]))
    assert type(net.gain).__name__ == "KalmanNetFilterGain" and net.interact.guard is not None
    assert net.interact.Pi[0, 0].item() == pytest.approx(0.999) and net.classify.p_stay == pytest.approx(0.999)


MEMBERS = sorted((REPO_ROOT / "configs" / "members").glob("*.yaml"))


@pytest.mark.parametrize("member", MEMBERS, ids=lambda p: p.name)
def test_a_member_overlay_trains_the_same_network_elsewhere(member, capsys):
    """Each ``configs/members`` overlay (a further member of a shipped ensemble of corrections, joined by
    ``immnet.training.export.join_corrections``) names the recipe it overlays in its ``Run:`` line, and changes
    nothing of that recipe's network or data, only the seed, the fresh views and where the run is written: the
    members share their filter, as joining them requires."""
    run = next(line for line in member.read_text().splitlines() if "Run:" in line)
    recipe = REPO_ROOT / run.split("--config ")[1].split()[0]
    base = _print_config(["--config", str(recipe)], capsys)
    over = _print_config(["--config", str(recipe), "--config", str(member)], capsys)
    assert over["model"] == base["model"]
    assert {k: v for k, v in over["data"].items() if k != "augment"} == {
        k: v for k, v in base["data"].items() if k != "augment"}
    assert over["trainer"]["default_root_dir"] != base["trainer"]["default_root_dir"]
    dirs = [c["init_args"]["dirpath"] for c in over["trainer"]["callbacks"] if "dirpath" in c.get("init_args", {})]
    assert dirs == [f"{over['trainer']['default_root_dir']}/checkpoints"]
