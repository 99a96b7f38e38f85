"""Tuning a model-based method (``immnet.evaluation.search``, ``immnet tune``): the coordinate search, search
files, and the refusal to tune on a test split."""

import json

import pytest
import yaml

from immnet import keys
from immnet.cli import main
from immnet.config import REPO_ROOT, build, instantiate
from immnet.data.spec import DataSpec
from immnet.data.storage import write_dataset
from immnet.evaluation.search import Search, average_rmse, coordinate_search, set_path
from immnet.evaluation.tune_cli import tuning_data

SEARCHES = sorted((REPO_ROOT / "configs" / "tuning").glob("*.yaml"))


def test_coordinate_search_finds_a_separable_minimum_and_scores_each_setting_once():
    calls = []

    def score(s):
        calls.append(dict(s))
        return (s["a"] - 2) ** 2 + (s["b"] + 1) ** 2

    best, value, table = coordinate_search(score, {"a": [0, 1, 2, 3], "b": [-2, -1, 0]}, {"a": 0, "b": 0}, progress=False)
    assert best == {"a": 2, "b": -1} and value == 0
    assert len(calls) == len({tuple(c.items()) for c in calls}) == len(table)
    assert [row["score"] for row in table] == sorted(row["score"] for row in table)


def test_set_path_reaches_list_items_and_refuses_a_wrong_path():
    config = {"sigma_q": [1.0, 2.0], "model_set": {"models": [{"init_args": {"vertical": 1.0}}]}}
    out = set_path(config, "model_set.models.0.init_args.vertical", 0.3)
    assert out["model_set"]["models"][0]["init_args"]["vertical"] == 0.3 and config["model_set"]["models"][0]["init_args"]["vertical"] == 1.0
    assert set_path(config, "sigma_q.1", 5.0)["sigma_q"] == [1.0, 5.0]
    with pytest.raises(ValueError, match="not a path"):
        Search({"class_path": "x", "init_args": config}, {"sigma_q.7": [1.0]})
    with pytest.raises(ValueError, match="non-empty list"):
        Search({"class_path": "x", "init_args": config}, {"sigma_q.0": 1.0})


@pytest.mark.parametrize("path", SEARCHES, ids=lambda p: p.stem)
def test_every_search_file_builds_its_method_at_every_grid_value(path):
    """Each knob's values are valid settings of the method (each value built once, the others at the start)."""
    search = Search.from_yaml(path)
    assert path.read_text().startswith("#") and "immnet tune --search" in path.read_text().splitlines()[1]
    for knob, values in search.grid.items():
        for v in values:
            method = instantiate(search.config({**search.start, knob: v}))
            r = search.method["init_args"].get("r")  # told each track's r or each detection's covariance, or neither
            needs = {"data": (keys.R,), "detection": (keys.MEAS_COV,)}.get(r, ())
            assert method.any_interval and method.needs == needs


def _kalman_search(path, model: str, sigmas: list[float]):
    """A search file at ``path``: one Kalman filter of ``model`` (continuous noise, told r) from sigma_q 2, over
    ``sigmas``; named after the file."""
    path.write_text(yaml.safe_dump({
        "method": {"class_path": "immnet.filters.KalmanFilterTracker",
                   "init_args": {"name": path.stem, "r": "data", "sigma_q": 2.0,
                                 "model": {"class_path": f"immnet.motion.{model}", "init_args": {"noise": "continuous"}}}},
        "grid": {"sigma_q": sigmas},
    }))
    return path


def test_immnet_tune_writes_the_best_config_with_its_score_and_refuses_a_test_split(tmp_path, capsys):
    """On a small 3D-LAST set: the written config builds a method whose Average RMSE is the reported score, and
    is at least as good as the search's start."""
    spec = DataSpec(T=120)
    train = write_dataset(tmp_path / "train", 24, 5, spec, progress=False)
    search_file = _kalman_search(tmp_path / "ca.yaml", "ConstantAcceleration", [0.3, 1.0, 2.0])
    out = tmp_path / "ca-tuned.yaml"
    assert main(["tune", "--search", str(search_file), "--data", str(train), "--out", str(out), "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    batch = tuning_data([train])  # float64 of the stored float32 set, as the search scored it
    tuned = average_rmse(build(out), batch)
    assert tuned == pytest.approx(result["score"], rel=1e-6)
    start = average_rmse(instantiate(Search.from_yaml(search_file).config({"sigma_q": 2.0})), batch)
    assert tuned <= start
    assert "never a test split" in out.read_text().splitlines()[0]
    assert yaml.safe_load(out.read_text())["init_args"]["name"] == "ca-tuned"  # the registry's name: its file's

    test = tmp_path / "test"
    test.mkdir()
    meta = json.loads((train / "meta.json").read_text())
    for part in train.iterdir():
        (test / part.name).symlink_to(part)
    (test / "meta.json").unlink()
    (test / "meta.json").write_text(json.dumps({**meta, "split": "test"}))
    assert main(["tune", "--search", str(search_file), "--data", str(test), "--out", str(tmp_path / "x.yaml")]) == 2
    assert "test split" in capsys.readouterr().err


def test_immnet_tune_on_several_sets_scores_the_geometric_mean_of_each_sets_rmse(tmp_path, capsys):
    """Two sets of different lengths and scales (1 s and 5 s scans): the search's score of the written config is
    the geometric mean of its Average RMSE on each set, computed apart; the header says so."""
    one = write_dataset(tmp_path / "one", 16, 5, DataSpec(T=120), progress=False)
    five = write_dataset(tmp_path / "five", 12, 6, DataSpec(T=90, dt=5.0, r_min=5.0, r_max=35.0, n_segments=2),
                         progress=False)
    search_file = _kalman_search(tmp_path / "cv.yaml", "ConstantVelocity", [0.5, 2.0, 8.0])
    out = tmp_path / "cv-mix.yaml"
    assert main(["tune", "--search", str(search_file), "--data", str(one), str(five), "--out", str(out),
                 "--quiet"]) == 0
    result = json.loads(capsys.readouterr().out)
    sets = tuning_data([one, five])
    assert isinstance(sets, list) and [b.batch_size[0] for b in sets] == [16, 12]
    per_set = [average_rmse(build(out), batch) for batch in sets]
    assert per_set[1] > 3 * per_set[0]  # the 5 s set's error is of another scale
    assert result["score"] == pytest.approx((per_set[0] * per_set[1]) ** 0.5, rel=1e-9)
    assert "geometric mean of the 2 sets' Average RMSE" in out.read_text()
    assert "28 tracks" in out.read_text().splitlines()[0]


def test_a_knob_of_several_paths_sets_each_to_its_value():
    """A grid knob naming paths joined by commas (the two turns of an IMM alike) sets every one of them; its start
    is the first path's value; a wrong path among them is refused by name."""
    config = {"sigma_q": [0.7, 0.2, 0.5, 0.5], "p_stay": 0.95}
    search = Search({"class_path": "x", "init_args": config}, {"sigma_q.2,sigma_q.3": [1.0, 2.0], "p_stay": [0.9]})
    assert search.start == {"sigma_q.2,sigma_q.3": 0.5, "p_stay": 0.95}
    assert search.config({"sigma_q.2,sigma_q.3": 2.0, "p_stay": 0.9})["init_args"] == {
        "sigma_q": [0.7, 0.2, 2.0, 2.0], "p_stay": 0.9}
    with pytest.raises(ValueError, match="'sigma_q.4' is not a path"):
        Search({"class_path": "x", "init_args": config}, {"sigma_q.2,sigma_q.4": [1.0]})
