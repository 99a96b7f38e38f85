"""Generation sharded across machines (``generate --shard i/K``) and ``immnet data merge``."""

import json
import shutil

import pytest

import immnet.cli
from immnet.data import shards as shards_mod
from immnet.data.generate import BLOCK
from immnet.data.shards import merge_shards
from immnet.data.spec import DataSpec
from immnet.data.storage import load_dataset, shard_blocks, shard_rows, write_dataset

SPEC = DataSpec(T=50, min_segment=10)
N = 2 * BLOCK + 150  # three blocks, the last one partial


def _files(d):
    return {p.relative_to(d).as_posix(): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


@pytest.fixture()
def main(monkeypatch):
    monkeypatch.setattr(immnet.cli, "_COMMAND_MODULES", ("immnet.data.cli",))
    return immnet.cli.main


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """Shards 0, 1, 2 of 3 (written through the CLI) and the same N and seed written in one go."""
    d = tmp_path_factory.mktemp("shards")
    cfg = d / "spec.yaml"
    cfg.write_text("T: 50\nmin_segment: 10\n")
    old = immnet.cli._COMMAND_MODULES
    immnet.cli._COMMAND_MODULES = ("immnet.data.cli",)
    try:
        for i in range(3):
            assert immnet.cli.main(["data", "generate", "--n", str(N), "--seed", "5", "--config", str(cfg),
                                    "--shard", f"{i}/3", "--out", str(d / f"s{i}"), "--quiet"]) == 0
    finally:
        immnet.cli._COMMAND_MODULES = old
    whole = write_dataset(d / "whole", N, seed=5, spec=SPEC)
    return d, [d / f"s{i}" for i in range(3)], whole


def test_shard_rule_is_contiguous_whole_blocks():
    for n_blocks_, K in ((10, 3), (7, 7), (5, 1), (9, 4)):
        n = n_blocks_ * BLOCK - 1
        parts = [shard_blocks(n, i, K) for i in range(K)]
        assert [b for p in parts for b in p] == list(range(n_blocks_))
        assert max(map(len, parts)) - min(map(len, parts)) <= 1
    assert [list(shard_blocks(10 * BLOCK, i, 3)) for i in range(3)] == [[0, 1, 2], [3, 4, 5], [6, 7, 8, 9]]
    assert shard_rows(N, 2, 3) == (2 * BLOCK, N)


def test_merged_shards_equal_one_go_byte_for_byte(made, main, tmp_path, capsys):
    d, parts, whole = made
    for i, p in enumerate(parts):
        td, meta = load_dataset(p)  # each shard is a complete, valid data set
        a, b = shard_rows(N, i, 3)
        assert meta["n"] == b - a == td.batch_size[0] and meta["seed"] == 5
        assert meta["shard"] == {"index": i, "count": 3, "n_total": N, "rows": [a, b], "blocks": [i, i + 1]}
    out = tmp_path / "merged"
    assert main(["data", "merge", "--out", str(out), *map(str, parts[::-1]), "--quiet"]) == 0  # any order
    assert "merged 3 shards" in capsys.readouterr().out
    assert _files(out) == _files(whole)  # tensors and meta.json alike
    assert [p.name for p in tmp_path.iterdir()] == ["merged"]
    # the output exists now: a second merge needs --overwrite
    assert main(["data", "merge", "--out", str(out), *map(str, parts), "--quiet"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert merge_shards(out, parts, overwrite=True) == out and _files(out) == _files(whole)


def _shard_copy(src, dst, **meta_changes):
    shutil.copytree(src, dst)
    meta = json.loads((dst / "meta.json").read_text())
    for k, v in meta_changes.items():
        if k in meta.get("shard", {}) and k not in meta:
            meta["shard"][k] = v
        else:
            meta[k] = v
    (dst / "meta.json").write_text(json.dumps(meta))
    return dst


def test_merge_errors_name_the_problem(made, tmp_path):
    d, (s0, s1, s2), whole = made
    other_seed = write_dataset(tmp_path / "seed6", N, seed=6, spec=SPEC, shard=(2, 3))
    other_spec = write_dataset(tmp_path / "t40", N, seed=5, spec=DataSpec(T=40, min_segment=10), shard=(2, 3))
    overlap = _shard_copy(s1, tmp_path / "overlap", rows=[BLOCK - 96, 2 * BLOCK - 96])
    cases = [
        ([s0, s1], r"missing shard\(s\) 2 of 3"),
        ([s0, s1, s1, s2], "shard 1 of 3 is given twice"),
        ([s0, s1, other_seed], "seed differs"),
        ([s0, s1, other_spec], "T differs"),
        ([s0, overlap, s2], r"overlaps shard .*s0"),
        ([s0, s1, whole], "whole is not a shard"),
        ([s0, s1, tmp_path / "nowhere"], "nowhere is not a data set directory"),
    ]
    for dirs, msg in cases:
        with pytest.raises((ValueError, FileNotFoundError), match=msg):
            merge_shards(tmp_path / "out", dirs)
        assert not (tmp_path / "out").exists()
    with pytest.raises(ValueError, match="one of the shards"):
        merge_shards(s0, [s0, s1, s2], overwrite=True)


def test_merge_failure_leaves_nothing(made, tmp_path, monkeypatch):
    _, parts, _ = made

    def boom(*a, **k):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(shards_mod, "_write_meta", boom)
    with pytest.raises(RuntimeError):
        merge_shards(tmp_path / "out", parts)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "shard, msg",
    [("3/3", r"shard index 3 is out of range for 3 shards \(valid: 0..2\)"),
     ("0/4", "3 block.*cannot be split into 4 shards"),
     ("0/0", "shard count must be >= 1")],
    ids=["index-past-count", "more-shards-than-blocks", "zero-shards"],
)
def test_generate_shard_errors(main, tmp_path, capsys, shard, msg):
    assert main(["data", "generate", "--n", str(N), "--seed", "1", "--shard", shard,
                 "--out", str(tmp_path / "x"), "--quiet"]) == 2
    import re

    assert re.search(msg, capsys.readouterr().err)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(SystemExit):
        main(["data", "generate", "--n", "5", "--seed", "1", "--shard", "1of3", "--out", str(tmp_path / "x")])


def test_shards_written_before_scan_times_merge_with_scans_at_k_dt(made, tmp_path):
    """Shards without a t memmap (written before scan times were stored) merge into the bytes of the
    whole set: their t is k dt, the generator's t at a fixed interval."""
    from immnet.data.storage import TENSORS, as_batch

    _, shard_dirs, whole = made
    old = []
    for i, s in enumerate(shard_dirs):
        dst = tmp_path / f"old{i}"
        shutil.copytree(s, dst)
        td, _ = load_dataset(dst)
        plain = as_batch(td.exclude("t")).clone()
        del td
        shutil.rmtree(dst / TENSORS)
        plain.memmap_(dst / TENSORS)
        assert "t" not in load_dataset(dst)[0].keys()
        old.append(dst)
    merged, _ = load_dataset(merge_shards(tmp_path / "merged", old))
    ref, _ = load_dataset(whole)
    for k in ref.keys():
        assert (merged[k].contiguous() == ref[k].contiguous()).all(), k
