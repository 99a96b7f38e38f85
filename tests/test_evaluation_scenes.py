"""``immnet evaluate --data SCENES``: the multi-target tracker scored on a tiny scene set (GOSPA per scan checked
against a brute-force GOSPA written here), the filter told the association (checked against one filter per aircraft
stepped by hand), the W&B run in offline mode, and the refusals."""

import json
import subprocess
import sys

import numpy as np
import pytest

import immnet.cli
from immnet.cli import main
from immnet.data.scenes import SceneSpec, load_scene, observe, save_scene
from immnet.evaluation.scenes import RAW, TOLD, run_told
from immnet.filters.multi import MultiTargetTracker, TrackFilter, TwoPointStart

FILTER = "real-ca-5s"


@pytest.fixture(autouse=True)
def only_our_commands(monkeypatch):
    monkeypatch.setattr(immnet.cli, "_COMMAND_MODULES", ("immnet.evaluation.cli",))


def _scene(seed: int, name: str, split: str, pd: float = 0.9, clutter: float = 3.0, S: int = 18):
    """Three straight flights 8-20 km from a radar at the origin, scans every 4.5-5.5 s."""
    rng = np.random.default_rng(seed)
    spec = SceneSpec(pd=pd, clutter=clutter, max_range=30_000.0)
    t = np.cumsum(np.r_[0.0, rng.uniform(4.5, 5.5, S - 1)])
    starts = np.array([[8000.0, 2000.0, 3000.0], [-6000.0, 12000.0, 5000.0], [2000.0, -15000.0, 7000.0]])
    vels = np.array([[150.0, 80.0, 0.0], [120.0, -60.0, 2.0], [-90.0, 140.0, 0.0]])
    states = np.zeros((3, S, 9))
    states[..., 0::3] = starts[:, None] + vels[:, None] * t[None, :, None]
    states[..., 1::3] = vels[:, None]
    states[2, :3] = np.nan  # the third aircraft enters the cover at the fourth scan
    meta = {"format": "scene", "version": 1, "kind": "3d-last", "name": name, "split": split, "sample": "test",
            "spec": spec.to_dict()}
    return observe(states, t, spec, rng, ["a", "b", "c"], [np.nan] * 3, meta)


@pytest.fixture(scope="module")
def scene_set(tmp_path_factory):
    root = tmp_path_factory.mktemp("scenes")
    entries = []
    for i, (seed, split) in enumerate(((1, "train"), (2, "test"), (3, "test"))):
        sc = _scene(seed, f"tiny-{i:02d}", split)
        rel = f"{split}/{sc.name}.npz"
        save_scene(sc, root / rel)
        entries.append({"name": sc.name, "file": rel, "split": split, "kind": "3d-last", "sample": "test",
                        "counts": sc.meta["counts"]})
    (root / "scenes.json").write_text(json.dumps({"format": "scene", "version": 1, "scenes": entries}))
    return root


def brute_gospa(X, Y, c=200.0, p=2.0, alpha=2.0) -> float:
    """GOSPA by enumerating every injection of the smaller set into the larger (``alpha = 2``: the cut-off distance
    ``min(d, c)`` per pair, ``c^p / alpha`` per point left over)."""
    import itertools

    X, Y = np.asarray(X).reshape(-1, 3), np.asarray(Y).reshape(-1, 3)
    if len(X) > len(Y):
        X, Y = Y, X
    best = np.inf
    for perm in itertools.permutations(range(len(Y)), len(X)):
        cost = sum(min(np.linalg.norm(X[i] - Y[j]), c) ** p for i, j in enumerate(perm))
        best = min(best, cost)
    return float((best + c**p / alpha * (len(Y) - len(X))) ** (1 / p))


def run_cli(scene_set, out, *extra) -> dict:
    assert main(["evaluate", "--data", str(scene_set), "--methods", FILTER, "--json", str(out / "r.json"), "--quiet",
                 *extra]) == 0
    return json.loads((out / "r.json").read_text())


def test_scores_are_gospa_of_the_confirmed_tracks(scene_set, tmp_path, capsys):
    doc = run_cli(scene_set, tmp_path)
    table = capsys.readouterr().out
    assert doc["kind"] == "scenes" and doc["scenes"] == ["tiny-01", "tiny-02"]  # --split test: the held-out ones
    # the record holds every setting the tracker ran with, the start's prior and min_coast among them
    want = {k: v for k, v in MultiTargetTracker(FILTER).settings().items() if k not in ("pd", "clutter_density")}
    assert doc["tracker"] == json.loads(json.dumps(want))
    assert doc["tracker"]["init"] == {"max_speed": 350.0, "sigma": 3.0, "vz_std": 5.0, "p_cv": 0.9}
    assert doc["tracker"]["min_coast"] == 4.0 and doc["tracker"]["confirm"]["alpha"] == 1e-7  # TrackScore()
    assert list(doc["methods"]) == [FILTER, FILTER + TOLD, RAW]
    for name in doc["methods"]:
        assert name in table
    all_scans, raw_scans = [], []
    for name in doc["scenes"]:
        sc = load_scene(scene_set / "test" / f"{name}.npz")
        tracker = MultiTargetTracker(FILTER)
        got = doc["methods"][FILTER]["scenes"][name]
        want = []
        for k, (t, plots, cov) in enumerate(sc.scans()):
            reps = tracker.step(t, plots, cov)
            want.append(brute_gospa(sc.truth(k)[0], [r.state[[0, 3, 6]] for r in reps]))
            a, b = sc.plot_offsets[k], sc.plot_offsets[k + 1]
            raw_scans.append(brute_gospa(sc.truth(k)[0], sc.plots[a:b][sc.plot_source[a:b] >= 0]))
        assert got["gospa_per_scan"] == pytest.approx(want, abs=1e-6)
        assert got["gospa"] == pytest.approx(np.mean(want))
        assert got["t"] == pytest.approx(sc.t - sc.t[0])
        all_scans += want
    mean = doc["methods"][FILTER]["mean"]
    assert mean["gospa"] == pytest.approx(np.mean(all_scans))  # over every scan of both scenes
    assert mean["scans"] == len(all_scans)
    assert doc["methods"][RAW]["mean"]["gospa"] == pytest.approx(np.mean(raw_scans))
    assert doc["methods"][FILTER + TOLD]["mean"]["id_switches"] == 0
    for r in doc["methods"].values():
        ms = r["mean"]["ms_per_scan"]
        assert 0 <= ms["median"] <= ms["max"]


def test_a_shipped_network_is_a_method_of_the_scenes(scene_set, tmp_path):
    """``--methods real-ca-5s,radar-5s``: the network's rows beside the model-based filter's, its scores those of
    ``MultiTargetTracker("radar-5s")`` on each scene (GOSPA by brute force), its told row the network told the
    association (no id switch)."""
    doc = run_cli(scene_set, tmp_path, "--methods", f"{FILTER},radar-5s")
    assert list(doc["methods"]) == [FILTER, FILTER + TOLD, "radar-5s", "radar-5s" + TOLD, RAW]
    for name in doc["scenes"]:
        sc = load_scene(scene_set / "test" / f"{name}.npz")
        tracker = MultiTargetTracker("radar-5s")
        want = [brute_gospa(sc.truth(k)[0], [r.state[[0, 3, 6]] for r in tracker.step(t, plots, cov)])
                for k, (t, plots, cov) in enumerate(sc.scans())]
        assert doc["methods"]["radar-5s"]["scenes"][name]["gospa_per_scan"] == pytest.approx(want, abs=1e-6)
    assert doc["methods"]["radar-5s" + TOLD]["mean"]["id_switches"] == 0
    # in a W&B run's config: the network by name with its checkpoint's checksum, as weights.json lists it
    from immnet.checkpoints import WEIGHTS
    from immnet.evaluation.cli import filter_info

    info = filter_info("radar-5s")
    assert info["network"] == "radar-5s"
    assert info["checkpoint"]["weights_sha256"] == WEIGHTS["radar-5s"]["weights_sha256"]
    assert "config" in filter_info(FILTER)
    # the default, the IMMs by scan interval: each band's method with its config
    bands = filter_info("real-imm-by-interval")["by_interval"]
    assert [(b["longest_interval"], b["method"]) for b in bands] == [(3.0, "real-imm"), (6.0, "mtt-imm-5s"),
                                                                      (float("inf"), "real-imm-11s")]
    assert all(b["config"].endswith(f"{b['method']}.yaml") for b in bands)


def test_told_association_is_one_filter_per_aircraft_by_hand():
    """The told reference (batched, with coasting, deletion after 2 misses and restarts) gives at every scan the
    estimates of one filter per aircraft stepped by hand on that aircraft's plots alone; clutter never enters."""
    sc = _scene(7, "told", "test", pd=0.6, clutter=20.0, S=25)
    got = run_told(sc, FILTER, delete_after=2)
    want = [[] for _ in range(len(sc))]
    for ac in range(len(sc.aircraft)):
        f, seed, misses, t_prev = None, None, 0, None
        for k in range(len(sc)):
            t, plots, cov = sc.scan(k)
            a, b = sc.plot_offsets[k], sc.plot_offsets[k + 1]
            j = np.flatnonzero(sc.plot_source[a:b] == ac)
            plot = (plots[j[0]], cov[j[0]]) if len(j) else None
            if f is not None:
                f.predict(t - t_prev)
                f.update(np.full((1, 3), np.nan) if plot is None else plot[0][None], np.eye(3)[None] if plot is None else plot[1][None])
                misses = 0 if plot is not None else misses + 1
                if misses >= 2:
                    f = None
                else:
                    plot = None  # taken by the track
            if f is None and plot is not None:
                if seed is None:
                    seed = (t, *plot)
                else:
                    f = TrackFilter.from_method(FILTER)
                    f.start(plot[0][None], plot[1][None], seed[1][None], seed[2][None], t - seed[0],
                            TwoPointStart().vz_std)  # the tracker's start, its vertical-speed prior
                    seed, misses = None, 0
            if f is not None:
                want[k].append(f.state()[0][0, [0, 3, 6]])
            t_prev = t
    assert sum(len(w) for w in want) > 0 and any(len(w) < 3 for w in want[5:])  # coasting and deleted tracks occur
    for k in range(len(sc)):
        g = np.sort(np.asarray(got["est_pos"][k]).reshape(-1, 3), axis=0)
        w = np.sort(np.asarray(want[k]).reshape(-1, 3), axis=0)
        assert g.shape == w.shape and np.allclose(g, w, atol=1e-6), k


def records(run_dir) -> list[dict]:
    proc = subprocess.run([sys.executable, "-m", "wandb", "leet", "inspect", "--json", str(run_dir)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return [json.loads(line) for line in proc.stdout.splitlines() if line.strip()]


def test_wandb_offline_logs_the_table_and_gospa_over_time_per_scene(scene_set, tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    for var in ("WANDB_RUN_GROUP", "WANDB_NAME", "WANDB_JOB_TYPE", "WANDB_PROJECT", "WANDB_DIR"):
        monkeypatch.delenv(var, raising=False)
    doc = run_cli(scene_set, tmp_path, "--split", "all", "--wandb", "--wandb-dir", str(tmp_path / "w"))
    runs = list((tmp_path / "w" / "wandb").glob("offline-run-*"))
    assert len(runs) == 1
    recs = records(runs[0])
    history, summary, config = {}, {}, {}
    for r in recs:
        if r["type"] == "history":
            history.update(r["history"]["item"])
        elif r["type"] == "summary":
            summary.update(r["summary"]["update"])
    run = next(r["run"] for r in recs if r["type"] == "run")
    config = {**run["config"]["update"]}
    assert config["data"]["kind"] == "scenes" and config["data"]["scenes"] == ["tiny-00", "tiny-01", "tiny-02"]
    assert config["tracker"] == doc["tracker"]
    table = json.loads((runs[0] / "files" / history["results.path"]).read_text())
    rows = {row[0]: dict(zip(table["columns"], row)) for row in table["data"]}
    assert list(rows) == list(doc["methods"])
    for name, r in doc["methods"].items():
        assert rows[name]["GOSPA [m]"] == pytest.approx(r["mean"]["gospa"])
        assert rows[name]["id switches"] == r["mean"]["id_switches"]
        assert summary[f"{name}/gospa"] == pytest.approx(r["mean"]["gospa"])
        lines = json.loads((runs[0] / "files" / history[f"gospa_over_time/{name}_table.path"]).read_text())
        cols = lines["columns"]
        assert {row[cols.index("lineKey")] for row in lines["data"]} == set(doc["scenes"])  # a line per scene
        mine = [row for row in lines["data"] if row[cols.index("lineKey")] == "tiny-01"]
        assert [row[cols.index("lineVal")] for row in mine] == pytest.approx(r["scenes"]["tiny-01"]["gospa_per_scan"])


@pytest.mark.parametrize("args, message", [
    (["--figures", "figs"], "--figures is for trajectory data sets; {data} is a scene set, scored by GOSPA"),
    (["--checkpoint", "x.ckpt"], "--checkpoint is for trajectory data sets; {data} is a scene set"),
    (["--told-r"], "--told-r is for trajectory data sets; {data} is a scene set"),
    (["--batch-size", "8"], "--batch-size is for trajectory data sets; {data} is a scene set"),
    (["--methods", "immnet"], "immnet is a IMMNet"),
    (["--methods", "real-imm-channel-5s"], "an IMM with modes per channel is not a multi-target filter"),
    (["--methods", ","], "--methods is empty"),
    (["--methods", "radar-5s", "--associator", "jpda"], "radar-5s is a network: JPDA needs a mixture update"),
    (["--limit", "0"], "--limit must be positive"),
])
def test_refusals(scene_set, tmp_path, capsys, args, message):
    assert main(["evaluate", "--data", str(scene_set), "--quiet", "--json", str(tmp_path / "r.json"), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("immnet evaluate: error: ")
    assert message.format(data=scene_set) in err[0]
    assert not (tmp_path / "r.json").exists()


def test_no_scenes_of_the_split_and_associator_on_trajectories(scene_set, tmp_path, capsys):
    only_train = tmp_path / "train-only"
    only_train.mkdir()
    index = json.loads((scene_set / "scenes.json").read_text())
    index["scenes"] = [e for e in index["scenes"] if e["split"] == "train"]
    (only_train / "scenes.json").write_text(json.dumps(index))
    assert main(["evaluate", "--data", str(only_train), "--quiet"]) == 2
    assert f"{only_train} has no test scenes (split test); --split all takes every scene" in capsys.readouterr().err
    npz = tmp_path / "d.npz"
    np.savez(npz, measurements=np.zeros((1, 4, 3)))
    assert main(["evaluate", "--data", str(npz), "--associator", "jpda", "--quiet"]) == 2
    assert f"--associator is for scene sets (immnet data scenes); {npz} is not one" in capsys.readouterr().err


def test_immnet_tune_on_scenes_scores_the_trackers_gospa_on_training_scenes_only(scene_set, tmp_path, capsys,
                                                                                  monkeypatch):
    """``immnet tune --scenes``: the written filter's score is the multi-target tracker's mean GOSPA with it on the
    set's training scenes (scored here by ``evaluate_scenes``, the table's own scoring), at least as low as the
    search's start; the test scenes are never read (made unreadable here); a set without training scenes is
    refused in one line."""
    import shutil

    import yaml

    from immnet.config import build, instantiate
    from immnet.evaluation.scenes import evaluate_scenes
    from immnet.evaluation.search import Search

    monkeypatch.setattr(immnet.cli, "_COMMAND_MODULES", ("immnet.evaluation.tune_cli",))
    scenes = tmp_path / "scenes"
    shutil.copytree(scene_set, scenes)
    for path in (scenes / "test").iterdir():
        path.write_bytes(b"not a scene")
    search = tmp_path / "ca.yaml"
    search.write_text(yaml.safe_dump({
        "method": {"class_path": "immnet.filters.KalmanFilterTracker",
                   "init_args": {"name": "ca", "r": "data", "sigma_q": 0.05,
                                 "model": {"class_path": "immnet.motion.ConstantAcceleration",
                                           "init_args": {"noise": "continuous"}}}},
        "grid": {"sigma_q": [0.05, 0.5, 2.0]}}))
    out = tmp_path / "ca-scenes.yaml"
    assert main(["tune", "--search", str(search), "--scenes", str(scenes), "--out", str(out), "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    train = [load_scene(scenes / "train" / "tiny-00.npz")]

    def gospa(method) -> float:
        filt = TrackFilter.of_method(method, "ca")
        return evaluate_scenes(train, [filt], told=False, raw=False)[filt]["mean"]["gospa"]

    start = gospa(instantiate(Search.from_yaml(search).config({"sigma_q": 0.05})))
    assert gospa(build(out)) == pytest.approx(result["score"], rel=1e-12) and result["score"] <= start
    header = out.read_text().splitlines()[0]
    assert f"--scenes {scenes}" in header and "1 training scenes, never a test scene" in header
    empty = tmp_path / "no-train"
    empty.mkdir()
    index = json.loads((scene_set / "scenes.json").read_text())
    (empty / "scenes.json").write_text(json.dumps({**index, "scenes": [e for e in index["scenes"]
                                                                          if e["split"] == "test"]}))
    assert main(["tune", "--search", str(search), "--scenes", str(empty), "--out", str(tmp_path / "x.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{empty}: no training scenes (split train) to tune on" in err[0]
    assert not (tmp_path / "x.yaml").exists()


def test_the_told_reference_deletes_by_the_trackers_position_std():
    """``evaluate_scenes``' told-association row is ``run_told`` with the tracker's deletion rules, ``max_pos_std``
    among them: at 60 m (a track's position std passes it between plots) its GOSPA is ``run_told``'s at 60 m, not
    at the default."""
    from immnet.evaluation.scenes import evaluate_scenes, score

    sc = _scene(11, "pos-std", "test", pd=0.6, clutter=5.0, S=25)
    told = evaluate_scenes([sc], [FILTER], raw=False, settings={"max_pos_std": 60.0})[FILTER + TOLD]
    got = told["scenes"][sc.name]["gospa"]
    assert got == score(sc, run_told(sc, FILTER, max_pos_std=60.0))["gospa"]
    assert got != score(sc, run_told(sc, FILTER))["gospa"]
