"""``immnet evaluate --wandb``: the offline run, read back with wandb's own reader of its run files
(``wandb leet inspect --json``, which decodes the run's ``.wandb`` transaction log), holds the config,
the results table with every method, the per-method scalars (equal to the ``--json`` results), the
RMSE-over-time plot, the confusion charts and the figures; ``WANDB_MODE=disabled`` changes nothing."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import immnet.cli
from immnet import keys
from immnet.cli import main
from immnet.config import REPO_ROOT

pytest.importorskip("wandb")
generate = pytest.importorskip("immnet.data.generate").generate
DataSpec = pytest.importorskip("immnet.data.spec").DataSpec

METHODS = ["measurements", "imm-accurate", "immnet", "clairvoyant"]


@pytest.fixture(autouse=True)
def only_our_commands(monkeypatch):
    monkeypatch.setattr(immnet.cli, "_COMMAND_MODULES", ("immnet.evaluation.cli",))


@pytest.fixture(scope="module")
def npz(tmp_path_factory):
    td = generate(4, seed=11, spec=DataSpec(T=60, min_segment=20))
    path = tmp_path_factory.mktemp("wandb-data") / "full.npz"
    np.savez(path, dt=1.0, **{k: td[k].numpy() for k in (keys.STATES, keys.MEASUREMENTS, keys.MODE, keys.TURN_RATE, keys.R)})
    return path


def evaluate(npz, out: Path, *extra) -> dict:
    assert main(["evaluate", "--data", str(npz), "--methods", ",".join(METHODS), "--json", str(out / "r.json"),
                 "--quiet", "--seed", "1", *extra]) == 0
    return json.loads((out / "r.json").read_text())


def records(run_dir: Path) -> list[dict]:
    """The run's records, decoded from its .wandb file by wandb itself (its CLI ``leet inspect --json``)."""
    proc = subprocess.run([sys.executable, "-m", "wandb", "leet", "inspect", "--json", str(run_dir)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return [json.loads(line) for line in proc.stdout.splitlines() if line.strip()]


@pytest.fixture(scope="module")
def offline(npz, tmp_path_factory):
    """One offline evaluation run: ``(json results, run directory, records)``."""
    out = tmp_path_factory.mktemp("wandb-offline")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("WANDB_MODE", "offline")
        mp.setenv("WANDB_SILENT", "true")
        for var in ("WANDB_RUN_GROUP", "WANDB_NAME", "WANDB_JOB_TYPE", "WANDB_PROJECT", "WANDB_DIR"):
            mp.delenv(var, raising=False)
        doc = evaluate(npz, out, "--wandb", "--wandb-dir", str(out / "w"), "--wandb-group", "g", "--wandb-name", "eval")
    runs = list((out / "w" / "wandb").glob("offline-run-*"))
    assert len(runs) == 1
    return doc, runs[0], records(runs[0])


def merged(recs: list[dict], kind: str) -> dict:
    out = {}
    for r in recs:
        if r["type"] == kind:
            out.update(r[kind]["update"] if kind in ("summary", "config") else r[kind]["item"])
    return out


def test_the_run_holds_config_table_scalars_and_figures(offline):
    doc, run_dir, recs = offline
    run = next(r["run"] for r in recs if r["type"] == "run")
    assert (run["run_group"], run["display_name"], run["job_type"], run["project"]) == ("g", "eval", "evaluate", "immnet")
    config = {**run["config"]["update"], **merged(recs, "config")}
    assert config["command"] == "evaluate" and config["data"]["n_trajectories"] == 4 and config["data"]["meta"]["n"] == 4
    assert set(config["methods"]) == set(METHODS)  # (a config is a mapping: its order is not kept)
    ckpt = config["methods"]["immnet"]["checkpoint"]  # no --checkpoint: the shipped weights, with their provenance
    assert ckpt["path"].endswith("immnet.ckpt") and ckpt["weights_sha256"] == ckpt["provenance"]["weights_sha256"]

    history = merged(recs, "history")
    table = json.loads((run_dir / "files" / history["results.path"]).read_text())  # the wandb.Table's file
    assert table["columns"][:6] == ["method", "x [m]", "y [m]", "z [m]", "Average [m]", "post-switch [m]"]
    rows = {row[0]: dict(zip(table["columns"], row)) for row in table["data"]}
    assert list(rows) == METHODS
    summary = merged(recs, "summary")
    for name, r in doc["methods"].items():
        assert rows[name]["Average [m]"] == pytest.approx(r["rmse"]["avg"])
        assert rows[name]["post-switch [m]"] == pytest.approx(r["rmse_post_switch"]["avg"])
        for axis in ("x", "y", "z", "avg"):
            assert summary[f"{name}/rmse_{axis}"] == pytest.approx(r["rmse"][axis])
        assert summary.get(f"{name}/mode_accuracy") == pytest.approx(r.get("mode_accuracy"))
        assert summary[f"{name}/ratio_to_bound"] == pytest.approx(r["rmse"]["avg"] / doc["methods"]["clairvoyant"]["rmse"]["avg"])

    curve = history["rmse_over_time_table.path"]  # wandb.plot.line_series: its table, one line per method
    lines = json.loads((run_dir / "files" / curve).read_text())
    assert {row[lines["columns"].index("lineKey")] for row in lines["data"]} == set(METHODS)
    assert {"confusion/imm-accurate_table.path", "confusion/immnet_table.path"} <= set(history)
    images = {k.split("/", 1)[1].rsplit(".", 1)[0] for k in history if k.startswith("figures/") and k.endswith("._type")}
    assert {"rmse_over_time", "confusion_immnet", "confusion_imm-accurate"} <= images
    assert sum(n.endswith("_track") for n in images) == 2
    uploaded = {f["path"] for r in recs if r["type"] == "files" for f in r["files"]["files"]}
    for key in images:
        path = history[f"figures/{key}.path"]
        assert path in uploaded and (run_dir / "files" / path).read_bytes()[:4] == b"\x89PNG"


def test_disabled_writes_the_same_results_and_no_run(npz, offline, tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "disabled")
    monkeypatch.chdir(tmp_path)
    doc = evaluate(npz, tmp_path, "--wandb", "--wandb-dir", str(tmp_path / "w"))
    strip = lambda d: {**d, "methods": {n: {k: v for k, v in r.items() if k != "seconds"} for n, r in d["methods"].items()}}  # noqa: E731
    assert strip(doc) == strip(offline[0])
    assert not (tmp_path / "w").exists() and not (tmp_path / "wandb").exists()


def test_the_report_definition_names_what_the_evaluation_logs(offline):
    """configs/wandb/report.yaml (built by scripts/wandb_report.py, online) shows keys the runs hold."""
    sys.path.insert(0, str(REPO_ROOT / "scripts"))
    try:
        import wandb_report
    finally:
        sys.path.remove(str(REPO_ROOT / "scripts"))
    spec = wandb_report.load()
    history = merged(offline[2], "history")
    evaluated = [s for s in spec["sections"] if "JobType = 'evaluate'" in s["runs"] or "ablations-table" in s["runs"]]
    assert len(evaluated) == 2
    for sec in evaluated:
        for p in sec["panels"]:
            keys = [p["table"]] if "table" in p else [f"{p['chart']}_table"] if "chart" in p else p.get("media", [])
            assert all(f"{k}._type" in history for k in keys), (p, sorted(history))


def test_the_training_logger_writes_nothing_when_disabled(tmp_path, monkeypatch):
    """``immnet fit``'s default logger under ``WANDB_MODE=disabled`` writes no run (Lightning's
    ``offline=True`` would set WANDB_MODE to offline itself). wandb reads its environment once per
    process (as each ``immnet fit`` is): torn down before and after, so that it reads it here."""
    import wandb
    from lightning.pytorch.loggers import WandbLogger

    from immnet.training.cli import _default_logger

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("WANDB_MODE", "disabled")
    wandb.teardown()
    try:
        logger = WandbLogger(**_default_logger()["init_args"])
        logger.log_metrics({"val/loss": 1.0}, step=0)
        logger.experiment.finish()
    finally:
        wandb.teardown()
    assert not (tmp_path / "runs" / "wandb").exists() and not (tmp_path / "wandb").exists()


def test_a_checkpoint_for_a_skipped_method_does_not_stop_the_run_after_scoring(npz, tmp_path, monkeypatch):
    """Without ``--methods`` a method the data does not allow is skipped (a note); a ``--checkpoint NAME=CKPT`` named
    for it was taken when the methods were chosen, so the W&B run's config takes it too rather than refusing it after
    every method was scored (here the 5 s network on 1 s data)."""
    import immnet.filters.methods as methods

    monkeypatch.setattr(methods, "available_methods", lambda methods_dir=None: ["measurements", "immnet-real-5s"])
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    monkeypatch.chdir(tmp_path)
    ckpt = REPO_ROOT / "immnet" / "pretrained" / "immnet-real-5s.ckpt"
    assert main(["evaluate", "--data", str(npz), "--json", str(tmp_path / "r.json"), "--quiet", "--wandb",
                 "--wandb-dir", str(tmp_path / "w"), "--checkpoint", f"immnet-real-5s={ckpt}"]) == 0
    assert len(list((tmp_path / "w" / "wandb").glob("offline-run-*"))) == 1
    assert list(json.loads((tmp_path / "r.json").read_text())["methods"]) == ["measurements"]
