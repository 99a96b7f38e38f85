"""``scripts/make_shipped.py`` (docs/checkpoints.md "Shipped weights"): the claims it writes for the tests to hold a
shipped file to, and ``--rescore``, which scores a shipped file again and must keep its provenance's training
record, refuse weights its provenance does not describe, and leave the weights as they are."""

import importlib.util
import json
import math
import shutil
import subprocess

import pytest

from immnet.config import REPO_ROOT
from immnet.data.spec import DataSpec
from immnet.data.storage import write_dataset

SCRIPT = REPO_ROOT / "scripts" / "make_shipped.py"
SHIPPED = REPO_ROOT / "immnet" / "pretrained"


@pytest.fixture
def script():
    spec = importlib.util.spec_from_file_location("make_shipped", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _rows(avgs: dict) -> dict:
    return {name: {"rmse": {"x": v, "y": v, "z": v, "avg": v}} for name, v in avgs.items()}


def test_claims_are_the_ratio_to_the_bound_or_to_the_best_model_based_filter_rounded_up(script):
    """On 3D-LAST (a clairvoyant row) the claim is the ratio to the bound; elsewhere to the best of the model-based
    filters (``real-*``, ``imm-*``), never to the raw measurements or another network, rounded up to 0.01 so that
    the test holding the file to it cannot fail on the file's own score."""
    last = script.claims(_rows({"measurements": 4.0, "clairvoyant": 2.0, "imm-tuned": 2.3, "immnet": 2.101}),
                         "immnet")
    assert last == {"ratio_to_clairvoyant": 1.06}  # 1.0505 up
    real = script.claims(_rows({"measurements": 2.0, "real-imm-singer": 2.619, "real-imm-axis": 2.645,
                                "imm-ekf": 3.022, "immnet-general": 2.4, "immnet-real": 2.546}), "immnet-real")
    assert real == {"ratio_to_best_model_based": math.ceil(100 * 2.546 / 2.619) / 100,
                    "best_model_based": "real-imm-singer"}
    assert real["ratio_to_best_model_based"] == 0.98


def _shipped_copy(tmp_path, name: str, registry: str):
    out = tmp_path / "pretrained"
    out.mkdir()
    shutil.copy(SHIPPED / f"{registry}.ckpt", out)
    shutil.copy(SHIPPED / f"provenance-{name}.json", out)
    return out


def test_rescore_refuses_weights_its_provenance_does_not_describe(script, tmp_path, monkeypatch, capsys):
    """A shipped file whose bytes are not the ones its provenance's ``weights_sha256`` names is refused by name
    before anything is scored, and the provenance is left as it was."""
    out = _shipped_copy(tmp_path, "real", "immnet-real")
    prov = json.loads((out / "provenance-real.json").read_text())
    prov["weights_sha256"] = "0" * 64
    (out / "provenance-real.json").write_text(json.dumps(prov))
    before = (out / "provenance-real.json").read_bytes()
    monkeypatch.setattr(script, "OUT", out)
    with pytest.raises(SystemExit) as e:
        script.main(["--name", "real", "--rescore"])
    assert e.value.code == 2
    assert "weights_sha256 differs" in capsys.readouterr().err
    assert (out / "provenance-real.json").read_bytes() == before
    assert not (out / "PROVENANCE-real.md").exists()


@pytest.mark.parametrize("extra", [["--note", "x"], ["--commit", "HEAD~1"], ["--wandb-runs", "abc"],
                                   ["--checkpoint", "runs/x.ckpt"]])
def test_rescore_refuses_options_that_would_rewrite_the_training_record(script, extra, capsys):
    with pytest.raises(SystemExit) as e:
        script.main(["--name", "real", "--rescore", *extra])
    assert e.value.code == 2
    assert "--rescore keeps the shipped provenance's training record" in capsys.readouterr().err


def test_rescore_keeps_the_training_record_and_the_weights_and_records_when_it_scored(script, tmp_path, monkeypatch):
    """``--rescore`` on a copy of the shipped ``real`` (its test sets replaced by a small generated one): the weights'
    bytes unchanged, every field of the training record (recipe, init, commit, date, data, W&B runs, note) as it
    was, the new set's metrics and claims written, and ``scored`` naming today's commit."""
    out = _shipped_copy(tmp_path, "real", "immnet-real")
    weights = (out / "immnet-real.ckpt").read_bytes()
    kept = json.loads((out / "provenance-real.json").read_text())
    data = write_dataset(tmp_path / "small", 4, 3, DataSpec(T=40, min_segment=12), progress=False)
    ship = dict(script.SHIPS["real"], tests={"small": (str(data), ["measurements", "real-imm-singer", "immnet-real"])})
    monkeypatch.setattr(script, "OUT", out)
    monkeypatch.setitem(script.SHIPS, "real", ship)
    assert script.main(["--name", "real", "--rescore"]) == 0

    assert (out / "immnet-real.ckpt").read_bytes() == weights
    prov = json.loads((out / "provenance-real.json").read_text())
    for field in ("file", "weights_sha256", "recipe", "init", "made_by", "date", "commit", "data", "guard",
                  "scan_interval", "interval_range", "settings", "wandb", "note"):
        assert prov[field] == kept[field], field
    assert list(prov["tests"]) == ["small"]
    small = prov["tests"]["small"]
    assert small["n"] == 4 and set(small["metrics"]) == {"measurements", "real-imm-singer", "immnet-real"}
    avg = {n: m["avg"] for n, m in small["metrics"].items()}
    assert small["claims"] == {"ratio_to_best_model_based": math.ceil(100 * avg["immnet-real"]
                                                                      / avg["real-imm-singer"]) / 100,
                               "best_model_based": "real-imm-singer"}
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO_ROOT, capture_output=True, text=True).stdout.strip()
    assert prov["scored"]["commit"] == head
    assert prov["scored"]["by"].endswith("make_shipped.py --name real --rescore")
    md = (out / "PROVENANCE-real.md").read_text()
    assert kept["weights_sha256"] in md and f"scored again at commit `{head[:10]}`" in md
    assert "gu82meid" in md  # the training's W&B run, read from the kept record
