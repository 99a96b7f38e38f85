"""A newcomer's first minute (issue 60, item 11): ``immnet --help`` and each command's help build without torch,
Lightning or wandb (their CPU time is in BENCHMARKS.md, "CLI help")."""

from __future__ import annotations

import inspect
import os
import subprocess
import sys
from pathlib import Path

import pytest

import immnet
from immnet.cli import main

HEAVY = ("torch", "lightning", "wandb", "tensordict", "torchrl", "scipy", "matplotlib")
SOURCE = str(Path(immnet.__file__).resolve().parents[1])


def _python(code: str, cwd=None) -> subprocess.CompletedProcess:
    """``code`` run by a fresh interpreter on this checkout's package."""
    path = os.pathsep.join(p for p in (SOURCE, os.environ.get("PYTHONPATH")) if p)
    env = {**os.environ, "PYTHONPATH": path, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=120)


def test_building_the_parser_imports_no_heavy_module():
    done = _python(f"import sys; from immnet.cli import build_parser; build_parser(); "
                   f"print(sorted(m for m in {HEAVY!r} if m in sys.modules))")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


@pytest.mark.parametrize("argv", [["--help"], ["track", "--help"], ["evaluate", "--help"], ["tune", "--help"],
                                  ["tune-imm", "--help"], ["data", "--help"], ["data", "generate", "--help"]])
def test_help_exits_0_without_heavy_modules(argv):
    """Through ``main`` as the ``immnet`` command runs it: usage on stdout, exit 0, nothing heavy imported."""
    done = _python(f"import sys\nfrom immnet.cli import main\ntry:\n    main({argv!r})\nexcept SystemExit as e:\n"
                   f"    code = e.code\nprint('EXIT', code, sorted(m for m in {HEAVY!r} if m in sys.modules))")
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: immnet")
    assert done.stdout.strip().splitlines()[-1] == "EXIT 0 []"


def test_help_in_process_exits_0(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["data", "generate", "--help"])
    assert exit_.value.code == 0
    assert "--single-mode {cv,ca,ct+,ct-}" in capsys.readouterr().out


def test_lazy_package_names_are_the_real_ones():
    """The packages load their names on first use: the same objects as their modules'."""
    import immnet.data
    import immnet.evaluation
    import immnet.tracking
    from immnet.data.storage import load_dataset
    from immnet.evaluation.runner import evaluate
    from immnet.tracking.tracker import Tracker

    assert immnet.data.load_dataset is load_dataset and immnet.evaluation.evaluate is evaluate
    assert immnet.tracking.Tracker is Tracker
    for package in (immnet.data, immnet.evaluation, immnet.tracking):
        for name in package.__all__:
            assert getattr(package, name) is not None, (package.__name__, name)
        with pytest.raises(AttributeError, match="no attribute 'nope'"):
            package.nope  # noqa: B018


def test_generate_stays_the_function_after_its_module_is_imported():
    """``from immnet.data import generate`` is the function even where the module ``immnet.data.generate`` was
    imported first (by ``immnet.data.storage``), in a fresh interpreter."""
    done = _python("import sys, immnet.data.storage\nfrom immnet.data import generate\n"
                   "print(callable(generate), type(generate).__name__, type(sys.modules['immnet.data.generate']).__name__)")
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["True", "function", "module"]


def test_select_methods_default_guard_keeps_each_as_configured():
    from immnet.evaluation.cli import select_methods
    from immnet.filters.methods import AS_CONFIGURED

    assert inspect.signature(select_methods).parameters["guard"].default == AS_CONFIGURED


def _evaluate_help_names(capsys, monkeypatch) -> list[str]:
    monkeypatch.setenv("COLUMNS", "100000")  # one line per option: no name broken at a hyphen
    with pytest.raises(SystemExit) as exit_:
        main(["evaluate", "--help"])
    assert exit_.value.code == 0
    line = next(t for t in capsys.readouterr().out.splitlines() if t.lstrip().startswith("--methods"))
    listed = line.split(" of: ", 1)[1].split(" (the built-in", 1)[0]
    return listed.split(", ")


def test_evaluate_help_lists_exactly_the_methods_it_accepts(capsys, monkeypatch, tmp_path):
    """Issue 60, item 11: ``immnet evaluate --help`` names the methods, the working directory's own configs too; each
    name listed is one ``--methods`` takes (its config found, its class imported), and each it takes is listed."""
    from immnet.evaluation.cli import select_methods
    from immnet.filters.methods import BUILTIN, _method_class, available_methods
    from immnet.filters.registry import BUILTIN_NAMES, METHODS_DIR

    (tmp_path / "configs/methods").mkdir(parents=True)
    (tmp_path / "configs/methods/mine.yaml").write_text("class_path: immnet.filters.methods.RawMeasurements\n")
    monkeypatch.chdir(tmp_path)
    listed = _evaluate_help_names(capsys, monkeypatch)
    packaged = sorted(p.stem for p in Path(METHODS_DIR).glob("*.yaml"))
    assert len(packaged) > 10 and set(listed) == {*packaged, "mine", "measurements"} and len(listed) == len(set(listed))
    assert listed == available_methods()  # every one accepted, in table order
    for name in listed:
        assert _method_class(name)[0] is not None
    assert select_methods("mine", [], ["measurements"])["mine"].name == "mine"
    with pytest.raises(ValueError, match="unknown method 'nope'"):
        select_methods("nope", [], ["measurements"])
    assert set(BUILTIN) == set(BUILTIN_NAMES)


def test_track_help_shows_the_weights_default_and_every_name(capsys, monkeypatch):
    """Issue 60, item 11: ``--weights`` shows its real default (the bank, what ``immnet track`` loads when told no
    weights) and describes each name it takes; no option claims a default of None."""
    from immnet.checkpoints import BANK, BANK_MEMBERS, DEFAULT_WEIGHTS, SHIPPED
    from immnet.cli import build_parser
    from immnet.tracking.bank import DEFAULT_MEMBERS
    from immnet.tracking.cli import _weights

    monkeypatch.setenv("COLUMNS", "100000")
    with pytest.raises(SystemExit) as exit_:
        main(["track", "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert "None" not in out
    lines = out.splitlines()
    at = next(i for i, t in enumerate(lines) if t.lstrip().startswith("--weights"))
    names = {*SHIPPED, BANK}
    assert lines[at].split()[1] == "{" + ",".join(sorted(names)) + "}"  # the names it takes
    line = lines[at + 1]  # its help, on one line
    assert f"shipped weights by name (default {DEFAULT_WEIGHTS}); {DEFAULT_WEIGHTS}: " in line
    described = "; " + line.split(f"(default {DEFAULT_WEIGHTS}); ", 1)[1]
    for name in names:
        assert f"; {name}: " in described, name
    assert f"{BANK}: {', '.join(DEFAULT_MEMBERS)} as one tracker" in line and BANK_MEMBERS == DEFAULT_MEMBERS
    # the default the help names is what the command runs with no --weights: the bank (no single file)
    args = build_parser().parse_args(["track", "--input", "a.csv", "--output", "b.csv"])
    assert DEFAULT_WEIGHTS == BANK and _weights(args) is None
    for name in SHIPPED:
        assert build_parser().parse_args(["track", "--input", "a.csv", "--output", "b.csv", "--weights", name]).weights == name
