"""``scripts/real_kinds.py`` (docs/notebook/real-flights.md, "Where the held-out error is, by kind of flight"): each
window's flight is found in the sample that holds it, and the kinds are the samples' folders."""

import runpy

import pytest

from immnet.config import REPO_ROOT
from immnet.data import real
from tests.test_data_adsb import _records, _write


@pytest.fixture(scope="module")
def script():
    return runpy.run_path(str(REPO_ROOT / "scripts" / "real_kinds.py"))


def test_every_window_is_found_in_its_sample_and_kind(tmp_path, script):
    (tmp_path / "gliders").mkdir()
    (tmp_path / "surveys").mkdir()
    a = _write(tmp_path / "gliders" / "a.json.gz", _records(n_aircraft=2, n=200, seed=0))
    b_recs = [{**r, "icao24": "b" + r["icao24"][1:]} for r in _records(n_aircraft=3, n=200, seed=1)]
    b = _write(tmp_path / "surveys" / "b.json.gz", b_recs)
    meta = real.make_adsb(tmp_path / "ab", [a, b], real.RealSpec(T=40, splits=(0, 0, 1), max_range=60_000))
    owners = script["flight_samples"](meta)
    assert {f: script["kind"](s) for f, s in owners.items()} == {
        **{f"abc{k:03d}-1633608000": "gliders" for k in range(2)},
        **{f"bbc{k:03d}-1633608000": "surveys" for k in range(3)}}
    assert script["kind"]("collections/quickstart") == "collections"
    # a flight id in two samples: the second is make_adsb's "#2", and each window is found in its own sample
    (tmp_path / "calibration").mkdir()
    c = _write(tmp_path / "calibration" / "c.json.gz", _records(n_aircraft=1, n=200, seed=0))
    meta = real.make_adsb(tmp_path / "ac", [a, c], real.RealSpec(T=40, splits=(0, 0, 1), max_range=60_000))
    owners = script["flight_samples"](meta)
    assert set(meta["flights"]["test"]) <= set(owners)
    assert script["kind"](owners["abc000-1633608000#2"]) == "calibration"
    assert script["kind"](owners["abc000-1633608000"]) == "gliders"
