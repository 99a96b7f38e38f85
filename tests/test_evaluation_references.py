"""References that stay references in ``immnet evaluate``: the clairvoyant bound told the data's
statistics (meta.json or ``--sigma-q``), and ``--guard`` reaching every method with a range guard."""

import json
import math

import numpy as np
import pytest

import immnet.cli
from immnet import keys
from immnet.cli import main
from immnet.data.spec import DataSpec
from immnet.data.storage import export_npz, load_dataset, write_dataset

CV, CA = 0, 1
OTHERS = ["imm-max", "imm-tuned", "imm-ekf", "immnet", "clairvoyant-switch"]  # imm-max and imm-tuned assume sigma_q >= 0.5


@pytest.fixture(autouse=True)
def only_our_commands(monkeypatch):
    monkeypatch.setattr(immnet.cli, "_COMMAND_MODULES", ("immnet.evaluation.cli",))


def _evaluate(capsys, data, methods, *extra):
    out = data.parent / f"{data.name}.json"
    assert main(["evaluate", "--data", str(data), "--split", "all", "--methods", ",".join(methods),
                 "--json", str(out), "--quiet", *extra]) == 0
    capsys.readouterr()
    return {name: row["rmse"]["avg"] for name, row in json.loads(out.read_text())["methods"].items()}


def _kf_float64(z, mode, w, r, spec: DataSpec):
    """Per-trajectory FilterPy Kalman filter with the truth's modes, turn rates, r, sigma_q and CA draw
    variance, written from docs/spec.md section 2 independently of immnet.filters: states ``[N, T, 9]``."""
    from filterpy.kalman import KalmanFilter

    dt = spec.dt
    lo, hi = spec.ca_acc_h_min, spec.ca_acc_h_max
    acc_var = np.array([(hi**3 - lo**3) / (3 * (hi - lo)) / 2] * 2 + [spec.ca_acc_v_max**2 / 3])
    g = np.array([dt * dt / 2, dt, 0.0])
    G = np.kron(np.eye(3), g[:, None])  # [9, 3]
    Q = spec.sigma_q**2 * G @ G.T
    H = np.zeros((3, 9))
    H[0, 0] = H[1, 3] = H[2, 6] = 1.0
    acc = [2, 5, 8]

    def F(m, rate):
        if m == CA:
            return np.kron(np.eye(3), [[1, dt, dt * dt / 2], [0, 1, dt], [0, 0, 1]])
        out = np.kron(np.eye(3), [[1, dt, 0], [0, 1, 0], [0, 0, 0]])
        if m >= 2:  # coordinated turn in x-y at the true rate; acceleration = w x v after the step
            s, c = math.sin(rate * dt), math.cos(rate * dt)
            out[0, 1], out[0, 4], out[3, 1], out[3, 4] = s / rate, -(1 - c) / rate, (1 - c) / rate, s / rate
            out[1, 1], out[1, 4], out[4, 1], out[4, 4] = c, -s, s, c
            out[2, 1], out[2, 4], out[5, 1], out[5, 4] = -rate * s, -rate * c, rate * c, -rate * s
        return out

    N, T, _ = z.shape
    states = np.zeros((N, T, 9))
    for n in range(N):
        kf = KalmanFilter(dim_x=9, dim_z=3)
        kf.x = np.zeros(9)
        kf.x[0::3] = z[n, 0]
        kf.P = np.diag(np.tile([r[n] ** 2, 300.0**2, 10.0**2], 3))
        if mode[n, 0] == CA:
            kf.P[acc, acc] = acc_var
        states[n, 0] = kf.x
        for t in range(1, T):
            if mode[n, t] == CA and mode[n, t - 1] != CA:  # a new CA draw: known to happen, not its value
                kf.x[acc] = 0.0
                kf.P[acc, :] = 0.0
                kf.P[:, acc] = 0.0
                kf.P[acc, acc] = acc_var
            kf.predict(F=F(mode[n, t], w[n, t]), Q=Q)
            kf.update(z[n, t], R=r[n] ** 2 * np.eye(3), H=H)
            states[n, t] = kf.x
    return states


def test_clairvoyant_is_the_bound_of_data_with_another_sigma_q(tmp_path, capsys):
    """Issue 20, item 6: on data generated with sigma_q = 1 (and another CA draw), the clairvoyant takes the
    data's statistics from its meta.json (or ``--sigma-q`` for an .npz): its RMSE equals a float64 FilterPy
    Kalman filter with the true sigma_q, modes, turn rates, r and CA draw variance, and no other method
    beats it (with 3D-LAST's sigma_q 0.2 fixed, it was beaten: a bound no longer)."""
    spec = DataSpec(T=80, min_segment=25, sigma_q=1.0, ca_acc_h_min=1.0, ca_acc_h_max=5.0, ca_acc_v_max=0.5)
    data_dir = write_dataset(tmp_path / "sq1", 12, 5, spec, progress=False)
    td, _ = load_dataset(data_dir)
    z = td[keys.MEASUREMENTS].double().numpy()
    truth = td[keys.STATES].double().numpy()
    kf = _kf_float64(z, td[keys.MODE].numpy(), td[keys.TURN_RATE].double().numpy(), td[keys.R].double().numpy(), spec)
    e = kf[..., [0, 3, 6]] - truth[..., [0, 3, 6]]
    expected = float(np.sqrt((e**2).mean(1)).mean(0).mean())

    got = _evaluate(capsys, data_dir, ["clairvoyant", *OTHERS])
    assert got["clairvoyant"] == pytest.approx(expected, rel=1e-6)
    for name in OTHERS:
        assert got["clairvoyant"] <= got[name], f"{name} {got[name]:.3f} m beat the bound {got['clairvoyant']:.3f} m"

    npz = export_npz(data_dir, tmp_path / "sq1.npz")  # an .npz carries no spec: --sigma-q tells it
    told = _evaluate(capsys, npz, ["clairvoyant"], "--sigma-q", "1")["clairvoyant"]
    untold = _evaluate(capsys, npz, ["clairvoyant"])["clairvoyant"]
    spec_acc = DataSpec(sigma_q=1.0)  # the npz run knows sigma_q, not the CA draw: 3D-LAST's draw
    kf_npz = _kf_float64(z, td[keys.MODE].numpy(), td[keys.TURN_RATE].double().numpy(), td[keys.R].double().numpy(),
                         DataSpec(**{**spec.to_dict(), **{k: getattr(spec_acc, k) for k in ("ca_acc_h_min", "ca_acc_h_max", "ca_acc_v_max")}}))
    e = kf_npz[..., [0, 3, 6]] - truth[..., [0, 3, 6]]
    assert told == pytest.approx(float(np.sqrt((e**2).mean(1)).mean(0).mean()), rel=1e-6)
    assert untold > told


FAR = DataSpec(T=120, min_segment=40, range_min=60_000.0, range_max=60_000.0, bound_range_outer=70_000.0,
               bound_range_inner=50_000.0, hard_range_min=45_000.0, hard_range_max=75_000.0)


def test_evaluate_guard_reaches_immnet_and_the_guarded_imms(tmp_path, capsys):
    """Issue 20, item 6: ``immnet evaluate --guard none`` runs IMMNet without its range guard (targets at
    60 km, beyond 3D-LAST's 33 km: the RMSE equals the unguarded network's, computed here through
    ``Tracker``, and differs from the guarded one) and makes imm-ekf-guard its unguarded twin imm-ekf;
    ``--guard OUTER,INNER`` gives both the region; a bad value is a one-line error."""
    from immnet.evaluation.metrics import position_error, rmse
    from immnet.tracking.tracker import PRETRAINED, Tracker

    path = write_dataset(tmp_path / "far", 8, 3, FAR, progress=False)
    td, _ = load_dataset(path)
    names = ["immnet", "imm-ekf-guard", "imm-ekf"]
    guarded, unguarded = _evaluate(capsys, path, names), _evaluate(capsys, path, names, "--guard", "none")
    region = _evaluate(capsys, path, names, "--guard", "70000,50000")

    def net(guard):
        state = Tracker.from_checkpoint(PRETRAINED, guard).track(td[keys.MEASUREMENTS])[keys.STATE]
        return rmse(position_error(state.double(), td[keys.STATES]))["avg"]

    assert unguarded["immnet"] == pytest.approx(net(None), rel=1e-9)
    assert region["immnet"] == pytest.approx(net({"outer": 70_000.0, "inner": 50_000.0}), rel=1e-9)
    assert guarded["immnet"] > 1.05 * unguarded["immnet"]
    assert unguarded["imm-ekf-guard"] == pytest.approx(unguarded["imm-ekf"], rel=1e-12)
    assert guarded["imm-ekf-guard"] > 1.05 * guarded["imm-ekf"]
    assert unguarded["imm-ekf"] == guarded["imm-ekf"] == region["imm-ekf"]  # configured without a guard: none added
    assert main(["evaluate", "--data", str(path), "--methods", "immnet", "--guard", "far", "--quiet"]) == 2
    assert "--guard must be 'checkpoint', 'none' or 'OUTER,INNER'" in capsys.readouterr().err


def test_sigma_q_needs_a_reference(tmp_path, capsys):
    path = write_dataset(tmp_path / "d", 4, 1, DataSpec(T=60, min_segment=20), progress=False)
    assert main(["evaluate", "--data", str(path), "--split", "all", "--methods", "imm-ekf", "--sigma-q", "1"]) == 2
    assert "--sigma-q is for the clairvoyant references" in capsys.readouterr().err
