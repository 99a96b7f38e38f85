"""benchmarks/common.py's section rewrite: a rerun replaces a section's measured text and keeps everything else."""

import argparse
import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def _load(name: str):
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location(f"bench_{name}_under_test", BENCH / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod
    finally:
        sys.path.remove(str(BENCH))


DOC = """# Benchmarks

## Filters

old filters

## IMMNet

old numbers

### Reading the IMMNet tables

notes written by hand

## Modes per group

old modes
"""


def test_write_section_replaces_measured_text_and_keeps_notes(tmp_path):
    common = _load("common")
    path = tmp_path / "B.md"
    path.write_text(DOC)
    common.write_section("IMMNet", "new numbers", path)
    common.write_section("Modes per group", "new modes", path)
    common.write_section("IMMNet on cuda", "gpu numbers", path)
    assert path.read_text() == DOC.replace("old numbers", "new numbers").replace("old modes", "new modes") + (
        "\n## IMMNet on cuda\n\ngpu numbers\n")


def test_bench_immnet_parts_refuses_unknown_names():
    bench = _load("bench_immnet")
    assert bench.parts("inference, stages") == ("inference", "stages")
    with pytest.raises(argparse.ArgumentTypeError, match="unknown part.*'gpu'.*training, inference, stages"):
        bench.parts("inference,gpu")
