"""Training end to end at tiny sizes: the quick recipe's two chained stages and every ablation
train through `immnet fit` and evaluate through `immnet evaluate`, in a scratch directory laid out
as `bash scripts/main.sh` lays out the repository (runs/quick/data/...)."""

import json
import math
import os
import subprocess
import sys

import pytest

from immnet.checkpoints import load_checkpoint
from immnet.cli import main
from immnet.config import REPO_ROOT
from immnet.training import Stage2Module

from tiny_runs import TINY, write_quick_data

pytestmark = pytest.mark.slow
# a few optimizer steps, one validation on one batch, small batches: minutes become seconds
FAST = ["--trainer.max_steps", "4", "--trainer.val_check_interval", "2", "--trainer.limit_val_batches", "1",
        "--data.batch_size", "4", "--trainer.logger", "false"]
ABLATIONS = sorted((REPO_ROOT / "configs" / "ablations").glob("*.yaml"))


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    """runs/quick/data with a train set, the four single-mode sets and a test set, all tiny."""
    return write_quick_data(tmp_path_factory.mktemp("work"), TINY, test=True)


@pytest.fixture(scope="module")
def quick(workdir):
    """The quick recipe, both stages chained, at tiny size; returns the stage checkpoints."""
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(workdir)
        main(["fit", "--config", str(REPO_ROOT / "recipes/quick.yaml"), *FAST])
    s1, s2 = (workdir / f"runs/quick/stage{i}/checkpoints/best.ckpt" for i in (1, 2))
    assert s1.is_file() and s2.is_file()
    return s1, s2


def _evaluate(workdir, methods: str, *checkpoints: str) -> dict:
    out = workdir / "results.json"
    args = ["evaluate", "--data", str(workdir / "runs/quick/data/test"), "--split", "all", "--methods", methods,
            "--json", str(out), "--quiet"]
    for c in checkpoints:
        args += ["--checkpoint", c]
    assert main(args) == 0
    return json.loads(out.read_text())["methods"]


def test_quick_recipe_trains_both_stages_and_evaluates(workdir, quick):
    s1, s2 = quick
    state = load_checkpoint(s2)
    assert 0 < state["global_step"] <= 4
    # stage 2 started from stage 1's experts: the gain weights moved on from there, not from scratch
    g1 = load_checkpoint(s1)["state_dict"]["net.gain.fc2a.weight"]
    g2 = state["state_dict"]["net.gain.fc2a.weight"]
    fresh = Stage2Module(net={"model_set": "configs/model_sets/imm4-adaptive.yaml"}).net.gain.fc2a.weight
    assert (g2 - g1).abs().max() < (g2 - fresh).abs().max()
    res = _evaluate(workdir, "measurements,immnet,kalmannet", f"immnet={s2}", f"kalmannet={s1}")
    for name in ("immnet", "kalmannet"):
        assert math.isfinite(res[name]["rmse"]["avg"])
    assert 0.0 <= res["immnet"]["mode_accuracy"] <= 1.0


@pytest.mark.parametrize("ablation", ABLATIONS, ids=lambda p: p.stem)
def test_every_ablation_trains_and_evaluates(workdir, quick, ablation):
    """Each ablation trains by its own file alone (``immnet fit --config configs/ablations/NAME.yaml``; the
    one-stage ones from the quick run's stage-1 experts, which ``quick`` made) and its weights, where the file
    says, evaluate as the file says."""
    import yaml

    spec = yaml.safe_load(ablation.read_text())
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(workdir)
        main(["fit", "--config", str(ablation), *FAST])
    ckpt = workdir / spec["checkpoint"]
    assert ckpt.is_file()
    method = (spec.get("evaluate") or {}).get("method", "immnet")
    res = _evaluate(workdir, f"measurements,{method}", f"{method}={ckpt}")
    assert math.isfinite(res[method]["rmse"]["avg"])


def test_cosine_schedule_ends_at_its_floor(workdir, quick):
    """lr_schedule: cosine falls from lr to lr_floor * lr over max_steps (closed form at the end)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(workdir)
        main(["fit", "--config", str(REPO_ROOT / "recipes/quick-stage2.yaml"), *FAST,
              "--model.init_args.lr_schedule", "cosine", "--model.init_args.lr_floor", "0.1",
              "--model.init_args.stage1_checkpoint", str(quick[0]),
              "--trainer.default_root_dir", "runs/cosine", "--overwrite_checkpoints", "true"])
    state = load_checkpoint(workdir / "runs/quick/stage2/checkpoints/best.ckpt")
    sched = state["lr_schedulers"][0]
    lr = state["hyper_parameters"]["lr"]
    assert sched["last_epoch"] == state["global_step"]
    assert sched["_last_lr"][0] == pytest.approx(lr * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * state["global_step"] / 4))))


def test_chained_recipe_trains_under_ddp(workdir, tmp_path):
    """Two CPU processes (gloo) through Lightning's DDP strategy, the chain unchanged: each stage's
    workers are launched afresh, batches are sharded per rank, progress is printed by rank 0 only."""
    (tmp_path / "runs/quick").mkdir(parents=True)
    (tmp_path / "runs/quick/data").symlink_to(workdir / "runs/quick/data")
    cmd = [sys.executable, "-m", "immnet.cli", "fit", "--config", str(REPO_ROOT / "recipes/quick.yaml"), *FAST,
           "--trainer.accelerator", "cpu", "--trainer.strategy", "ddp", "--trainer.devices", "2"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stderr.count("Initializing distributed: GLOBAL_RANK: 1") == 2  # once per stage
    assert done.stderr.count("[train] Stage2Module") == 1
    for i in (1, 2):
        state = load_checkpoint(tmp_path / f"runs/quick/stage{i}/checkpoints/best.ckpt")
        assert 0 < state["global_step"] <= 4


def test_shipped_recipe_chains_a_fine_tune_of_the_whole_immnet(workdir, tmp_path):
    """recipes/pretrained.yaml, its three stages at tiny size: stage 3 takes stage 2's best checkpoint as
    init_checkpoint (every weight, the Transformer's too), not as stage1_checkpoint (the experts only)."""
    (tmp_path / "runs/quick").mkdir(parents=True)
    (tmp_path / "runs/quick/data").symlink_to(workdir / "runs/quick/data")
    (tmp_path / "runs/pretrained/data").mkdir(parents=True)
    (tmp_path / "runs/pretrained/data/train").symlink_to(workdir / "runs/quick/data/train")
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(tmp_path)
        main(["fit", "--config", str(REPO_ROOT / "recipes/pretrained.yaml"), *FAST])
    s2, s3 = (load_checkpoint(tmp_path / f"runs/pretrained/stage{i}/checkpoints/best.ckpt")
              for i in (2, 3))
    assert s3["hyper_parameters"]["init_checkpoint"].endswith("stage2/checkpoints/best.ckpt")
    assert s3["hyper_parameters"]["net"]["init_args"]["p_stay"] == 0.998  # set once, on the network
    # stage 3 started from stage 2's Transformer: its weights moved a few small steps from there, far less
    # than stage 2's own moved from a fresh start
    key = "net.classify.blocks.0.qkv.weight"
    fresh = Stage2Module(net=s3["hyper_parameters"]["net"]).state_dict()[key]
    assert (s3["state_dict"][key] - s2["state_dict"][key]).abs().max() < (s2["state_dict"][key] - fresh).abs().max()


def test_a_chained_stage_names_how_it_takes_the_checkpoint(tmp_path):
    from immnet.training.cli import run_stages

    with pytest.raises(ValueError, match="checkpoint_as must be"):
        run_stages({"stages": [{"config": "a.yaml", "checkpoint_as": "ckpt_path"}]}, [])
    with pytest.raises(ValueError, match="takes `config`"):
        run_stages({"stages": [{"config": "a.yaml", "trainer": {}}]}, [])
