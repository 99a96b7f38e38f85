"""The one table of shipped weights (``immnet/pretrained/weights.json``) against the files it names: each file's
weights and their checksum, the scan intervals each network serves and its range guard, its provenance; a file whose
weights are not the table's is refused at load."""

from __future__ import annotations

import json

import pytest

from immnet import checkpoints
from immnet.checkpoints import CheckpointError, load_checkpoint, shipped, weights_checksum


@pytest.mark.parametrize("name", list(checkpoints.WEIGHTS))
def test_each_table_entry_is_the_file_it_names(name):
    from immnet.tracking.networks import guarded, load_network, provenance_of

    entry = checkpoints.WEIGHTS[name]
    path = shipped(name)
    ckpt = load_checkpoint(path)
    assert weights_checksum(ckpt["state_dict"]) == entry["weights_sha256"]  # recomputed from the weights
    net = load_network(path)
    span = net.interval_range if net.interval_range is not None else (net.dt, net.dt)
    assert [float(v) for v in span] == [float(v) for v in entry["scans"]]
    assert guarded(net) == entry["guard"]
    assert (path.parent / entry["provenance"]).is_file()
    assert provenance_of(path) == f"provenance immnet/pretrained/{entry['provenance']}"
    prov = json.loads((path.parent / entry["provenance_json"]).read_text())
    assert prov.get("weights_sha256", entry["weights_sha256"]) == entry["weights_sha256"]


def test_the_bank_and_the_default_are_the_tables():
    bank = checkpoints.TABLE["bank"]
    assert set(bank["members"]) <= set(checkpoints.SHIPPED)
    assert checkpoints.BANK_MEMBERS == tuple(bank["members"]) and checkpoints.DEFAULT_WEIGHTS == checkpoints.TABLE["default"]
    assert (checkpoints.PRETRAINED.parent / bank["provenance"]).is_file()
    from immnet.tracking.bank import DEFAULT_MEMBERS, DEFER, LIKELIHOOD, LIKELIHOODS, PRUNE, PRUNE_AFTER, TEMPER

    # how the bank weighs and runs its members is the table's too, and the method immnet-bank says none of it again
    assert (LIKELIHOOD, TEMPER, PRUNE, PRUNE_AFTER) == (bank["likelihood"], bank["temper"], bank["prune"],
                                                       bank["prune_after"]) and LIKELIHOOD in LIKELIHOODS
    assert DEFER == {k: tuple(v) for k, v in bank["defer"].items()} and set(DEFER) <= set(bank["members"])
    from immnet.config import load_yaml
    from immnet.filters.methods import method_config

    assert set(load_yaml(method_config("immnet-bank"))["init_args"]) == {"name", "guard"}

    assert DEFAULT_MEMBERS == tuple(bank["members"])


def test_a_file_whose_weights_are_not_the_tables_is_refused_by_name(monkeypatch):
    entry = dict(checkpoints.WEIGHTS["real"], weights_sha256="0" * 64)
    table = dict(checkpoints.TABLE, weights=[entry if e["name"] == "real" else e for e in checkpoints.TABLE["weights"]])
    monkeypatch.setattr(checkpoints, "TABLE", table)
    with pytest.raises(CheckpointError, match=r"its weights are not the ones weights.json ships under 'real'") as err:
        load_checkpoint(shipped("real"))
    assert "\n" not in str(err.value)
    load_checkpoint(shipped("general"))  # the others load


def test_an_export_writes_its_checksum_into_the_table(monkeypatch, tmp_path):
    import copy

    table = tmp_path / "weights.json"
    truth = checkpoints.WEIGHTS["real"]["weights_sha256"]
    table.write_text(checkpoints.WEIGHTS_TABLE.read_text().replace(truth, "f" * 64))
    weights = copy.deepcopy(checkpoints.WEIGHTS)
    weights["real"]["weights_sha256"] = "f" * 64
    monkeypatch.setattr(checkpoints, "WEIGHTS_TABLE", table)
    monkeypatch.setattr(checkpoints, "WEIGHTS", weights)
    assert checkpoints.record_shipped("real") == truth
    assert json.loads(table.read_text())["weights"][2]["weights_sha256"] == truth
    assert table.read_text().count("f" * 64) == 0
