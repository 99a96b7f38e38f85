"""``immnet data generate|export|plot`` through ``immnet.cli.main``, in tmp_path."""

import numpy as np
import pytest

import immnet.cli
from immnet.data.storage import load_dataset


@pytest.fixture()
def main(monkeypatch):
    # only the data commands: other packages' CLIs are not under test here
    monkeypatch.setattr(immnet.cli, "_COMMAND_MODULES", ("immnet.data.cli",))
    return immnet.cli.main


def test_generate_export_plot(tmp_path, main, capsys):
    cfg = tmp_path / "small.yaml"
    cfg.write_text("T: 60\nmin_segment: 15\n")
    out = tmp_path / "ds"
    assert main(["data", "generate", "--out", str(out), "--n", "50", "--seed", "3", "--config", str(cfg), "--quiet"]) == 0
    td, meta = load_dataset(out)
    assert td["states"].shape == (50, 60, 9) and meta["spec"]["T"] == 60 and meta["seed"] == 3
    # again without --overwrite: a clean error, exit 2, data untouched
    assert main(["data", "generate", "--out", str(out), "--n", "5", "--seed", "3", "--quiet"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert load_dataset(out)[1]["n"] == 50
    npz = tmp_path / "x.npz"
    assert main(["data", "export", "--data", str(out), "--out", str(npz)]) == 0
    assert np.load(npz)["measurements"].shape == (50, 60, 3)
    for src in (out, npz):
        png = tmp_path / f"plot-{src.name}.png"
        assert main(["data", "plot", "--data", str(src), "--out", str(png), "--n", "20"]) == 0
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # measurements only: plotted from the measurements
    np.savez(tmp_path / "m.npz", measurements=np.random.default_rng(0).normal(size=(4, 10, 3)) * 1e3)
    assert main(["data", "plot", "--data", str(tmp_path / "m.npz"), "--out", str(tmp_path / "m.png")]) == 0


def test_single_mode_and_errors(tmp_path, main, capsys):
    out = tmp_path / "ct"
    assert main(["data", "generate", "--out", str(out), "--n", "20", "--seed", "1", "--single-mode", "ct+",
                 "--quiet"]) == 0
    td, meta = load_dataset(out)
    assert meta["single_mode"] == "ct+" and (td["mode"][:, 0] == 2).all()
    bad = tmp_path / "bad.yaml"
    bad.write_text("T: 60\nwarp_speed: 9\n")
    assert main(["data", "generate", "--out", str(tmp_path / "x"), "--n", "5", "--seed", "1", "--config", str(bad)]) == 2
    assert "warp_speed" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    assert main(["data", "export", "--data", str(tmp_path / "nope"), "--out", str(tmp_path / "y.npz")]) == 2
    np.savez(tmp_path / "bad.npz", states=np.zeros((2, 5, 9)))
    assert main(["data", "plot", "--data", str(tmp_path / "bad.npz"), "--out", str(tmp_path / "b.png")]) == 2
    assert "measurements" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["data", "generate", "--out", str(tmp_path / "z"), "--n", "5", "--seed", "1", "--single-mode", "loop"])


def test_every_data_preset_loads():
    from immnet.config import REPO_ROOT
    from immnet.data.spec import DataSpec

    presets = sorted((REPO_ROOT / "configs" / "data").glob("*.yaml"))
    assert presets
    for p in presets:
        spec = DataSpec.from_yaml(p)
        assert spec.T * spec.dt > 0
    assert DataSpec.from_yaml(REPO_ROOT / "configs/data/paper.yaml") == DataSpec()
