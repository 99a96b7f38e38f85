"""``scripts/bank_weighing.py`` (docs/tracking.md "A bank of networks"): each cell is the bank with that weighing,
scored as ``immnet evaluate`` scores it."""

import json
import runpy

import pytest

from immnet.config import REPO_ROOT
from immnet.data.storage import as_batch, load_dataset, write_dataset
from immnet.filters.methods import build_method
from immnet.evaluation.search import average_rmse
from immnet.tracking.bank import BankMethod
from tests.tiny_runs import TINY


def test_each_cell_is_the_bank_so_weighed(tmp_path, capsys):
    mod = runpy.run_path(str(REPO_ROOT / "scripts" / "bank_weighing.py"))
    write_dataset(tmp_path / "d", 6, seed=2, spec=TINY)
    out = tmp_path / "w.json"
    assert mod["main"](["--data", str(tmp_path / "d"), "--json", str(out)]) == 0
    rows = json.loads(out.read_text())
    batch = as_batch(load_dataset(tmp_path / "d")[0])
    cell = rows["filter, temper 1"][str(tmp_path / "d")]
    assert cell == pytest.approx(average_rmse(BankMethod(likelihood="filter", temper=1.0), batch), rel=1e-12)
    # the shipped weighing is the registry's immnet-bank
    shipped = rows["reported, temper 0.5"][str(tmp_path / "d")]
    assert shipped == pytest.approx(average_rmse(build_method("immnet-bank"), batch), rel=1e-12)
    assert len(rows) == 4 and "| reported, temper 0.5 |" in capsys.readouterr().out
