"""Flight phases from the truth (``immnet.evaluation.phases``) on kinematics whose phase is known, and the pooled
RMSE per phase against its float64 definition."""

import math

import pytest
import torch

from immnet.evaluation.phases import PHASES, phases, rmse_by_phase


def _state(vx=150.0, vy=0.0, ax=0.0, ay=0.0, vz=0.0) -> torch.Tensor:
    s = torch.zeros(9, dtype=torch.float64)
    s[1], s[4], s[2], s[5], s[7] = vx, vy, ax, ay, vz
    return s


def test_phases_of_known_kinematics():
    w = math.radians(3.0)  # a coordinated turn: a = w x v
    rows = [_state(), _state(ax=-w * 0.0, ay=w * 150.0), _state(vz=-6.0), _state(ax=1.0),
            _state(ay=w * 150.0, vz=8.0), torch.full((9,), float("nan"), dtype=torch.float64)]
    truth = torch.stack(rows)[None]  # [1, 6, 9]
    m = phases(truth)
    expect = {"level": [1, 0, 0, 0, 0, 0], "turn": [0, 1, 0, 0, 1, 0], "climb/descent": [0, 0, 1, 0, 1, 0],
              "speed change": [0, 0, 0, 1, 0, 0]}
    for name in PHASES:
        assert m[name][0].tolist() == [bool(v) for v in expect[name]], name


def test_rmse_by_phase_pools_the_scored_scans_of_each_phase():
    g = torch.Generator().manual_seed(0)
    truth = torch.stack([_state(), _state(vz=5.0)] * 50)[None].repeat(3, 1, 1)  # [3, 100, 9]
    state = truth + torch.randn(truth.shape, generator=g, dtype=torch.float64)
    scored = torch.ones(3, 100, dtype=torch.bool)
    scored[:, :10] = False
    out = rmse_by_phase(state, truth, scored)
    climb = torch.zeros(3, 100, dtype=torch.bool)
    climb[:, 1::2] = True
    e2 = (state - truth)[..., [0, 3, 6]].square().mean(-1)
    assert math.isclose(out["climb/descent"]["rmse"], float(e2[climb & scored].mean().sqrt()), rel_tol=1e-12)
    assert math.isclose(out["level"]["rmse"], float(e2[~climb & scored].mean().sqrt()), rel_tol=1e-12)
    assert out["turn"]["rmse"] is None and out["climb/descent"]["share"] == 0.5


def test_the_phases_script_scores_a_config_file_as_its_registry_method(tmp_path):
    """``scripts/real_phases.py --config LABEL=PATH`` (a method that is not in the registry, configs/studies/): a
    copy of a registry method's YAML gives that method's row to every digit; a missing file is refused by name."""
    import json
    import runpy

    from immnet.config import REPO_ROOT
    from immnet.data.storage import write_dataset
    from tests.tiny_runs import TINY

    write_dataset(tmp_path / "data", 6, seed=4, spec=TINY)
    main = runpy.run_path(str(REPO_ROOT / "scripts" / "real_phases.py"))["main"]
    cfg = REPO_ROOT / "configs" / "methods" / "real-ca.yaml"
    out = tmp_path / "phases.json"
    assert main(["--data", str(tmp_path / "data"), "--methods", "real-ca", "--config", f"copy={cfg}",
                 "--json", str(out)]) == 0
    rows = json.loads(out.read_text())
    assert rows["copy"] == rows["real-ca"] and set(rows["copy"]) == set(PHASES)
    with pytest.raises(SystemExit):
        main(["--data", str(tmp_path / "data"), "--config", f"x={tmp_path / 'none.yaml'}"])
