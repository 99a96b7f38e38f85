"""A non-editable install run from outside the checkout (docs/configs.md).

The wheel is built from a copy of the sources (the checkout stays untouched) and installed, not
editable, into a fresh virtual environment of the base interpreter. Its only link to the test
environment is one path line to the test environment's site-packages, for the dependencies (no
network, no index): a path line, not a site directory, so no ``.pth`` file there runs and an editable
install of the checkout stays out of sight. The commands run through the installed ``immnet`` script,
from a temporary directory, without ``PYTHONPATH``.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import site
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import numpy as np
import pytest
import yaml

from immnet.cli import main

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("imm-tuned", "imm-ekf", "immnet")


def _env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    return {**env, "PYTHONNOUSERSITE": "1", "OMP_NUM_THREADS": "1", "WANDB_MODE": "offline", "WANDB_SILENT": "true"}


def _run(cmd, cwd) -> str:
    done = subprocess.run([str(c) for c in cmd], cwd=cwd, env=_env(), capture_output=True, text=True)
    assert done.returncode == 0, f"{cmd} failed ({done.returncode}):\n{done.stdout}\n{done.stderr}"
    return done.stdout


@pytest.fixture(scope="module")
def install(tmp_path_factory):
    """``(wheel, python, immnet script, site-packages, working directory)`` of a fresh install."""
    base = tmp_path_factory.mktemp("install")
    src = base / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    for name in ("immnet", "configs", "recipes"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-index", "--no-build-isolation",
          "-w", base / "wheel", src], cwd=base)
    (wheel,) = (base / "wheel").glob("immnet-*.whl")
    env_dir = base / "venv"
    venv.EnvBuilder(with_pip=False, symlinks=os.name != "nt").create(env_dir)
    python = env_dir / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
    purelib = Path(_run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], cwd=base).strip())
    deps = dict.fromkeys([*site.getsitepackages(), sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]])
    (purelib / "_test_environment.pth").write_text("".join(f"{p}\n" for p in deps))
    _run([python, "-m", "pip", "install", "-q", "--no-deps", "--no-index", "--ignore-installed", wheel], cwd=base)
    script = python.parent / ("immnet.exe" if os.name == "nt" else "immnet")
    cwd = base / "elsewhere"
    cwd.mkdir()
    return wheel, python, script, purelib, cwd


def test_the_wheel_holds_the_package_its_configs_and_weights(install):
    """Issue 21, item 4: the method registry and configs ship inside the package: every module, every
    YAML of configs/ (as immnet/configs/), every recipe (as immnet/recipes/) and the shipped weights are in the wheel."""
    names = set(zipfile.ZipFile(install[0]).namelist())
    want = {p.relative_to(ROOT).as_posix() for p in (ROOT / "immnet").rglob("*.py") if "__pycache__" not in p.parts}
    want |= {"immnet/configs/" + p.relative_to(ROOT / "configs").as_posix() for p in (ROOT / "configs").rglob("*.yaml")}
    want |= {"immnet/recipes/" + p.name for p in (ROOT / "recipes").glob("*.yaml")}
    want |= {p.relative_to(ROOT).as_posix() for p in (ROOT / "immnet" / "pretrained").iterdir() if p.is_file()}
    assert "immnet/configs/methods/imm-tuned.yaml" in want and "immnet/pretrained/immnet.ckpt" in want
    assert sorted(want - names) == []


def test_the_installed_package_works_outside_the_checkout(install, tmp_path, monkeypatch):
    """Issue 21, item 4 ("works only from a checkout"): after ``pip install`` of the wheel, from another
    directory, ``immnet data generate`` (with a packaged ``--config``), ``immnet evaluate --methods
    imm-tuned,imm-ekf,immnet``, ``immnet track`` and ``immnet tune-imm`` work, with the installed copy
    (not the checkout) imported; the installed copy's results equal the checkout's on the same data, and
    tune-imm writes into the working directory, not into site-packages."""
    _, python, immnet, purelib, cwd = install
    where = Path(_run([python, "-c", "import immnet; print(immnet.__file__)"], cwd).strip())
    assert where.is_relative_to(purelib) and not where.is_relative_to(ROOT)
    # an ablation's chain finds its base recipe among the installed package's recipes
    found = _run([python, "-c", "from immnet.config import resolve_path; import yaml; from immnet.training.cli import "
                  "stage_entry; s = yaml.safe_load(resolve_path('configs/ablations/no-guard.yaml').read_text())['stages'][0]; "
                  "print(resolve_path(stage_entry(s, 0)[0][0]))"], cwd).strip()
    assert Path(found).is_relative_to(purelib) and found.endswith("recipes/quick-stage2.yaml")

    _run([immnet, "data", "generate", "--out", "d", "--n", "40", "--seed", "3", "--config", "configs/data/tiny.yaml",
          "--quiet"], cwd)
    meta = json.loads((cwd / "d" / "meta.json").read_text())
    tiny = yaml.safe_load((ROOT / "configs" / "data" / "tiny.yaml").read_text())
    assert meta["n"] == 40 and meta["T"] == tiny["T"] == 50

    evaluate = ["evaluate", "--data", cwd / "d", "--split", "all", "--methods", ",".join(METHODS), "--quiet"]
    _run([immnet, *evaluate, "--json", "r.json"], cwd)
    rows = json.loads((cwd / "r.json").read_text())["methods"]
    assert sorted(rows) == sorted(METHODS)
    assert all(math.isfinite(rows[m]["rmse"][a]) for m in METHODS for a in ("x", "y", "z", "avg"))
    _run([immnet, "data", "export", "--data", "d", "--out", "m.npz"], cwd)
    _run([immnet, "track", "--input", "m.npz", "--output", "o.npz"], cwd)
    with np.load(cwd / "o.npz") as out:
        state = out["state"]
    assert state.shape == (40, 50, 9) and np.isfinite(state[:, 1:]).all()

    # the checkout, run in this process on the same data, gives the same numbers
    monkeypatch.chdir(tmp_path)
    assert main([*map(str, evaluate), "--json", str(tmp_path / "r.json")]) == 0
    untimed = lambda r: {m: {k: v for k, v in row.items() if k != "seconds"} for m, row in r.items()}  # noqa: E731
    assert untimed(json.loads((tmp_path / "r.json").read_text())["methods"]) == untimed(rows)
    assert main(["track", "--input", str(cwd / "m.npz"), "--output", str(tmp_path / "o.npz")]) == 0
    with np.load(tmp_path / "o.npz") as out:
        assert np.array_equal(out["state"], state, equal_nan=True)

    packaged = _run([python, "-c", "import immnet.config as c; print(c.packaged_configs(), c.checkout())"], cwd)
    assert packaged.split() == [str(purelib / "immnet" / "configs"), "None"]
    shipped = purelib / "immnet" / "configs" / "methods" / "imm-tuned.yaml"
    before = shipped.read_bytes()
    _run([immnet, "tune-imm", "--data", "d", "--n", "20"], cwd)
    tuned = yaml.safe_load((cwd / "configs" / "methods" / "imm-tuned.yaml").read_text())
    assert tuned["class_path"] == "immnet.filters.IMMTracker"
    assert shipped.read_bytes() == before == (ROOT / "configs" / "methods" / "imm-tuned.yaml").read_bytes()
