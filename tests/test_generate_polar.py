"""3D-LAST with a radar's plots (``immnet data generate --sigma-range/-azimuth/-elevation``, docs/data.md): the
polar errors' stds, each plot's ``meas_cov``, the outliers' share, the default output unchanged, the refusals."""

import json
import math

import numpy as np
import pytest

import immnet.cli
from immnet import keys
from immnet.data import radar
from immnet.data.generate import generate
from immnet.data.spec import PLOT_FIELDS, DataSpec
from immnet.data.storage import load_dataset, write_dataset

SMALL = dict(T=50, min_segment=10)
S_RANGE, S_AZ, S_EL = 40.0, 0.1, 0.2  # m, degrees, degrees


def _spec(**kw) -> DataSpec:
    fixed = dict(sigma_range_min=S_RANGE, sigma_range_max=S_RANGE, sigma_azimuth_min_deg=S_AZ,
                 sigma_azimuth_max_deg=S_AZ, sigma_elevation_min_deg=S_EL, sigma_elevation_max_deg=S_EL)
    return DataSpec(**SMALL, **{**fixed, **kw})


def _measured_polar(z: np.ndarray, s_az: float, s_el: float):
    """The plot's range, azimuth, elevation from the unbiased converted measurement: its conversion undone
    (``e, n`` divided by ``lambda_a lambda_e``, ``u`` by ``lambda_e``; docs of radar.converted)."""
    la, le = np.exp(-0.5 * s_az**2), np.exp(-0.5 * s_el**2)
    return radar.polar(z * np.array([la * le, la * le, le]))


def _errors(td, s_az, s_el):
    z = td[keys.MEASUREMENTS].numpy()
    pos = td[keys.STATES].numpy()[..., [0, 3, 6]]
    rho_m, az_m, el_m = _measured_polar(z, s_az, s_el)
    rho, az, el = radar.polar(pos)
    return rho_m - rho, np.angle(np.exp(1j * (az_m - az))), el_m - el


@pytest.fixture()
def main(monkeypatch):
    monkeypatch.setattr(immnet.cli, "_COMMAND_MODULES", ("immnet.data.cli",))
    return immnet.cli.main


def test_polar_errors_have_the_stds_asked():
    td = generate(600, 1, spec=_spec())
    s_az, s_el = np.radians(S_AZ), np.radians(S_EL)
    for err, s in zip(_errors(td, s_az, s_el), (S_RANGE, s_az, s_el)):
        n = err.size  # 30,000 plots: the std's Monte Carlo error is s / sqrt(2 n) = 0.4 % of s
        assert abs(err.std() / s - 1) < 0.02
        assert abs(err.mean()) < 4 * s / np.sqrt(n)
    # r: the RMS of the per-axis stds of each trajectory's covariances
    cov = td[keys.MEAS_COV].numpy()
    want = np.sqrt(np.trace(cov, axis1=-2, axis2=-1).mean(-1) / 3)
    np.testing.assert_allclose(td[keys.R].numpy(), want, rtol=1e-12)
    # a std pair drawn per trajectory, U[20, 60] m: E[s^2] = (60^3 - 20^3) / (3 * 40) = 1733.3 m^2, its deciles 24
    # and 56 m (one std for all would put both near 40 m: each track's RMS error is within 10 % of its std)
    td = generate(600, 2, spec=_spec(sigma_range_min=20.0, sigma_range_max=60.0))
    per_track = np.mean(_errors(td, s_az, s_el)[0] ** 2, -1)
    assert abs(per_track.mean() / ((60**3 - 20**3) / (3 * 40)) - 1) < 0.05
    q10, q90 = np.quantile(np.sqrt(per_track), [0.1, 0.9])
    assert q10 < 29 and q90 > 51


def test_each_plots_meas_cov_is_the_unbiased_conversions():
    td = generate(200, 3, spec=_spec(p_miss=0.2, outliers=0.1))
    z, cov = td[keys.MEASUREMENTS].numpy(), td[keys.MEAS_COV].numpy()
    missed = np.isnan(z).any(-1)
    assert np.isnan(cov[missed]).all() and np.isfinite(cov[~missed]).all()
    assert not missed[:, :2].any() and abs(missed[:, 2:].mean() - 0.2) < 0.02
    s = (S_RANGE, np.radians(S_AZ), np.radians(S_EL))
    rho_m, az_m, el_m = _measured_polar(z[~missed], *s[1:])
    enu, want = radar.converted(rho_m, az_m, el_m, *s)  # outliers too: their stated covariance is not scaled
    np.testing.assert_allclose(enu, z[~missed], rtol=1e-12, atol=1e-6)
    np.testing.assert_allclose(cov[~missed], want, rtol=1e-7, atol=1e-6)


def test_outlier_share():
    share, scale = 0.1, 50.0
    td = generate(600, 4, spec=_spec(outliers=share, outlier_scale=scale))
    s = (S_RANGE, np.radians(S_AZ), np.radians(S_EL))
    normalized = np.stack([np.abs(e) / si for e, si in zip(_errors(td, *s[1:]), s)], -1)
    wild = (normalized > 6).any(-1)  # a plain plot: probability 6e-9; an outlier's: 1 - P(|N| < 6/50)^3 = 0.9991
    expected = share * (1 - (2 * 0.5 * (1 + math.erf(6 / scale / np.sqrt(2))) - 1) ** 3)
    assert abs(wild.mean() - expected) < 0.01  # 30,000 plots: the share's std is 0.0017
    assert normalized[~wild].std() < 1.05  # the rest: the stds asked


def test_default_output_unchanged_and_truth_shared(tmp_path):
    plain = generate(300, 7, spec=DataSpec(**SMALL))
    explicit = generate(300, 7, spec=DataSpec(**SMALL, sigma_range_min=0.0, sigma_range_max=0.0,
                                              sigma_azimuth_min_deg=0.0, sigma_azimuth_max_deg=0.0,
                                              sigma_elevation_min_deg=0.0, sigma_elevation_max_deg=0.0,
                                              outliers=0.0, outlier_scale=10.0))
    assert set(plain.keys()) == set(explicit.keys()) and keys.MEAS_COV not in plain.keys()
    for k in plain.keys():
        assert plain[k].numpy().tobytes() == explicit[k].numpy().tobytes(), k
    assert DataSpec().to_dict() == DataSpec(outliers=0.0, outlier_scale=10.0).to_dict()
    assert not set(PLOT_FIELDS) & set(DataSpec().to_dict()) and len(PLOT_FIELDS) == 8
    # the same seed with plots: the same truth, other measurements
    polar = generate(300, 7, spec=_spec())
    for k in (keys.STATES, keys.MODE, keys.TURN_RATE, keys.TIME, keys.DT):
        assert plain[k].numpy().tobytes() == polar[k].numpy().tobytes(), k
    assert not np.array_equal(plain[keys.MEASUREMENTS].numpy(), polar[keys.MEASUREMENTS].numpy())
    # on disk: meta.json names no plot field without plots; with them meas_cov is stored and reloads
    write_dataset(tmp_path / "plain", 300, 7, DataSpec(**SMALL))
    assert "meas_cov" not in json.loads((tmp_path / "plain" / "meta.json").read_text())["dtype"]
    write_dataset(tmp_path / "polar", 300, 7, _spec(), workers=1)
    td, meta = load_dataset(tmp_path / "polar")
    assert meta["dtype"]["meas_cov"] == "float32" and meta["spec"]["sigma_range_max"] == S_RANGE
    np.testing.assert_array_equal(td[keys.MEAS_COV].numpy(), polar[keys.MEAS_COV].float().numpy())
    assert DataSpec.from_dict(meta["spec"]) == _spec()


def test_cli_generate_polar(tmp_path, main):
    out = tmp_path / "p"
    cfg = tmp_path / "small.yaml"
    cfg.write_text("T: 50\nmin_segment: 10\n")
    assert main(["data", "generate", "--out", str(out), "--n", "40", "--seed", "7", "--config", str(cfg), "--quiet",
                 "--sigma-range", f"{S_RANGE},{S_RANGE}", "--sigma-azimuth", f"{S_AZ},{S_AZ}",
                 "--sigma-elevation", f"{S_EL},{S_EL}", "--outliers", "0.05", "--outlier-scale", "20"]) == 0
    td, meta = load_dataset(out)
    assert meta["spec"]["outliers"] == 0.05 and meta["spec"]["outlier_scale"] == 20
    want = generate(40, 7, spec=_spec(outliers=0.05, outlier_scale=20.0))
    np.testing.assert_array_equal(td[keys.MEASUREMENTS].numpy(), want[keys.MEASUREMENTS].float().numpy())


REFUSALS = [
    (["--sigma-range", "20,60"],
     "a radar's plots need sigma_range, sigma_azimuth and sigma_elevation together, got sigma_range alone"),
    (["--sigma-range", "0,60", "--sigma-azimuth", "0.1,0.2", "--sigma-elevation", "0.1,0.2"],
     "sigma_range is a pair LOW,HIGH with 0 < LOW <= HIGH, got 0,60"),
    (["--sigma-range", "20,60", "--sigma-azimuth", "0.3,0.2", "--sigma-elevation", "0.1,0.2"],
     "sigma_azimuth is a pair LOW,HIGH with 0 < LOW <= HIGH, got 0.3,0.2"),
    (["--sigma-range", "20,60", "--sigma-azimuth", "0.1,0.2", "--sigma-elevation", "0.1,0.2", "--outliers", "1"],
     "outliers is a share in [0, 1) and outlier_scale >= 1, got 1, 10"),
    (["--sigma-range", "20,60", "--sigma-azimuth", "0.1,0.2", "--sigma-elevation", "0.1,0.2", "--outliers", "0.1",
      "--outlier-scale", "0.5"], "outliers is a share in [0, 1) and outlier_scale >= 1, got 0.1, 0.5"),
    (["--outliers", "0.1"],
     "outliers need a radar's plots: give sigma_range, sigma_azimuth and sigma_elevation"),
    (["--sigma-range", "20,nan", "--sigma-azimuth", "0.1,0.2", "--sigma-elevation", "0.1,0.2"],
     "DataSpec field 'sigma_range_max' must be a finite number, got nan"),
]


@pytest.mark.parametrize("args,message", REFUSALS)
def test_refusals_are_one_line(tmp_path, main, capsys, args, message):
    out = tmp_path / "x"
    assert main(["data", "generate", "--out", str(out), "--n", "5", "--seed", "0", "--quiet", *args]) == 2
    err = capsys.readouterr().err
    assert err == f"immnet data: error: {message}\n"
    assert not out.exists() and list(tmp_path.iterdir()) == []


def test_bad_pair_text_is_refused(main, capsys, tmp_path):
    with pytest.raises(SystemExit) as exit_:
        main(["data", "generate", "--out", str(tmp_path / "x"), "--n", "5", "--seed", "0", "--sigma-range", "20"])
    assert exit_.value.code == 2
    assert "argument --sigma-range: expected LOW,HIGH such as 20,60, got '20'" in capsys.readouterr().err
