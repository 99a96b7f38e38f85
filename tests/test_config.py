"""Where a config path is found (immnet.config.resolve_path; docs/configs.md)."""

from pathlib import Path

import pytest
import yaml

from immnet.config import REPO_ROOT, checkout, packaged_configs, resolve_path
from immnet.motion import ModelSet


def test_packaged_configs_are_found_from_any_directory(tmp_path, monkeypatch):
    """Issue 21, item 4: a packaged config is found from a directory that does not hold it, with or
    without the leading ``configs/``; in a checkout the packaged configs are its ``configs/``."""
    monkeypatch.chdir(tmp_path)
    assert checkout() == REPO_ROOT and packaged_configs() == REPO_ROOT / "configs"
    want = REPO_ROOT / "configs" / "model_sets" / "imm6.yaml"
    assert resolve_path("configs/model_sets/imm6.yaml") == want
    assert resolve_path("model_sets/imm6.yaml") == want
    classes = [m["class_path"].rsplit(".", 1)[1] for m in yaml.safe_load(want.read_text())["models"]]
    assert [type(m).__name__ for m in ModelSet.from_config("model_sets/imm6.yaml")] == classes


def test_a_users_file_wins_over_the_packaged_one(tmp_path, monkeypatch):
    """Issue 21, item 4: a path that exists as given wins; the same name elsewhere is the packaged file."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "configs" / "model_sets").mkdir(parents=True)
    mine = Path("configs/model_sets/imm6.yaml")
    mine.write_text(yaml.safe_dump(yaml.safe_load((REPO_ROOT / "configs/model_sets/imm3.yaml").read_text())))
    assert resolve_path(mine) == mine and len(ModelSet.from_config(mine)) == 3
    assert len(ModelSet.from_config("model_sets/imm6.yaml")) == 6


def test_a_missing_config_names_every_place_looked_in(tmp_path, monkeypatch):
    """Issue 21, item 4: one FileNotFoundError that lists the working directory and the packaged configs."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(FileNotFoundError) as err:
        resolve_path("configs/data/no-such.yaml")
    msg = str(err.value)
    assert "config file not found: configs/data/no-such.yaml" in msg
    assert str(tmp_path / "configs/data/no-such.yaml") in msg
    assert str(packaged_configs() / "data/no-such.yaml") in msg
