"""``scripts/motion_oracle.py`` (docs/notebook/real-flights.md "What a tracker would need to know"): the truth's jerk,
the state change it makes, the oracle filter against FilterPy, and the script's rows against the filters run here."""

import json
import math
import runpy

import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter

from immnet import keys
from immnet.config import REPO_ROOT
from immnet.data.storage import as_batch, load_dataset, write_dataset
from immnet.filters.methods import build_method
from immnet.evaluation.search import states_rmse
from immnet.filters.imm import initial_state
from immnet.motion import ConstantAcceleration
from tests.tiny_runs import TINY

SCRIPT = REPO_ROOT / "scripts" / "motion_oracle.py"


@pytest.fixture(scope="module")
def mo():
    return runpy.run_path(str(SCRIPT))


def _pieces(t: np.ndarray, x0: tuple, jerks: list) -> np.ndarray:
    """States ``[len(t), 9]`` of a motion whose jerk is ``jerks[i]`` between scans ``i`` and ``i + 1``: each piece the
    cubic ``p + v h + a h^2 / 2 + j h^3 / 6`` (and its derivatives) in closed form; the axes scaled 1, -2, 0.5."""
    p, v, a = x0
    rows = [(p, v, a)]
    for h, j in zip(np.diff(t), jerks):
        p, v, a = p + v * h + a * h**2 / 2 + j * h**3 / 6, v + a * h + j * h**2 / 2, a + j * h
        rows.append((p, v, a))
    return np.array([[s * e for s in (1.0, -2.0, 0.5) for e in row] for row in rows])


def test_the_jerk_and_its_state_change_are_the_motion_that_made_the_truth(mo):
    """A trajectory of constant jerk between scans (uneven intervals): ``(a_t - a_{t-1}) / dt`` is each interval's
    jerk, and the CA prediction plus ``jerk_input`` is the next truth state, to rounding."""
    t = np.array([0.0, 1.0, 2.5, 3.0, 5.0, 9.0])
    jerks = [0.3, -0.7, 0.0, 1.1, -0.2]
    truth = _pieces(t, (100.0, 20.0, 0.5), jerks)
    states = torch.tensor(truth)[None]
    iv = torch.tensor(np.diff(t, prepend=t[0] - 1.0))[None]
    j = mo["truth_jerk"](states, iv)
    expect = torch.tensor([[0.0, 0.0, 0.0]] + [[s * v for s in (1.0, -2.0, 0.5)] for v in jerks], dtype=torch.float64)
    torch.testing.assert_close(j[0], expect, rtol=0, atol=1e-9)
    F = ConstantAcceleration(noise="continuous").F(iv, dtype=torch.float64)[0]
    u = mo["jerk_input"](j, iv)[0]
    pred = (F[1:] @ states[0, :-1, :, None]).squeeze(-1) + u[1:]
    torch.testing.assert_close(pred, states[0, 1:], rtol=0, atol=1e-9)
    # d scans late: the jerk of d scans before, none before scan d; a scan without truth gives no jerk
    torch.testing.assert_close(mo["delayed"](j, 2)[0, 2:], j[0, :-2])
    assert float(mo["delayed"](j, 2)[0, :2].abs().sum()) == 0.0
    states[0, 3] = float("nan")
    assert float(mo["truth_jerk"](states, iv)[0, 3:5].abs().sum()) == 0.0


def test_the_oracle_filter_is_filterpys_with_a_known_input(mo):
    """``ca_filter`` with noise per scan and axis and a known input: FilterPy's KalmanFilter (``predict(u, B=I, F,
    Q)``) from the same start at the first detection, missed scans predicted only."""
    g = torch.Generator().manual_seed(3)
    T = 12
    z = torch.randn(2, T, 3, generator=g, dtype=torch.float64) * 4 + torch.arange(T)[None, :, None] * 30.0
    z[0, :2] = float("nan")  # track 0 starts at scan 2
    z[1, 5] = float("nan")  # track 1 misses scan 5
    iv = torch.tensor([[1.0] * T, [1.0, 0.5, 2.0, 1.0, 1.5, 1.0, 3.0, 1.0, 1.0, 0.7, 1.0, 1.0]], dtype=torch.float64)
    q = torch.rand(2, T, 3, generator=g, dtype=torch.float64) * 0.5 + 0.01
    u = torch.randn(2, T, 9, generator=g, dtype=torch.float64) * 0.3
    r = torch.tensor([3.0, 6.0], dtype=torch.float64)
    ours = mo["ca_filter"](z, r, iv, q, u)
    x0, P0 = initial_state(z, r)
    model = ConstantAcceleration(noise="continuous")
    for b in range(2):
        start = int(torch.isfinite(z[b]).all(-1).nonzero()[0])
        kf = KalmanFilter(dim_x=9, dim_z=3)
        kf.x, kf.P = x0[b].numpy().copy(), P0[b].numpy().copy()
        kf.H = np.zeros((3, 9))
        kf.H[0, 0] = kf.H[1, 3] = kf.H[2, 6] = 1.0
        kf.R = np.eye(3) * float(r[b]) ** 2
        assert torch.isnan(ours[b, :start]).all()
        np.testing.assert_allclose(ours[b, start].numpy(), kf.x, atol=1e-9)
        for t in range(start + 1, T):
            F = model.F(float(iv[b, t]), dtype=torch.float64).numpy()
            Q = model.Q(1.0, float(iv[b, t]), dtype=torch.float64).numpy()
            s = np.repeat(np.sqrt(q[b, t].numpy()), 3)
            kf.predict(u=u[b, t].numpy(), B=np.eye(9), F=F, Q=Q * s[:, None] * s[None, :])
            if torch.isfinite(z[b, t]).all():
                kf.update(z[b, t].numpy())
            np.testing.assert_allclose(ours[b, t].numpy(), kf.x, atol=1e-7, rtol=1e-9)


def test_the_rows_are_the_filters_run_here_and_the_baseline_is_evaluates(tmp_path, mo, capsys):
    write_dataset(tmp_path / "tune", 8, seed=5, spec=TINY)
    write_dataset(tmp_path / "data", 8, seed=6, spec=TINY)
    out = tmp_path / "oracle.json"
    rc = mo["main"](["--tune", str(tmp_path / "tune"), "--data", str(tmp_path / "data"), "--baseline", "real-imm-axis",
                     "--imm", "real-imm-axis", "--delays", "0,2", "--scales", "1,4", "--noises", "0.01,1",
                     "--imm-scales", "1,0.1", "--json", str(out)])
    assert rc == 0
    rows = {row["row"]: row for row in json.loads(out.read_text())["rows"]}
    batch = as_batch(load_dataset(tmp_path / "data")[0])
    tune = as_batch(load_dataset(tmp_path / "tune")[0])
    score = states_rmse  # the table's Average RMSE, as immnet evaluate scores it
    baseline = score(build_method("real-imm-axis").track(batch)[keys.STATE], batch)
    assert rows["real-imm-axis"]["average"] == pytest.approx(baseline, rel=1e-9)
    # each row: the setting best on --tune, scored on --data
    sizes = {c: score(mo["size_oracle"](tune, c), tune) for c in (1.0, 4.0)}
    c = min(sizes, key=sizes.get)
    size_row = rows["CA told the size of each scan's change of acceleration (noise per scan and axis), c"]
    assert size_row["setting"] == f"{c:g}"
    assert size_row["average"] == pytest.approx(score(mo["size_oracle"](batch, c), batch), rel=1e-9)
    late = {q: score(mo["input_oracle"](tune, 2, q), tune) for q in (0.01, 1.0)}
    q = min(late, key=late.get)
    assert rows["CA told the change itself, 2 scans late, q"]["average"] == pytest.approx(
        score(mo["input_oracle"](batch, 2, q), batch), rel=1e-9)
    # the IMM told nothing (no input, its noise as configured) is the method itself: the input goes in where it should
    zero = mo["imm_input_oracle"](batch, build_method("real-imm-axis"), 10**6, 1.0)
    torch.testing.assert_close(zero, build_method("real-imm-axis").track(batch)[keys.STATE].double(), rtol=0, atol=1e-9)
    # told the truth's jerk as it happens, with little noise, the IMM is far ahead of itself on a generator's motion
    assert rows["real-imm-axis told the change itself, 0 scans late, noise x"]["average"] < 0.9 * rows["real-imm-axis"][
        "average"]
    assert math.isfinite(rows["CA told the change itself, 0 scans late, q"]["average"])
    assert "told the size" in capsys.readouterr().err  # each row's choice on --tune is shown
    report = json.loads(out.read_text())
    assert report["interval"] == pytest.approx(1.0) and {r["kind"] for r in report["rows"]} == {
        "baseline", "size", "ca", "imm"}
    assert mo["main"](["--plot", str(out), str(out), "--figure", str(tmp_path / "f.png")]) == 0
    assert (tmp_path / "f.png").stat().st_size > 10_000
    (tmp_path / "bad.json").write_text("{}")
    assert mo["main"](["--plot", str(tmp_path / "bad.json"), "--figure", str(tmp_path / "g.png")]) == 2
    assert "--plot needs this script's --json reports" in capsys.readouterr().err


def test_a_set_without_r_is_refused_by_name(tmp_path, mo, capsys):
    write_dataset(tmp_path / "data", 2, seed=5, spec=TINY)
    td, _ = load_dataset(tmp_path / "data")
    np.savez(tmp_path / "nor.npz", measurements=td[keys.MEASUREMENTS].numpy(), states=td[keys.STATES].numpy(), dt=1.0)
    rc = mo["main"](["--tune", str(tmp_path / "data"), "--data", str(tmp_path / "nor.npz")])
    assert rc == 2 and "has no r per track" in capsys.readouterr().err


def test_an_imm_that_is_not_decoupled_is_refused_by_name(tmp_path, mo, capsys):
    write_dataset(tmp_path / "data", 2, seed=5, spec=TINY)
    rc = mo["main"](["--tune", str(tmp_path / "data"), "--data", str(tmp_path / "data"), "--imm", "imm-tuned"])
    assert rc == 2 and "--imm imm-tuned: not a decoupled IMM" in capsys.readouterr().err
    rc = mo["main"](["--tune", str(tmp_path / "data"), "--data", str(tmp_path / "data"),
                     "--baseline", "no-such-method"])
    assert rc == 2 and "no-such-method" in capsys.readouterr().err
