"""Multi-target scenes (immnet.data.scenes): reproducible, the radar's statistics as set, plots that convert back
to the truth within the noise, the plot CSV, the split of samples."""

from __future__ import annotations

import math

import numpy as np
import pytest

import immnet.cli
from immnet.data import adsb, radar
from immnet.data import scenes as S

SMALL = S.SceneSpec(duration=60.0, targets=4, crossing_pairs=1, close_pairs=1, last_step=0.25)
needs_samples = pytest.mark.skipif(adsb.samples_dir() is None, reason="traffic's sample files are not installed")


@pytest.fixture(scope="module")
def quickstart():
    return S.sample_flights("collections/quickstart")[0]


@pytest.fixture(scope="module")
def quick_scene(quickstart):
    return S.adsb_scenes("collections/quickstart", 1, SMALL, seed=0, flights=quickstart)[0]


def _same(a: S.Scene, b: S.Scene) -> bool:
    return all(np.array_equal(x, y, equal_nan=x.dtype.kind == "f") for x, y in zip(a.arrays().values(),
                                                                                     b.arrays().values())) \
        and a.meta == b.meta


def test_3dlast_scene_is_seeded_and_reproducible():
    a, b = S.last_scene(0, SMALL, seed=3), S.last_scene(0, SMALL, seed=3)
    assert _same(a, b)
    c = S.last_scene(0, SMALL, seed=4)
    assert not np.array_equal(a.t, c.t) or not np.array_equal(a.plots, c.plots)
    assert a.meta["counts"]["aircraft"] == 4 and list(a.aircraft) == ["crossing0a", "crossing0b", "close1a", "close1b"]


def test_3dlast_pairs_cross_and_fly_close():
    """At some scan a crossing pair is within crossing_miss horizontally (and 50 m vertically) at 30-150 degrees of
    heading; a close pair is within close_separation at 10 degrees at most: measured on the stored truth."""
    sc = S.last_scene(1, SMALL, seed=0)
    st = np.stack([np.stack([sc.truth_states[sc.truth_offsets[k]:sc.truth_offsets[k + 1]][sc.truth(k)[1] == i][0]
                             for k in range(len(sc))]) for i in range(4)])
    heading = np.degrees(np.arctan2(st[..., 4], st[..., 1]))

    def apart(i, j):
        return np.linalg.norm(st[i][:, [0, 3]] - st[j][:, [0, 3]], axis=-1), np.abs(st[i][:, 6] - st[j][:, 6]), \
            np.abs((heading[i] - heading[j] + 180) % 360 - 180)

    h, v, turn = apart(0, 1)
    meet = (h <= SMALL.crossing_miss + 1e-6) & (v <= 50 + 1e-6)
    assert meet.any() and (30 - 1e-6 <= turn[meet]).all() and (turn[meet] <= 150 + 1e-6).all()
    h, v, turn = apart(2, 3)
    lo, hi = SMALL.close_separation
    side = (lo - 1e-6 <= h) & (h <= hi + 1e-6) & (v <= 100 + 1e-6) & (turn <= 10 + 1e-6)
    assert side.any()


@needs_samples
def test_adsb_scene_is_seeded_and_reproducible(quickstart, quick_scene):
    again = S.adsb_scenes("collections/quickstart", 1, SMALL, seed=0, flights=quickstart)[0]
    assert _same(quick_scene, again)
    other = S.adsb_scenes("collections/quickstart", 1, SMALL, seed=1, flights=quickstart)[0]
    assert not _same(quick_scene, other)
    per_scan = np.diff(quick_scene.truth_offsets)
    assert per_scan.min() >= SMALL.min_targets and per_scan.max() <= SMALL.max_targets


def test_detection_probability_and_clutter_rate_match_their_settings():
    """Counts over many scans against the binomial and Poisson laws: 4 standard deviations either way."""
    spec = S.SceneSpec(pd=0.7, clutter=4.0, max_range=50_000.0, min_range=1_000.0, max_elevation=20.0)
    A, n_scans = 12, 1500
    rng = np.random.default_rng(0)
    enu = np.stack([rng.uniform(-30e3, 30e3, A), rng.uniform(-30e3, 30e3, A), rng.uniform(2e3, 9e3, A)], -1)
    states = np.zeros((A, n_scans, 9))
    states[..., [0, 3, 6]] = enu[:, None, :]
    sc = S.observe(states, np.arange(n_scans) * 5.0, spec, np.random.default_rng(1), [f"a{i}" for i in range(A)],
                   [np.nan] * 3, {})
    n_truth = A * n_scans
    assert len(sc.truth_id) == n_truth  # every aircraft in cover at every scan
    det = int((sc.plot_source >= 0).sum())
    assert abs(det - spec.pd * n_truth) <= 4 * math.sqrt(n_truth * spec.pd * (1 - spec.pd))
    per_scan = np.array([(sc.plot_source[a:b] < 0).sum() for a, b in zip(sc.plot_offsets[:-1], sc.plot_offsets[1:])])
    lam = spec.clutter
    assert abs(per_scan.sum() - lam * n_scans) <= 4 * math.sqrt(lam * n_scans)
    # a Poisson count's variance equals its mean: Var(s^2) ~ (mu4 - sigma^4) / n = (lam + 2 lam^2) / n
    assert abs(per_scan.var(ddof=1) - lam) <= 4 * math.sqrt((lam + 2 * lam * lam) / n_scans)
    # clutter uniform over the cover in range, azimuth and elevation: the means of uniform laws
    c = sc.plot_polar[sc.plot_source < 0]
    for col, lo, hi in ((0, spec.min_range, spec.max_range), (1, 0.0, 2 * math.pi),
                        (2, 0.0, math.radians(spec.max_elevation))):
        assert lo <= c[:, col].min() and c[:, col].max() <= hi
        assert abs(c[:, col].mean() - (lo + hi) / 2) <= 4 * (hi - lo) / math.sqrt(12 * len(c))
    # every detection's aircraft appears at most once per scan
    for a, b in zip(sc.plot_offsets[:-1], sc.plot_offsets[1:]):
        src = sc.plot_source[a:b]
        assert len(set(src[src >= 0])) == (src >= 0).sum()


def _residuals(sc: S.Scene):
    """Per detection: the polar residual against its aircraft's truth, and the ENU residual with its covariance."""
    dpol, denu, covs = [], [], []
    for k in range(len(sc)):
        a, b = sc.plot_offsets[k], sc.plot_offsets[k + 1]
        pos, ids = sc.truth(k)
        for i in range(a, b):
            s = sc.plot_source[i]
            if s < 0:
                continue
            p = pos[ids == s][0]
            rho, az, el = radar.polar(p)
            d = sc.plot_polar[i] - np.array([rho, az, el])
            d[1] = (d[1] + math.pi) % (2 * math.pi) - math.pi
            dpol.append(d)
            denu.append(sc.plots[i] - p)
            covs.append(sc.plot_cov[i])
    return np.array(dpol), np.array(denu), np.array(covs)


def _check_noise(sc: S.Scene, spec: S.SceneSpec):
    assert np.allclose(sc.plots, radar.from_polar(*sc.plot_polar.T), rtol=0, atol=1e-6)
    dpol, denu, covs = _residuals(sc)
    n = len(dpol)
    z = dpol / np.array([spec.sigma_range, math.radians(spec.sigma_azimuth_deg),
                         math.radians(spec.sigma_elevation_deg)])
    assert np.abs(z).max() < 5.5
    assert (np.abs(z.mean(0)) <= 4 / math.sqrt(n)).all()
    # the sample variance of n standard normals: 1 +- 4 sqrt(2 / n)
    assert (np.abs(z.var(0) - 1) <= 4 * math.sqrt(2 / n)).all()
    # the ENU plots against their own covariance: Mahalanobis distances ~ chi^2(3) (to first order), mean 3, var 6
    d2 = np.einsum("ni,ni->n", denu, np.linalg.solve(covs, denu[..., None])[..., 0])
    assert abs(d2.mean() - 3) <= 4 * math.sqrt(6 / n) + 0.05


def test_plots_convert_back_to_the_truth_within_the_noise_3dlast():
    spec = S.SceneSpec(duration=300.0, targets=6, crossing_pairs=1, close_pairs=1)
    _check_noise(S.last_scene(2, spec, seed=0), spec)


@needs_samples
def test_plots_convert_back_to_the_truth_within_the_noise_adsb(quick_scene):
    _check_noise(quick_scene, SMALL)
    assert not np.isnan(quick_scene.site).any()


def test_plot_csv_round_trips(tmp_path):
    sc = S.last_scene(0, S.SceneSpec(duration=60.0, targets=2, crossing_pairs=1, close_pairs=0, pd=0.5, clutter=0.3),
                      seed=0)
    assert (np.diff(sc.plot_offsets) == 0).any()  # a scan without plots is kept too
    path = S.write_plots_csv(sc, tmp_path / "plots.csv")
    got = S.read_plots_csv(path)
    assert [t for t, _ in got] == sc.t.tolist()
    for k, (t, p) in enumerate(got):
        a, b = sc.plot_offsets[k], sc.plot_offsets[k + 1]
        want = sc.plot_polar[a:b]
        assert np.array_equal(p, np.c_[want[:, 0], np.degrees(want[:, 1:])])
        assert np.allclose(radar.from_polar(p[:, 0], np.radians(p[:, 1]), np.radians(p[:, 2])), sc.plots[a:b],
                           rtol=0, atol=1e-6)
    bad = tmp_path / "bad.csv"
    bad.write_text("t,range,azimuth,elevation\n1,100,2,x\n")
    with pytest.raises(ValueError, match="line 2: column .elevation. is not a number: .x."):
        S.read_plots_csv(bad)


def test_scene_file_round_trips_and_refuses_what_is_not_a_scene(tmp_path):
    sc = S.last_scene(0, SMALL, seed=0)
    back = S.load_scene(S.save_scene(sc, tmp_path / "s.npz"))
    assert _same(sc, back)
    np.savez(tmp_path / "other.npz", t=np.zeros(3))
    with pytest.raises(ValueError, match="not a scene: the array"):
        S.load_scene(tmp_path / "other.npz")
    arrays = sc.arrays()
    arrays["aircraft"] = np.array([{"x": 1}] * len(sc.aircraft), dtype=object)
    np.savez(tmp_path / "pickled.npz", meta=np.asarray("{}"), **arrays)
    with pytest.raises(ValueError, match="pickled.npz"):  # object arrays need pickle: refused, never run
        S.load_scene(tmp_path / "pickled.npz")


@needs_samples
def test_a_quickstart_scene_never_holds_a_flight_of_another_sample(quickstart):
    spec = S.SceneSpec(duration=60.0)
    got = S.adsb_scenes("collections/quickstart", 3, spec, seed=0, flights=quickstart)
    swiss = {f.id for f in S.sample_flights("collections/switzerland")[0]}
    mine = {f.id for f in quickstart}
    assert len(got) == 3
    for sc in got:
        assert sc.meta["split"] == "train" and sc.meta["samples_of_aircraft"] == ["collections/quickstart"]
        assert set(sc.aircraft) <= mine and not set(sc.aircraft) & swiss
    starts = sorted(sc.meta["start"] for sc in got)
    assert np.diff(starts).min() >= spec.duration  # windows do not overlap
    assert S.split_of("collections/quickstart") == "train"
    assert S.split_of(str(adsb.resolve_sample("collections/quickstart"))) == "train"  # the same file by its path
    assert S.split_of("collections/switzerland") == "test"


@needs_samples
def test_cli_writes_a_set_and_refuses_bad_settings(tmp_path, capsys):
    out = tmp_path / "scenes"
    args = ["data", "scenes", "--samples", "collections/quickstart", "--out", str(out), "--n", "1", "--last", "1",
            "--duration", "40", "--quiet", "--csv"]
    assert immnet.cli.main(args) == 0
    index = S.load_index(out)
    assert [(e["split"], e["kind"]) for e in index["scenes"]] == [("train", "adsb"), ("test", "3d-last")]
    assert len(S.load_split(out, "train")) == 1 and (out / "test" / "3dlast-00.csv").is_file()
    bad = tmp_path / "bad"
    assert immnet.cli.main(["data", "scenes", "--last", "1", "--out", str(bad), "--pd", "0"]) == 2
    assert "pd (detection probability) must be in (0, 1], got 0.0" in capsys.readouterr().err
    assert immnet.cli.main(["data", "scenes", "--out", str(bad)]) == 2
    assert "no scenes asked for" in capsys.readouterr().err
    # no window fits: the line names the sample, what was asked and the options that would change it
    assert immnet.cli.main(["data", "scenes", "--samples", "collections/quickstart", "--out", str(bad),
                            "--targets-in-cover", "40,50"]) == 2
    err = capsys.readouterr().err
    assert "sample collections/quickstart: no window of 300 s with 40-50 aircraft in cover" in err
    assert err.rstrip().endswith("(try --max-range, --site or --targets-in-cover)")
    assert not bad.exists() and not list(tmp_path.glob(".bad*"))


def _gospa_brute(X, Y, c=200.0, p=2.0, alpha=2.0) -> float:
    """GOSPA by enumerating every partial assignment (pairs closer than c), for a handful of points."""
    import itertools

    best = (c**p / alpha) * (len(X) + len(Y))
    for k in range(1, min(len(X), len(Y)) + 1):
        for xs in itertools.combinations(range(len(X)), k):
            for ys in itertools.permutations(range(len(Y)), k):
                d = [np.linalg.norm(X[i] - Y[j]) for i, j in zip(xs, ys)]
                if max(d) < c:
                    best = min(best, sum(v**p for v in d) + (c**p / alpha) * (len(X) + len(Y) - 2 * k))
    return best ** (1 / p)


def test_the_peer_benchmark_scores_gospa_as_its_definition():
    pytest.importorskip("stonesoup")
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import mtt_peer

    rng = np.random.default_rng(0)
    tid, tpos, eid, epos = [], [], [], []
    for n, m in ((0, 0), (3, 0), (0, 2), (3, 3), (2, 4), (4, 2)):
        tpos.append(rng.uniform(0, 400, (n, 3)))
        epos.append(rng.uniform(0, 400, (m, 3)))
        tid.append(np.arange(n))
        eid.append(np.arange(m))
    got = mtt_peer.score(tid, tpos, eid, epos)
    want = [_gospa_brute(X, Y) for X, Y in zip(tpos, epos)]
    assert np.allclose(got["gospa_per_scan"], want, rtol=1e-9, atol=1e-9)
    assert got["gospa"] == pytest.approx(np.mean(want))
