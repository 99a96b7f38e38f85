"""``scripts/learned_residual.py`` (docs/immnet.md "The output correction"): the filter row is
``immnet evaluate``'s score, an untrained correction is none, the corrected estimate at scan t reads nothing after
t, and a short run trains and reports."""

import json
import runpy

import pytest
import torch

from immnet import keys
from immnet.config import REPO_ROOT, instantiate, load_yaml
from immnet.data.storage import as_batch, load_dataset, write_dataset
from immnet.filters.methods import build_method, method_config
from immnet.evaluation.search import average_rmse
from tests.tiny_runs import TINY

SCRIPT = REPO_ROOT / "scripts" / "learned_residual.py"


@pytest.fixture(scope="module")
def residual():
    return runpy.run_path(str(SCRIPT))


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("residual")
    for name, n, seed in (("train", 12, 3), ("val", 6, 4), ("test", 6, 5)):
        write_dataset(root / name, n, seed=seed, spec=TINY)
    return root


def _method(name="real-imm-singer"):
    config = load_yaml(method_config(name))
    config.setdefault("init_args", {})["return_cov"] = True
    return instantiate(config)


def test_an_untrained_correction_leaves_the_filter_as_evaluate_scores_it(residual, data):
    batch = as_batch(load_dataset(data / "test")[0])
    part = residual["prepared"](_method(), batch)
    model = residual["Residual"](part["feats"].shape[-1], hidden=16)  # its output layer starts at zero
    state = residual["predict"](model, part)
    assert torch.equal(state, part["state"])
    score, axes = residual["average"](state, batch)
    assert score == pytest.approx(average_rmse(build_method("real-imm-singer"), batch), rel=1e-12)
    assert sum(axes) / 3 == pytest.approx(score, rel=1e-12)


def test_the_corrected_estimate_at_a_scan_reads_nothing_after_it(residual, data):
    batch = as_batch(load_dataset(data / "test")[0])
    torch.manual_seed(0)
    model = residual["Residual"](30, hidden=16)
    torch.nn.init.normal_(model.out.weight)  # a correction that is not zero
    t = 17
    later = batch.clone()
    z = later[keys.MEASUREMENTS].clone()
    z[:, t + 1 :] += 50.0 * torch.randn_like(z[:, t + 1 :])
    later[keys.MEASUREMENTS] = z
    method = _method()
    a = residual["predict"](model, residual["prepared"](method, batch))
    b = residual["predict"](model, residual["prepared"](method, later))
    assert (a[:, : t + 1] - residual["prepared"](method, batch)["state"][:, : t + 1]).abs().max() > 1e-3
    torch.testing.assert_close(a[:, : t + 1], b[:, : t + 1], rtol=0, atol=1e-9)
    assert (a[:, t + 1 :] - b[:, t + 1 :]).abs().max() > 1.0


def test_a_short_run_trains_chooses_on_validation_and_scores_each_test_set(residual, data, tmp_path):
    out = tmp_path / "residual.json"
    rc = residual["main"](["--train", str(data / "train"), "--val", str(data / "val"), "--test", str(data / "test"),
                           "--epochs", "2", "--views", "1", "--batch", "4", "--hidden", "16", "--json", str(out)])
    assert rc == 0
    report = json.loads(out.read_text())
    val, test = report["rows"]
    assert val["corrected"] == pytest.approx(min(h["val"] for h in report["history"]))
    batch = as_batch(load_dataset(data / "test")[0])
    assert test["filter"] == pytest.approx(average_rmse(build_method("real-imm-singer"), batch), rel=1e-12)
    assert test["corrected"] > 0 and len(report["history"]) == 2
