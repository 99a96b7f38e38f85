"""Real flights (``immnet data adsb``): reading, cleaning, the smoother, windows, splits, bytes, the CLI.

Most tests use small synthetic samples written to tmp_path; one runs on traffic's ``quickstart`` sample
where its files are installed (scripts/setup.sh installs them)."""

import dataclasses
import gzip
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import immnet.cli
from immnet.data import adsb, real
from immnet.data.contract import check_arrays
from immnet.data.geodesy import enu_to_geodetic
from immnet.data.smoother import rts_smooth
from immnet.data.storage import load_dataset

SITE = (48.9, 2.45, 0.0)
T0 = 1_633_608_000_000  # ms epoch


def _track(k: int, n: int, rng) -> np.ndarray:
    """ENU positions [n, 3] at 1 s of aircraft k: straight, then a 1.5 deg/s turn, climbing."""
    speed, heading = 140.0 + 10 * k, rng.uniform(0, 2 * np.pi)
    w = np.where(np.arange(n) > n // 2, np.radians(1.5) * (-1) ** k, 0.0)
    psi = heading + np.cumsum(w)
    v = speed * np.stack([np.sin(psi), np.cos(psi)], -1)
    xy = rng.uniform(-30e3, 30e3, 2) + np.cumsum(v, 0)
    z = 3000.0 + 5.0 * np.arange(n)
    return np.c_[xy, z]


def _records(n_aircraft=6, n=400, seed=0, stale=False) -> list[dict]:
    rng = np.random.default_rng(seed)
    recs = []
    for k in range(n_aircraft):
        lat, lon, h = enu_to_geodetic(_track(k, n, rng), SITE)
        icao = f"abc{k:03d}"
        for i in range(n):
            alt_ft = 25.0 * round(h[i] / 0.3048 / 25.0)
            rec = {"timestamp": T0 + 1000 * (2 * i if stale else i), "icao24": icao, "latitude": float(lat[i]),
                   "longitude": float(lon[i]), "altitude": alt_ft, "onground": False, "callsign": f"T{k}"}
            recs.append(rec)
            if stale:  # the state vector one second later repeats the position
                recs.append({**rec, "timestamp": rec["timestamp"] + 1000})
    return recs


def _write(path, recs) -> str:
    with gzip.open(path, "wt") as f:
        json.dump(recs, f)
    return str(path)


def _digest(d) -> str:
    h = hashlib.sha256()
    for p in sorted(d.rglob("*")):
        if p.is_file():
            h.update(p.relative_to(d).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()


SMALL = real.RealSpec(T=50, splits=(0.5, 0.25, 0.25), max_range=60_000)


def test_stale_positions_removed(tmp_path):
    recs = _records(n_aircraft=2, n=100, stale=True)
    got = adsb.flights(adsb.read_records(_write(tmp_path / "s.json.gz", recs)))
    assert got.counts["rows"] == 400 and got.counts["stale"] == 200
    assert got.counts["flights"] == 2 and got.counts["fresh_points"] == 200
    f = got.flights[0]
    assert np.all(np.diff(f.t) == 2.0) and f.t[0] == T0 / 1000  # the fresh rows, at their own times


def test_glitch_dropped_and_counted_ground_and_gaps(tmp_path):
    recs = _records(n_aircraft=1, n=300)
    recs[100] = {**recs[100], "latitude": recs[100]["latitude"] + 0.2}  # 22 km off: a decoding glitch
    recs[150] = {**recs[150], "altitude": recs[150]["altitude"] + 2000}  # a 600 m jump in one second
    recs[10] = {**recs[10], "onground": True}
    recs[20] = {**recs[20], "altitude": None}  # a null value: the row is incomplete
    for r in recs[200:]:  # a gap of 11 minutes starts a new flight
        r["timestamp"] += 660_000
    got = adsb.flights(adsb.read_records(_write(tmp_path / "g.json.gz", recs)))
    c = got.counts
    assert (c["glitch"], c["onground"], c["incomplete"]) == (2, 1, 1)
    assert c["flights"] == 2 and [len(f.t) for f in got.flights] == [196, 100]
    assert all(np.all(np.diff(f.t) > 0) for f in got.flights)
    assert np.isclose(got.flights[0].h[0], recs[0]["altitude"] * 0.3048)  # feet -> metres


def test_timestamps_in_seconds_or_iso_read_as_ms(tmp_path):
    recs = _records(n_aircraft=1, n=20)
    ms = adsb.read_records(_write(tmp_path / "a.json.gz", recs))
    s = [{**r, "timestamp": r["timestamp"] / 1000} for r in recs]
    (tmp_path / "b.jsonl").write_text("".join(json.dumps(r) + "\n" for r in s))
    iso = [{**recs[0], "timestamp": "2021-10-07T12:00:00Z"}]
    assert np.array_equal(adsb.read_records(tmp_path / "b.jsonl").t, ms.t)
    one = adsb.read_records(_write(tmp_path / "c.json", iso))  # gzipped under a .json name: read all the same
    assert one.t[0] == 1633608000.0
    cols = {k: {str(i): r[k] for i, r in enumerate(recs)} for k in recs[0]}  # pandas' "columns" orientation
    assert np.array_equal(adsb.read_records(_write(tmp_path / "d.json.gz", cols)).lat, ms.lat)


def test_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no ADS-B sample 'collections/nowhere'"):
        adsb.resolve_sample("collections/nowhere")
    bad = tmp_path / "bad.json"
    bad.write_text('[{"timestamp": 1, "icao24": "a", ')
    with pytest.raises(ValueError, match=r"bad\.json: not valid JSON"):
        adsb.read_records(bad)
    trunc = tmp_path / "t.json.gz"
    whole = gzip.compress(json.dumps(_records(n_aircraft=1, n=50)).encode())
    trunc.write_bytes(whole[: len(whole) // 2])  # an interrupted download
    with pytest.raises(ValueError, match=r"t\.json\.gz: cannot be read"):
        adsb.read_records(trunc)
    recs = _records(n_aircraft=1, n=5)
    del recs[3]["altitude"]
    with pytest.raises(ValueError, match="record 3 lacks the required field 'altitude'"):
        adsb.read_records(_write(tmp_path / "m.json.gz", recs))
    with pytest.raises(ValueError, match="expected a JSON list of records"):
        adsb.read_records(_write(tmp_path / "o.json.gz", {"a": 1}))
    recs = _records(n_aircraft=1, n=5)
    recs[2]["latitude"] = "north"
    with pytest.raises(ValueError, match="record 2 has latitude = 'north', not a number"):
        adsb.read_records(_write(tmp_path / "n.json.gz", recs))


def _opensky_csv(path, recs, zipped=False) -> str:
    """``recs`` as OpenSky's historical state vectors CSV: epoch seconds, ``lat``/``lon``, ``baroaltitude`` in
    metres, ``onground`` true/false, ``lastposupdate``, and fields the reader ignores."""
    header = "time,icao24,lat,lon,velocity,heading,vertrate,callsign,onground,alert,spi,squawk,baroaltitude," \
             "geoaltitude,lastposupdate,lastcontact"
    lines = [header]
    for r in recs:
        alt = "" if r["altitude"] is None else repr(r["altitude"] * 0.3048)
        t = r["timestamp"] / 1000
        lines.append(f"{t:.3f},{r['icao24']},{r['latitude']!r},{r['longitude']!r},150.0,90.0,0.0,{r['callsign']},"
                     f"{str(r['onground']).lower()},false,false,1000,{alt},{alt},{t - 0.4:.3f},{t:.3f}")
    text = "\n".join(lines) + "\n"
    if zipped:
        Path(path).write_bytes(gzip.compress(text.encode()))
    else:
        Path(path).write_text(text)
    return str(path)


def test_opensky_csv_and_rest_names_read_as_traffics_json(tmp_path):
    """The same state vectors as traffic's JSON, as OpenSky's CSV (metres, its names, gzipped or not) and under its
    REST API's names: the same records, the altitude in metres either way, positions timed by their own update."""
    recs = _records(n_aircraft=2, n=30)
    recs[4]["onground"] = True
    recs[7]["altitude"] = None  # a null value: an empty cell
    want = adsb.read_records(_write(tmp_path / "a.json.gz", [{**r, "last_position": r["timestamp"] / 1000 - 0.4}
                                                             for r in recs]))
    for got in (adsb.read_records(_opensky_csv(tmp_path / "a.csv", recs)),
                adsb.read_records(_opensky_csv(tmp_path / "b.csv.gz", recs, zipped=True)),
                adsb.read_records(_write(tmp_path / "rest.json.gz", [
                    {"time": r["timestamp"] / 1000, "icao24": r["icao24"], "latitude": r["latitude"],
                     "longitude": r["longitude"], "on_ground": r["onground"], "time_position": r["timestamp"] / 1000 - 0.4,
                     "baro_altitude": None if r["altitude"] is None else r["altitude"] * 0.3048} for r in recs]))):
        np.testing.assert_allclose(got.t, want.t, rtol=0, atol=1e-6)
        np.testing.assert_allclose(got.timestamp, want.timestamp, rtol=0, atol=1e-6)
        assert np.array_equal(got.lat, want.lat) and np.array_equal(got.lon, want.lon)
        np.testing.assert_allclose(got.h, want.h, rtol=1e-12, equal_nan=True)
        assert np.isnan(got.h[7]) and got.onground[4] and got.onground.sum() == 1 and got.exact.all()
        assert list(got.icao24) == list(want.icao24)
    # an address of digits stays an address
    (tmp_path / "d.csv").write_text("time,icao24,lat,lon,baroaltitude\n1633608000,400123,48.9,2.4,3000\n")
    assert adsb.read_records(tmp_path / "d.csv").icao24[0] == "400123"
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbf" + (tmp_path / "d.csv").read_bytes())  # saved by a spreadsheet
    assert adsb.read_records(tmp_path / "bom.csv").lat[0] == 48.9
    # the flights and data sets made from either are the same
    four = [{**r, "last_position": r["timestamp"] / 1000 - 0.4} for r in _records(n_aircraft=4, n=200)]
    a = real.make_adsb(tmp_path / "ja", [_write(tmp_path / "j.json.gz", four)], SMALL, seed=1)
    b = real.make_adsb(tmp_path / "ca", [_opensky_csv(tmp_path / "c.csv", _records(n_aircraft=4, n=200))], SMALL,
                       seed=1)
    assert a["counts"] == b["counts"] and a["flights"] == b["flights"]
    for split in real.SPLITS:
        ta, tb = load_dataset(tmp_path / "ja" / split)[0], load_dataset(tmp_path / "ca" / split)[0]
        np.testing.assert_allclose(ta["states"].numpy(), tb["states"].numpy(), rtol=0, atol=1e-3)


def test_reported_velocity_in_si_under_either_names(tmp_path):
    """The velocity an aircraft reports: knots and feet per minute under traffic's names, m/s under OpenSky's (its
    CSV's ``velocity``/``heading``/``vertrate``, its REST API's ``velocity``/``true_track``/``vertical_rate``); NaN
    where a row has none, and for a file without the fields."""
    recs = _records(n_aircraft=1, n=3)
    traffic = [{**r, "groundspeed": 300.0, "track": 90.0, "vertical_rate": -1280.0} for r in recs]
    traffic[1].update(groundspeed=None, track=None, vertical_rate=None)
    got = adsb.read_records(_write(tmp_path / "t.json.gz", traffic))
    np.testing.assert_allclose(got.groundspeed[[0, 2]], 300 * 1852 / 3600)  # 154.33 m/s
    np.testing.assert_allclose(got.vertical_rate[[0, 2]], -1280 * 0.3048 / 60)  # -6.50 m/s
    assert (got.track[[0, 2]] == 90).all() and np.isnan([got.groundspeed[1], got.track[1], got.vertical_rate[1]]).all()
    csv = adsb.read_records(_opensky_csv(tmp_path / "o.csv", recs))  # velocity 150.0, heading 90.0, vertrate 0.0
    assert (csv.groundspeed == 150.0).all() and (csv.track == 90.0).all() and (csv.vertical_rate == 0.0).all()
    rest = adsb.read_records(_write(tmp_path / "rest.json.gz", [
        {"time": r["timestamp"] / 1000, "icao24": r["icao24"], "latitude": r["latitude"], "longitude": r["longitude"],
         "baro_altitude": r["altitude"] * 0.3048, "velocity": 154.33, "true_track": 271.5, "vertical_rate": -6.5}
        for r in recs]))
    assert (rest.groundspeed == 154.33).all() and (rest.track == 271.5).all() and (rest.vertical_rate == -6.5).all()
    bare = adsb.read_records(_write(tmp_path / "b.json.gz", recs))
    assert np.isnan(bare.groundspeed).all() and np.isnan(bare.track).all() and np.isnan(bare.vertical_rate).all()


def test_csv_errors_name_the_file_row_and_field(tmp_path):
    def csv(name, text):
        (tmp_path / name).write_text(text)
        return tmp_path / name

    with pytest.raises(ValueError, match=r"e\.csv: an empty CSV file"):
        adsb.read_records(csv("e.csv", ""))
    with pytest.raises(ValueError, match=r"h\.csv: holds no records"):
        adsb.read_records(csv("h.csv", "time,icao24,lat,lon,baroaltitude\n"))
    with pytest.raises(ValueError, match=r"no field 'latitude' or 'lat' \(has \['baroaltitude', 'icao24', 'lon', 'time'\]"):
        adsb.read_records(csv("m.csv", "time,icao24,lon,baroaltitude\n1,a,2,3\n"))
    with pytest.raises(ValueError, match="record 1 has lat = 'north', not a number"):
        adsb.read_records(csv("n.csv", "time,icao24,lat,lon,baroaltitude\n1,a,48,2,3\n2,a,north,2,3\n"))
    with pytest.raises(ValueError, match="data row 2 has 6 cells, the header 5"):
        adsb.read_records(csv("w.csv", "time,icao24,lat,lon,baroaltitude\n1,a,48,2,3\n2,a,48,2,3,9\n"))
    with pytest.raises(ValueError, match="record 0 has time = 'noon', neither epoch"):
        adsb.read_records(csv("t.csv", "time,icao24,lat,lon,baroaltitude\nnoon,a,48,2,3\n"))
    (tmp_path / "z.csv.gz").write_bytes(gzip.compress(b"time,icao24,lat,lon,baroaltitude\n" * 50)[:40])
    with pytest.raises(ValueError, match=r"z\.csv\.gz: cannot be read"):
        adsb.read_records(tmp_path / "z.csv.gz")


def test_smoother_recovers_constant_acceleration():
    rng = np.random.default_rng(0)
    tm = np.sort(rng.uniform(0, 200, 200))  # irregular measurement times
    ts = np.arange(0.5, 199, 1.0)  # where the truth is wanted
    t = np.r_[tm, ts]
    o = np.argsort(t, kind="stable")
    p0, v0, a = np.array([1e3, -2e3, 3e3]), np.array([150.0, -80.0, 5.0]), np.array([0.8, -0.5, 0.05])

    def true(s):
        return p0 + v0 * s[:, None] + 0.5 * a * s[:, None] ** 2

    z = np.r_[true(tm) + 5.0 * rng.standard_normal((200, 3)), np.full((len(ts), 3), np.nan)][o]
    xs = rts_smooth(np.repeat(t[o][:, None], 3, 1), z, np.full_like(z, 25.0), np.full(3, 0.01))[o >= 200]
    err = xs[..., 0] - true(ts)
    assert np.sqrt((err ** 2).mean()) < 1.5  # points: 5 m
    verr = xs[..., 1] - (v0 + a * ts[:, None])
    assert np.sqrt((verr ** 2).mean()) < 0.3 and np.abs(verr).max() < 1.0  # worst at the ends
    # consistent states: the velocity is the derivative of the position
    fd = np.diff(xs[..., 0], axis=0)
    assert np.abs(fd - (xs[1:, :, 1] + xs[:-1, :, 1]) / 2).max() < 0.01


def test_written_sets_load_split_by_flight_same_bytes(tmp_path):
    sample = _write(tmp_path / "six.json.gz", _records(n_aircraft=8, n=400, stale=False))
    meta = real.make_adsb(tmp_path / "a", [sample], SMALL, seed=3, npz=True)
    flights = meta["flights"]
    assert sum(len(v) for v in flights.values()) == meta["counts"]["flights_with_windows"] == 8
    assert len(set().union(*flights.values())) == 8  # no flight in two splits
    assert [len(flights[k]) for k in real.SPLITS] == [4, 2, 2]
    for split in real.SPLITS:
        td, m = load_dataset(tmp_path / "a" / split)
        assert m["format"] == "adsb" and m["split"] == split and m["flights"] == flights
        assert td.batch_size[0] == meta["counts"]["windows"][split] > 0
        arrays = {k: td[k].numpy() for k in td.keys()}
        check_arrays(arrays, split)
        assert arrays["states"].shape[1:] == (50, 9) and (arrays["mode"] == -1).all()
        assert np.isfinite(arrays["states"]).all() and (arrays["t"][:, 0] == 0).all()
        assert np.allclose(np.diff(arrays["t"], axis=1), 1.0)
        s = arrays["states"].astype(np.float64)
        w = (s[..., 1] * s[..., 5] - s[..., 4] * s[..., 2]) / (s[..., 1] ** 2 + s[..., 4] ** 2)
        assert np.allclose(arrays["turn_rate"], w, atol=1e-6)
        assert np.abs(np.degrees(w)).max() < 2.5  # flown at 1.5 deg/s at most
        e = arrays["measurements"] - arrays["states"][..., [0, 3, 6]]
        assert np.all((arrays["r"] >= 1) & (arrays["r"] <= 7)) and 1 < np.sqrt(np.mean(e ** 2)) < 7
        assert load_dataset(tmp_path / "a" / f"{split}.npz")[0].batch_size == td.batch_size
    # the splits train as they are: a set labelled at no scan, validation and test kept by flight
    from immnet.data.datamodule import LASTDataModule

    dm = LASTDataModule(str(tmp_path / "a" / "train"), val_data=str(tmp_path / "a" / "val"),
                        test_data=str(tmp_path / "a" / "test"), batch_size=4)
    batch = next(iter(dm.train_dataloader()))
    assert batch["states"].shape == (4, 50, 9) and (batch["mode"] == -1).all()
    assert len(dm.split("val")) == meta["counts"]["windows"]["val"]
    real.make_adsb(tmp_path / "b", [sample], SMALL, seed=3, npz=True)
    assert _digest(tmp_path / "a") == _digest(tmp_path / "b")
    real.make_adsb(tmp_path / "c", [sample], SMALL, seed=4)
    assert load_dataset(tmp_path / "c" / "train")[0]["r"].sum() != load_dataset(tmp_path / "a" / "train")[0]["r"].sum()
    with pytest.raises(FileExistsError, match="not empty"):
        real.make_adsb(tmp_path / "a", [sample], SMALL, seed=3)


def test_jitter_misses_range_and_all_test(tmp_path):
    sample = _write(tmp_path / "s.json.gz", _records(n_aircraft=3, n=300))
    spec = real.RealSpec(T=40, dt=2.0, dt_jitter=0.5, p_miss=0.2, splits=(0, 0, 1), max_range=60_000)
    meta = real.make_adsb(tmp_path / "o", [sample], spec, seed=0)
    assert sorted(p.name for p in (tmp_path / "o").iterdir()) == ["test"]
    td, _ = load_dataset(tmp_path / "o" / "test")
    steps = np.diff(td["t"].numpy(), axis=1)
    assert steps.min() >= 1.5 and steps.max() <= 2.5 and steps.std() > 0.1
    miss = np.isnan(td["measurements"].numpy()[..., 0])
    assert not miss[:, :2].any() and 0.1 < miss[:, 2:].mean() < 0.3
    assert len(meta["flights"]["test"]) == 3
    # a site far away: nothing in range, a clear error
    with pytest.raises(ValueError, match="no window of T=40 scans"):
        real.make_adsb(tmp_path / "far", [sample], spec, site=(10.0, 2.0, 0.0))


def test_several_samples_and_a_failed_write_leaves_nothing(tmp_path, monkeypatch):
    a = _write(tmp_path / "a.json.gz", _records(n_aircraft=2, n=200, seed=0))
    b = _write(tmp_path / "b.json.gz", _records(n_aircraft=2, n=200, seed=1))
    spec = real.RealSpec(T=40, splits=(0, 0, 1), max_range=60_000)
    meta = real.make_adsb(tmp_path / "ab", [a, b], spec)
    assert [s["file"] for s in meta["samples"]] == ["a.json.gz", "b.json.gz"] and meta["counts"]["flights"] == 4
    assert meta["counts"]["rows"] == sum(c["rows"] for c in meta["counts_per_sample"].values()) == 800
    assert set(meta["sites"]) == {a, b} and meta["site_from"] == "median of each sample" and meta["skipped"] == []
    with pytest.raises(ValueError, match="the same file as sample"):
        real.make_adsb(tmp_path / "aa", [a, a], spec)
    bad = tmp_path / "bad.json"
    bad.write_text('{"name": "an airspace", "shapes": []}')
    with pytest.raises(ValueError, match="expected a JSON list of records"):
        real.make_adsb(tmp_path / "ab2", [a, str(bad), b], spec)
    meta2 = real.make_adsb(tmp_path / "ab2", [a, str(bad), b], spec, skip_unreadable=True)
    assert meta2["skipped"] == [{"name": str(bad), "error": meta2["skipped"][0]["error"]}]
    assert meta2["skipped"][0]["error"].startswith("bad.json: expected a JSON list")  # the file's name, not its path
    assert meta2["flights"] == meta["flights"]

    def fail(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr("immnet.data.storage.write_arrays", fail)
    with pytest.raises(RuntimeError, match="disk full"):
        real.make_adsb(tmp_path / "x", [a], spec)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json.gz", "ab", "ab2", "b.json.gz", "bad.json"]


@pytest.mark.skipif(adsb.samples_dir() is None, reason="traffic's sample files are not installed")
def test_quickstart_flights_split_by_flight(tmp_path):
    spec = real.RealSpec(max_flights=12, splits=(0.5, 0.25, 0.25))
    meta = real.make_adsb(tmp_path / "q", ["collections/quickstart"], spec, seed=0)
    c = meta["counts"]
    assert c["rows"] == 284505 and c["flights"] == 238 and c["stale"] > 10_000 and c["glitch"] > 0
    ids = [i for v in meta["flights"].values() for i in v]
    assert len(ids) == len(set(ids)) == c["flights_with_windows"] > 0
    for split in real.SPLITS:
        td, m = load_dataset(tmp_path / "q" / split)
        assert set(m["flights"][split]) == set(meta["flights"][split])
        assert np.isfinite(td["states"].numpy()).all()


def test_cli_on_a_synthetic_file(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(immnet.cli, "_COMMAND_MODULES", ("immnet.data.cli",))
    sample = _write(tmp_path / "s.json.gz", _records(n_aircraft=4, n=300))
    out = tmp_path / "runs" / "real" / "data"  # parents that do not exist yet are made
    args = ["data", "adsb", "--samples", sample, "--out", str(out), "--T", "60", "--splits", "0.5,0.25,0.25",
            "--r", "2,3", "--site", "48.9,2.45,0", "--max-range", "60000", "--seed", "1", "--quiet"]
    assert immnet.cli.main(args) == 0
    assert "flights with windows" in capsys.readouterr().out
    td, meta = load_dataset(out / "train")
    assert td["states"].shape[1:] == (60, 9) and meta["site_from"] == "given" and meta["seed"] == 1
    assert ((td["r"] >= 2) & (td["r"] <= 3)).all()
    assert immnet.cli.main(["data", "adsb", "--samples", "nowhere/none", "--out", str(tmp_path / "x"), "--quiet"]) == 2
    assert "no ADS-B sample 'nowhere/none'" in capsys.readouterr().err


def test_evaluate_a_real_set(tmp_path, monkeypatch, capsys):
    """The sets have no mode labels: trackers are scored without a mode accuracy, the clairvoyant bounds
    are refused by name (explicitly) or skipped with a note (by default)."""
    sample = _write(tmp_path / "s.json.gz", _records(n_aircraft=2, n=200))
    real.make_adsb(tmp_path / "o", [sample], real.RealSpec(T=50, splits=(0, 0, 1), max_range=60_000))
    out = tmp_path / "r.json"
    args = ["evaluate", "--data", str(tmp_path / "o" / "test"), "--split", "all", "--guard", "none", "--quiet"]
    assert immnet.cli.main([*args, "--methods", "imm-ekf", "--json", str(out)]) == 0
    row = json.loads(out.read_text())["methods"]["imm-ekf"]
    assert "mode_accuracy" not in row and row["rmse"]["avg"] > 0
    assert "mode acc" not in capsys.readouterr().out
    assert immnet.cli.main([*args, "--methods", "imm-ekf,clairvoyant"]) == 2
    assert "clairvoyant needs the true mode at every scan" in capsys.readouterr().err


def test_window_flights_and_subsets_of_flights(tmp_path, monkeypatch, capsys):
    """Each split names the flight of every window; ``immnet data subset`` keeps some flights' windows, byte
    for byte, nested for one seed (a data-scaling curve adds flights), refusing what it cannot do by name."""
    sample = _write(tmp_path / "s.json.gz", _records(n_aircraft=8, n=400))
    spec = real.RealSpec(T=50, splits=(0.75, 0.125, 0.125), max_range=60_000)
    meta = real.make_adsb(tmp_path / "o", [sample], spec, seed=0)
    train = tmp_path / "o" / "train"
    td, m = load_dataset(train)
    owners = m["window_flights"]
    assert m["format_version"] == 2 and len(owners) == td.batch_size[0] and set(owners) == set(meta["flights"]["train"])
    # the flight named is the one flown: aircraft k flies at 140 + 10 k m/s (_track)
    speed = np.hypot(td["states"][..., 1].numpy(), td["states"][..., 4].numpy()).mean(1)
    assert np.allclose(speed, [140 + 10 * int(f.split("-")[0][3:]) for f in owners], atol=2)

    three = real.subset_flights(train, tmp_path / "three", 0.5, seed=1)
    two = real.subset_flights(train, tmp_path / "two", 2, seed=1)
    assert three["subset"] == {"flights": 3, "of_flights": 6, "windows": three["n"], "of_windows": len(owners),
                               "seed": 1}
    assert set(two["flights"]["train"]) < set(three["flights"]["train"])  # nested for one seed
    assert three["flights"]["val"] == meta["flights"]["val"] and three["split"] == "train"
    sub, sm = load_dataset(tmp_path / "three")
    rows = [i for i, f in enumerate(owners) if f in set(sm["flights"]["train"])]
    assert sm["window_flights"] == [owners[i] for i in rows] and sub.batch_size[0] == len(rows) == three["n"]
    for key in td.keys():
        assert np.array_equal(sub[key].numpy(), td[key].numpy()[rows], equal_nan=True)
    real.subset_flights(train, tmp_path / "again", 0.5, seed=1)
    assert _digest(tmp_path / "again") == _digest(tmp_path / "three")
    chosen = {tuple(real.subset_flights(train, tmp_path / f"s{s}", 3, seed=s)["flights"]["train"]) for s in range(4)}
    assert len(chosen) > 1  # the seed chooses

    for flights, message in ((0, "a count >= 1 or a fraction"), (1.5, "whole number"), (7, "has 6 flights")):
        with pytest.raises(ValueError, match=message):
            real.subset_flights(train, tmp_path / "bad", flights)
    with pytest.raises(ValueError, match="replace its own source"):
        real.subset_flights(train, train, 0.5, overwrite=True)
    with pytest.raises(FileExistsError, match="not empty"):
        real.subset_flights(train, tmp_path / "two", 2)
    old = tmp_path / "v1"  # a set written before the flights of its windows were named
    shutil.copytree(train, old)
    m1 = {k: v for k, v in m.items() if k != "window_flights"}
    (old / "meta.json").write_text(json.dumps({**m1, "format_version": 1}))
    with pytest.raises(ValueError, match="does not name the flight of each window"):
        real.subset_flights(old, tmp_path / "bad", 0.5)
    assert not (tmp_path / "bad").exists()  # nothing written by a refusal

    monkeypatch.setattr(immnet.cli, "_COMMAND_MODULES", ("immnet.data.cli",))
    out = tmp_path / "cli"
    assert immnet.cli.main(["data", "subset", "--data", str(train), "--out", str(out), "--flights", "0.5",
                            "--seed", "1"]) == 0
    assert "3 of 6 flights" in capsys.readouterr().out and _digest(out) == _digest(tmp_path / "three")
    assert immnet.cli.main(["data", "subset", "--data", str(tmp_path / "o" / "val.npz"), "--out",
                            str(tmp_path / "npz"), "--flights", "1"]) == 2
    assert "needs a real-flight data set directory" in capsys.readouterr().err
    from immnet.data.spec import DataSpec
    from immnet.data.storage import write_dataset

    last = write_dataset(tmp_path / "3dlast", 4, 0, DataSpec(T=120), progress=False)
    with pytest.raises(ValueError, match="format '3d-last' is not real flights"):
        real.subset_flights(last, tmp_path / "bad", 0.5)


def test_flights_of_sparse_positions_left_out(tmp_path, monkeypatch, capsys):
    """``--max-position-interval``: a flight whose fresh positions lie further apart (median) than the limit is left
    out and counted; every kept flight's windows are those of the set of all flights, byte for byte."""
    every_second = _records(n_aircraft=3, n=400, seed=0)
    every_fifth = [{**r, "icao24": "def" + r["icao24"][3:]} for r in _records(n_aircraft=2, n=400, seed=1)
                   if (r["timestamp"] - T0) // 1000 % 5 == 0]  # a resampled sample: a row every 5 s
    sample = _write(tmp_path / "s.json.gz", every_second + every_fifth)
    spec = real.RealSpec(T=40, splits=(0.0, 0.0, 1.0), max_range=60_000.0)  # as the CLI gives it, to compare bytes
    full = real.make_adsb(tmp_path / "all", [sample], spec)
    assert full["counts"]["sparse"] == 0 and len(full["flights"]["test"]) == 5  # truth_gap 5: 5 s rows have truth
    dense = real.make_adsb(tmp_path / "dense", [sample], dataclasses.replace(spec, max_position_interval=2.0))
    assert dense["counts"]["sparse"] == dense["counts_per_sample"][sample]["sparse"] == 2
    assert sorted(dense["flights"]["test"]) == sorted(f for f in full["flights"]["test"] if f.startswith("abc"))
    assert dense["params"]["max_position_interval"] == 2.0
    td, m = load_dataset(tmp_path / "all" / "test")
    sub, sm = load_dataset(tmp_path / "dense" / "test")
    rows = [i for i, f in enumerate(m["window_flights"]) if f.startswith("abc")]
    assert sm["window_flights"] == [m["window_flights"][i] for i in rows] and sub.batch_size[0] == len(rows) > 0
    for key in td.keys():
        assert np.array_equal(sub[key].numpy(), td[key].numpy()[rows], equal_nan=True)
    assert [real.position_interval(f) for f in adsb.flights(adsb.read_records(sample)).flights] == [1, 1, 1, 5, 5]
    with pytest.raises(ValueError, match="no flight whose fresh positions are at most 0.5 s apart"):
        real.make_adsb(tmp_path / "none", [sample], dataclasses.replace(spec, max_position_interval=0.5))
    with pytest.raises(ValueError, match="max_position_interval must be >= 0"):
        real.RealSpec(max_position_interval=-1.0)
    monkeypatch.setattr(immnet.cli, "_COMMAND_MODULES", ("immnet.data.cli",))
    out = tmp_path / "cli"
    assert immnet.cli.main(["data", "adsb", "--samples", sample, "--out", str(out), "--splits", "all-test", "--T",
                            "40", "--max-range", "60000", "--max-position-interval", "2", "--quiet"]) == 0
    assert "left out 2 flight(s) whose fresh positions lie more than 2 s apart" in capsys.readouterr().out
    assert _digest(out) == _digest(tmp_path / "dense")


def _two_intervals(tmp_path, seed=2):
    """One sample at 1 s scans (seed ``seed``) and at 5 s (seed 0): ``(sample, 5 s spec, meta a, meta b)``, two
    partitions of its flights (eight long flights, and three short ones that have windows at 1 s only)."""
    long = _records(n_aircraft=8, n=400, seed=0)
    short = [{**r, "icao24": "abd" + r["icao24"][3:]} for r in _records(n_aircraft=3, n=120, seed=2)]
    sample = _write(tmp_path / "s.json.gz", long + short)
    one = real.RealSpec(T=40, splits=(0.5, 0.25, 0.25), max_range=60_000.0)
    five = dataclasses.replace(one, dt=5.0)
    return (sample, five, real.make_adsb(tmp_path / "a", [sample], one, seed=seed),
            real.make_adsb(tmp_path / "b", [sample], five))


def test_one_partition_for_every_scan_interval(tmp_path, monkeypatch, capsys):
    """Sets of the same samples and seed at two scan intervals split the flights alike, though a short flight has
    windows at 1 s and none at 5 s (the partition is drawn over the flights selected, not those with windows);
    ``--splits-from`` takes another set's partition (here one of another seed), and ``immnet data subset --without``
    leaves out the flights another set trains and validates on."""
    sample, five, a, b = _two_intervals(tmp_path)
    a0 = real.make_adsb(tmp_path / "a0", [sample], dataclasses.replace(five, dt=1.0))  # b's seed
    split_0 = {f: k for k, v in a0["flights"].items() for f in v}
    split_a = {f: k for k, v in a["flights"].items() for f in v}
    split_b = {f: k for k, v in b["flights"].items() for f in v}
    assert set(split_b) < set(split_0) and split_b == {f: split_0[f] for f in split_b}  # one partition
    assert len(split_0) == a0["counts"]["flights"]  # every flight has windows at 1 s
    ref = real.partition(sorted(split_0), (0.5, 0.25, 0.25), 0)  # the draw, over the flights alone
    assert {k: [f for f in v if f in split_b] for k, v in ref.items()} == b["flights"]
    assert any(split_a[f] != split_b[f] for f in split_b)  # the case below: two partitions
    c = real.make_adsb(tmp_path / "c", [sample], five, splits_from=tmp_path / "a" / "val")
    assert {f: k for k, v in c["flights"].items() for f in v} == {f: split_a[f] for f in split_b}
    assert c["splits_from"] == str(tmp_path / "a" / "val") and c["counts"]["unsplit"] == 0
    def windows(out):  # {flight: its windows' measurements}, over every split
        got = {}
        for split in real.SPLITS:
            td, m = load_dataset(out / split)
            assert set(m["window_flights"]) == set(m["flights"][split])
            for f, z in zip(m["window_flights"], td["measurements"].numpy()):
                got.setdefault(f, []).append(z)
        return got

    wb, wc = windows(tmp_path / "b"), windows(tmp_path / "c")  # the windows are b's, only the partition differs
    assert wb.keys() == wc.keys() and all(np.array_equal(np.stack(wb[f]), np.stack(wc[f]), equal_nan=True) for f in wb)
    assert real.make_adsb(tmp_path / "c2", [sample], five, splits_from=tmp_path / "a")["flights"] == c["flights"]
    # a reference of some of the samples: the flights it does not name are left out and counted
    other = _write(tmp_path / "o.json.gz", [{**r, "icao24": "fed" + r["icao24"][3:]} for r in _records(2, 400, seed=5)])
    d = real.make_adsb(tmp_path / "d", [sample, other], five, splits_from=tmp_path / "a")
    assert d["counts"]["unsplit"] == d["counts_per_sample"][other]["flights"] > 0
    assert d["counts_per_sample"][other]["windows"] == 0 and d["flights"] == c["flights"]
    with pytest.raises(ValueError, match="made from none of these samples"):
        real.make_adsb(tmp_path / "e", [other], five, splits_from=tmp_path / "a")
    with pytest.raises(ValueError, match="no meta.json"):
        real.make_adsb(tmp_path / "e", [sample], five, splits_from=tmp_path / "nowhere")
    from immnet.data.spec import DataSpec
    from immnet.data.storage import write_dataset

    last = write_dataset(tmp_path / "3dlast", 4, 0, DataSpec(T=120), progress=False)
    with pytest.raises(ValueError, match="not a set of `immnet data adsb`"):
        real.make_adsb(tmp_path / "e", [sample], five, splits_from=last)
    assert not (tmp_path / "e").exists()

    # the test flights of a at 1 s that b (5 s) neither trains nor validates on
    test, tm = load_dataset(tmp_path / "a" / "test")
    seen = set(b["flights"]["train"]) | set(b["flights"]["val"])
    u = real.subset_flights(tmp_path / "a" / "test", tmp_path / "u", without=[tmp_path / "b" / "train",
                                                                              tmp_path / "b" / "val"])
    assert set(u["flights"]["test"]) == set(a["flights"]["test"]) - seen
    assert u["subset"]["without"]["flights"] == len(set(a["flights"]["test"]) & seen) > 0
    sub, sm = load_dataset(tmp_path / "u")
    rows = [i for i, f in enumerate(tm["window_flights"]) if f not in seen]
    assert sm["window_flights"] == [tm["window_flights"][i] for i in rows]
    for key in test.keys():
        assert np.array_equal(sub[key].numpy(), test[key].numpy()[rows], equal_nan=True)
    with pytest.raises(ValueError, match="every flight of it is in"):
        real.subset_flights(tmp_path / "a" / "test", tmp_path / "x", without=[tmp_path / "a" / "test"])
    with pytest.raises(ValueError, match="needs --flights, --without or both"):
        real.subset_flights(tmp_path / "a" / "test", tmp_path / "x")
    with pytest.raises(ValueError, match="not one split of a set but a set's OUT"):
        real.subset_flights(tmp_path / "a" / "test", tmp_path / "x", without=[tmp_path / "d"])
    monkeypatch.setattr(immnet.cli, "_COMMAND_MODULES", ("immnet.data.cli",))
    cli = ["data", "adsb", "--samples", sample, other, "--T", "40", "--dt", "5", "--max-range", "60000", "--splits-from",
           str(tmp_path / "a"), "--quiet"]
    assert immnet.cli.main([*cli, "--out", str(tmp_path / "cli")]) == 0
    printed = capsys.readouterr().out
    assert f"left out {d['counts']['unsplit']} flight(s) with windows that {tmp_path / 'a' / 'train'} does not" in printed
    real.make_adsb(tmp_path / "d2", [sample, other], dataclasses.replace(five, splits=(0.7, 0.15, 0.15)),
                   splits_from=tmp_path / "a")  # the CLI's spec: --splits at its default, unused
    assert _digest(tmp_path / "cli") == _digest(tmp_path / "d2")
    assert immnet.cli.main([*cli, "--out", str(tmp_path / "both"), "--splits", "0.5,0.25,0.25"]) == 2
    assert "give --splits or --splits-from, not both" in capsys.readouterr().err and not (tmp_path / "both").exists()
    assert immnet.cli.main(["data", "subset", "--data", str(tmp_path / "a" / "test"), "--out", str(tmp_path / "cu"),
                            "--without", str(tmp_path / "b" / "train"), str(tmp_path / "b" / "val")]) == 0
    assert "left out as flights of --without" in capsys.readouterr().out and _digest(tmp_path / "cu") == _digest(
        tmp_path / "u")


def test_training_refuses_flights_another_set_keeps_for_validation_or_test(tmp_path):
    """``LASTDataModule`` refuses a run whose real-flight training set holds flights that a set of the same samples
    in the run keeps for validation or test (sets at two scan intervals and two seeds: two partitions), unless told
    ``allow_seen_flights``; one partition (``--splits-from``) trains, as does a set alone or beside 3D-LAST."""
    from immnet.data import LASTDataModule
    from immnet.data.datamodule import MixtureDataset
    from immnet.data.spec import DataSpec
    from immnet.data.storage import write_dataset

    sample, five, a, b = _two_intervals(tmp_path)
    real.make_adsb(tmp_path / "c", [sample], five, splits_from=tmp_path / "a")
    held_b = set(b["flights"]["val"]) | set(b["flights"]["test"])
    assert set(a["flights"]["train"]) & held_b  # the case: a trains on flights b holds out

    def setup(data, val, **kw):
        dm = LASTDataModule([str(tmp_path / d) for d in data], val_data=[v and str(tmp_path / v) for v in val],
                            batch_size=2, **kw)
        dm.setup("fit")
        return dm

    with pytest.raises(ValueError, match=r"a/train trains on \d+ flight\(s\) that the set of .*b/\w+ keeps for"):
        setup(["a/train", "b/train"], ["a/val", "b/val"])
    with pytest.raises(ValueError, match="--splits-from"):
        LASTDataModule(str(tmp_path / "b" / "train"), val_data=str(tmp_path / "b" / "val"),
                       test_data=str(tmp_path / "a" / "test"), batch_size=2).setup("fit")  # b trains on a's test
    assert isinstance(setup(["a/train", "b/train"], ["a/val", "b/val"], allow_seen_flights=True).dataset("train"),
                      MixtureDataset)
    assert isinstance(setup(["a/train", "c/train"], ["a/val", "c/val"]).dataset("train"), MixtureDataset)  # one partition
    write_dataset(tmp_path / "3dlast", 8, 0, DataSpec(T=40, min_segment=12), progress=False)  # trajectories, no flights
    assert isinstance(setup(["a/train", "3dlast"], ["a/val", None]).dataset("train"), MixtureDataset)


def test_turns_added_to_a_real_set(tmp_path, monkeypatch, capsys):
    """``immnet data turns``: the windows of a real set, some flown through added coordinated turns and measured
    again with their own r; the others' truth as stored; same seed, same bytes; refusals by name."""
    sample = _write(tmp_path / "s.json.gz", _records(n_aircraft=8, n=400))
    real.make_adsb(tmp_path / "o", [sample], real.RealSpec(T=50, splits=(0.75, 0.125, 0.125), max_range=60_000),
                   seed=0)
    train = tmp_path / "o" / "train"
    meta = real.turned_flights(train, tmp_path / "t", 0.5, seed=3, bank=(20.0, 30.0))
    td, m = load_dataset(train)
    tt, _ = load_dataset(tmp_path / "t")
    assert meta["turns"] == {"turns": 0.5, "bank": [20.0, 30.0], "segment": [20.0, 120.0], "seed": 3}
    assert meta["window_flights"] == m["window_flights"] and meta["n"] == m["n"]
    x, y = td["states"].double().numpy(), tt["states"].double().numpy()
    moved = np.abs(y - x).max((1, 2)) > 1.0
    assert 0 < moved.sum() < len(moved)
    np.testing.assert_allclose(np.hypot(y[..., 1], y[..., 4]), np.hypot(x[..., 1], x[..., 4]), rtol=1e-5)
    np.testing.assert_array_equal(y[..., 6:], x[..., 6:])
    for key in ("t", "r", "dt", "mode"):
        assert np.array_equal(tt[key].numpy(), td[key].numpy())
    np.testing.assert_array_equal(np.isnan(tt["measurements"].numpy()), np.isnan(td["measurements"].numpy()))
    np.testing.assert_allclose(tt["turn_rate"].numpy(), real.turn_rate(y), atol=1e-6)
    # an added turn banked at most 30 deg, at each window's mean speed
    speed = np.hypot(x[..., 1], x[..., 4]).mean(1, keepdims=True)
    added = real.turn_rate(y) - real.turn_rate(x)
    assert np.all(np.abs(added) <= 9.80665 * np.tan(np.radians(30)) / speed + 1e-6)
    assert np.abs(added[moved]).max() > 9.80665 * np.tan(np.radians(20)) / speed.max() - 1e-6
    real.turned_flights(train, tmp_path / "again", 0.5, seed=3, bank=(20.0, 30.0))
    assert _digest(tmp_path / "again") == _digest(tmp_path / "t")
    with pytest.raises(ValueError, match="replace its own source"):
        real.turned_flights(train, train, 0.5, overwrite=True)
    with pytest.raises(ValueError, match="turns is the share"):
        real.turned_flights(train, tmp_path / "bad", 2.0)
    from immnet.data.spec import DataSpec
    from immnet.data.storage import write_dataset

    last = write_dataset(tmp_path / "3dlast", 4, 0, DataSpec(T=120), progress=False)
    with pytest.raises(ValueError, match="is not real flights"):
        real.turned_flights(last, tmp_path / "bad", 0.5)
    assert not (tmp_path / "bad").exists()
    monkeypatch.setattr(immnet.cli, "_COMMAND_MODULES", ("immnet.data.cli",))
    assert immnet.cli.main(["data", "turns", "--data", str(train), "--out", str(tmp_path / "cli"), "--turns", "0.5",
                            "--bank", "20,30", "--seed", "3"]) == 0
    assert "turns added to a share 0.5" in capsys.readouterr().out
    assert _digest(tmp_path / "cli") == _digest(tmp_path / "t")
    with pytest.raises(SystemExit):
        immnet.cli.main(["data", "turns", "--data", str(train), "--out", str(tmp_path / "x"), "--turns", "0.5",
                         "--bank", "20"])
    assert "expected LOW,HIGH" in capsys.readouterr().err
