"""``scripts/data_scaling.py`` (docs/notebook/real-flights.md "How much more flights would give"): the overlay that
places each run, and the table, checked against ``immnet evaluate`` of the same weights on the same sets."""

import json
import runpy
import shutil

import pytest
import yaml
from test_data_adsb import _records, _write

import immnet.cli
from immnet.config import REPO_ROOT
from immnet.data import real
from immnet.data.storage import load_dataset

SCRIPT = REPO_ROOT / "scripts" / "data_scaling.py"
WEIGHTS = REPO_ROOT / "immnet" / "pretrained" / "immnet-real.ckpt"


def test_the_overlay_moves_the_run_and_its_data_alone(tmp_path):
    recipe = yaml.safe_load((REPO_ROOT / "recipes" / "real.yaml").read_text())
    ns = runpy.run_path(str(SCRIPT))
    over = ns["overlay"](recipe, tmp_path / "run", tmp_path / "data")
    assert over["trainer"]["default_root_dir"] == str(tmp_path / "run") and over["data"] == {"data": str(tmp_path / "data")}
    callbacks = recipe["trainer"]["callbacks"]
    assert [c["class_path"] for c in over["trainer"]["callbacks"]] == [c["class_path"] for c in callbacks]
    ckpt = next(c for c in over["trainer"]["callbacks"] if c["class_path"].endswith("ModelCheckpoint"))
    was = next(c for c in callbacks if c["class_path"].endswith("ModelCheckpoint"))
    assert ckpt["init_args"] == {**was["init_args"], "dirpath": str(tmp_path / "run" / "checkpoints")}
    assert was["init_args"]["dirpath"] == "runs/real/axis/checkpoints"  # the recipe itself untouched
    assert ns["label"](1.0) == "all" and ns["label"](0.25) == "0.25" and ns["label"](40.0) == "40"


@pytest.mark.skipif(not WEIGHTS.exists(), reason="the shipped real-flight weights are not in the checkout")
def test_the_table_is_what_evaluate_gives(tmp_path, capsys, monkeypatch):
    """Runs already trained (--skip-training; the shipped weights stand in for each run's best checkpoint): each
    row's RMSE is `immnet evaluate`'s for those weights on that set, its ratio to the filter's."""
    sample = _write(tmp_path / "s.json.gz", _records(n_aircraft=8, n=400))
    spec = real.RealSpec(T=50, splits=(0.5, 0.25, 0.25), max_range=60_000)
    real.make_adsb(tmp_path / "o", [sample], spec, seed=0)
    out = tmp_path / "scaling"
    real.subset_flights(tmp_path / "o" / "train", out / "seed3" / "0.5" / "data", 0.5, seed=3)
    for run in ("seed3/0.5", "all"):
        (out / run / "checkpoints").mkdir(parents=True)
        shutil.copy(WEIGHTS, out / run / "checkpoints" / "best.ckpt")
    main = runpy.run_path(str(SCRIPT))["main"]
    args = ["--data", str(tmp_path / "o"), "--flights", "0.5,1", "--seeds", "3", "--out", str(out), "--skip-training",
            "--json", str(tmp_path / "t.json"), "--figure", str(tmp_path / "f.png")]
    assert main(args) == 0
    got = json.loads((tmp_path / "t.json").read_text())
    assert [(r["name"], r["seed"], r["flights"], r["windows"]) for r in got["runs"]] == [
        ("0.5 (seed 3)", 3, 2, load_dataset(out / "seed3" / "0.5" / "data")[1]["n"]),
        ("all", None, 4, load_dataset(tmp_path / "o" / "train")[1]["n"])]
    assert (tmp_path / "f.png").stat().st_size > 0
    capsys.readouterr()
    for name, split in (("validation", "val"), ("test", "test")):
        res = tmp_path / f"{split}.json"
        assert immnet.cli.main(["evaluate", "--data", str(tmp_path / "o" / split), "--split", "all", "--guard", "none",
                                "--methods", "real-imm-axis,immnet-real", "--json", str(res), "--quiet",
                                "--no-wandb"]) == 0
        rows = json.loads(res.read_text())["methods"]
        net, base = rows["immnet-real"]["rmse"]["avg"], rows["real-imm-axis"]["rmse"]["avg"]
        assert got["best_baseline"][name] == pytest.approx(base, rel=1e-9)
        for r in got["runs"]:
            assert r["sets"][name] == {"rmse_avg": pytest.approx(net, rel=1e-9), "ratio": pytest.approx(net / base)}
