"""Method registry, the raw-measurements method, the runner and the results table."""

import math
import sys
import types

import pytest
import torch
from tensordict import TensorDict

from immnet import keys
from immnet.evaluation import RawMeasurements, build_method, evaluate, format_markdown, format_table, to_json
from immnet.filters.methods import available_methods, configured_methods


def _data(n=6, t=30, seed=0):
    g = torch.Generator().manual_seed(seed)
    states = torch.randn(n, t, 9, generator=g, dtype=torch.float64) * 1000
    meas = states[..., [0, 3, 6]] + torch.randn(n, t, 3, generator=g, dtype=torch.float64)
    mode = torch.zeros(n, t, dtype=torch.long)
    mode[:, 10:] = 2
    return TensorDict({keys.STATES: states, keys.MEASUREMENTS: meas, keys.MODE: mode,
                       keys.DT: torch.ones(n, dtype=torch.float64)}, batch_size=[n])


class Offset:
    """Truth plus a constant position offset ``c`` (RMSE ``c`` on every axis), perfect mode probs."""

    needs = (keys.STATES, keys.MODE)
    build_options = {"checkpoint": None}

    def __init__(self, c=1.0, checkpoint=None, name="offset"):
        self.c, self.checkpoint, self.name = c, checkpoint, name

    def track(self, batch):
        state = batch[keys.STATES].clone()
        state[..., [0, 3, 6]] += self.c
        probs = torch.nn.functional.one_hot(batch[keys.MODE], 4).double()
        return TensorDict({keys.STATE: state, keys.MODE_PROBS: probs}, batch_size=batch.batch_size)


@pytest.fixture
def methods_dir(tmp_path, monkeypatch):
    mod = types.ModuleType("fake_methods")
    mod.Offset = Offset
    monkeypatch.setitem(sys.modules, "fake_methods", mod)
    (tmp_path / "offset.yaml").write_text("class_path: fake_methods.Offset\ninit_args: {c: 2.0}\n")
    (tmp_path / "clairvoyant.yaml").write_text("class_path: fake_methods.Offset\ninit_args: {c: 0.5}\n")
    (tmp_path / "broken.yaml").write_text("class_path: no_such_module.Thing\n")
    return tmp_path


def test_raw_measurements_fill_missing_detections():
    z = torch.tensor([[[math.nan] * 3, [1.0, 2, 3], [math.nan] * 3, [4.0, 5, 6], [math.nan] * 3]])
    z = torch.cat([z, torch.full_like(z, math.nan)])  # second trajectory never detected
    out = RawMeasurements().track(TensorDict({keys.MEASUREMENTS: z}, batch_size=[2]))
    s = out[keys.STATE]
    assert s.shape == (2, 5, 9)
    assert s[0, 1:, 0].tolist() == [1, 1, 4, 4] and s[0, 1:, 6].tolist() == [3, 3, 6, 6]
    assert torch.all(s[0, 1:, [1, 2, 4, 5, 7, 8]] == 0)
    # Issue 20, item 3: nothing made up before a track's first detection, nor for a track never detected
    assert torch.isnan(s[0, 0]).all() and torch.isnan(s[1]).all()


def test_build_method_from_yaml_and_checkpoint(methods_dir, tmp_path):
    m = build_method("offset", methods_dir=methods_dir)
    assert isinstance(m, Offset) and m.c == 2.0 and m.name == "offset" and m.checkpoint is None
    ck = tmp_path / "model.ckpt"
    ck.write_text("x")
    assert build_method("offset", checkpoint=ck, methods_dir=methods_dir).checkpoint == str(ck)
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        build_method("offset", checkpoint=tmp_path / "missing.ckpt", methods_dir=methods_dir)
    with pytest.raises(ValueError, match="does not take a checkpoint"):
        build_method("measurements", checkpoint=ck, methods_dir=methods_dir)
    assert isinstance(build_method("measurements", methods_dir=methods_dir), RawMeasurements)


def test_unknown_and_unavailable_methods_name_the_available_ones(methods_dir):
    assert configured_methods(methods_dir) == ["measurements", "clairvoyant", "broken", "offset"]
    assert available_methods(methods_dir) == ["measurements", "clairvoyant", "offset"]
    with pytest.raises(ValueError, match=r"unknown method 'nope'.*available: measurements, clairvoyant, offset"):
        build_method("nope", methods_dir=methods_dir)
    with pytest.raises(ValueError, match=r"method 'broken' is not available.*no_such_module"):
        build_method("broken", methods_dir=methods_dir)


def test_evaluate_closed_forms_and_batching():
    data = _data()
    methods = {"offset": Offset(1.5), "measurements": RawMeasurements()}
    r1 = evaluate(methods, data, batch_size=4, progress=False, keep=[5, 0])
    r2 = evaluate(methods, data, batch_size=100, progress=False)
    o = r1["offset"]
    assert o["rmse"] == pytest.approx({"x": 1.5, "y": 1.5, "z": 1.5, "avg": 1.5})
    assert o["rmse_pooled"] == pytest.approx(o["rmse"]) and o["rmse_post_switch"] == pytest.approx(o["rmse"])
    assert o["mode_accuracy"] == 1.0 and int(o["confusion"].sum()) == 6 * 30
    assert r1["measurements"]["mode_accuracy"] is None
    assert r1["measurements"]["rmse"] == pytest.approx(r2["measurements"]["rmse"], rel=1e-12)
    kept = o["kept"][keys.STATE]
    assert kept.shape == (2, 30, 9) and torch.equal(kept[1], Offset(1.5).track(data[5:6])[keys.STATE][0])
    assert o["seconds"] >= 0


def test_evaluate_errors():
    data = _data()
    with pytest.raises(ValueError, match="needs mode"):
        evaluate({"offset": Offset()}, data.exclude(keys.MODE), progress=False)
    with pytest.raises(ValueError, match="ground-truth 'states'"):
        evaluate({"m": RawMeasurements()}, data.exclude(keys.STATES), progress=False)


def test_json_rows_and_tables():
    data = _data()
    res = to_json(evaluate({"measurements": RawMeasurements(), "offset": Offset(3.0),
                            "clairvoyant": Offset(1.5)}, data, progress=False))
    base = {"rmse", "rmse_pooled", "rmse_post_switch", "seconds", "nan_scans", "diverged"}
    assert set(res["offset"]) == base | {"mode_accuracy", "confusion"} and set(res["measurements"]) == base
    assert res["offset"]["nan_scans"] == 0 and res["offset"]["diverged"] == 0
    assert set(res["offset"]["rmse"]) == {"x", "y", "z", "avg"}
    text = format_table(res)
    lines = text.splitlines()
    assert lines[0].split()[:2] == ["method", "x"] and "mode acc." in lines[0] and "/ bound" in lines[0]
    assert len(lines) == 2 + 3 and len({len(line) for line in lines}) == 1  # aligned
    off = next(line for line in lines if line.startswith("offset")).split()
    assert off[1:5] == ["3.000"] * 4 and off[5] == "3.000" and off[-3:] == ["100.0", "%", "2.000"]
    meas = next(line for line in lines if line.startswith("measurements")).split()
    assert meas[-2] == "-"  # no mode accuracy
    md = format_markdown(res).splitlines()
    assert md[0].startswith("| method | x [m]") and md[1].startswith("|:---|---:")
    assert md[3] == "| offset | 3.000 | 3.000 | 3.000 | 3.000 | 3.000 | 100.0 % | 2.000 |"
    no_bound = format_table({k: v for k, v in res.items() if k != "clairvoyant"})
    assert "/ bound" not in no_bound


def test_the_working_directorys_method_configs_come_first(tmp_path, monkeypatch):
    """Issue 21, item 4: ``configs/methods/<name>.yaml`` of the working directory is looked in before the
    packaged registry (docs/configs.md): it replaces a shipped method and adds new ones; an unknown name's
    error lists both places."""
    from immnet.config import packaged_configs

    monkeypatch.chdir(tmp_path)
    mine = tmp_path / "configs" / "methods"
    mine.mkdir(parents=True)
    (mine / "imm-ekf.yaml").write_text("class_path: immnet.filters.IMMEKF\ninit_args: {p_stay: 0.9}\n")
    (mine / "my-imm.yaml").write_text("class_path: immnet.filters.IMMEKF\ninit_args: {p_stay: 0.8}\n")
    assert build_method("imm-ekf").p_stay == pytest.approx(0.9)
    assert build_method("my-imm").p_stay == pytest.approx(0.8)
    shipped = {p.stem for p in (packaged_configs() / "methods").glob("*.yaml")}
    assert shipped | {"my-imm", "measurements"} == set(configured_methods())
    with pytest.raises(ValueError, match="unknown method 'nope'") as err:
        build_method("nope")
    assert str(mine / "nope.yaml") in str(err.value) and str(packaged_configs() / "methods" / "nope.yaml") in str(err.value)


def test_what_a_method_class_declares_build_method_may_set_is_what_its_constructor_takes():
    """``build_method`` sets checkpoint, return_cov, guard and r on a method by its class's ``build_options``, never by
    reading the constructor: each configured class's declaration must name exactly those of its parameters, with
    their defaults (a guard's default decides whether ``--guard`` replaces it), or an option would be dropped."""
    import inspect

    from immnet.config import import_class, load_yaml
    from immnet.filters.methods import build_options, method_config

    classes = {import_class(load_yaml(method_config(name))["class_path"]) for name in configured_methods()
               if name != "measurements"}
    assert len(classes) >= 9
    for cls in classes:
        params = inspect.signature(cls).parameters
        taken = {k: params[k].default for k in ("checkpoint", "return_cov", "guard", "r") if k in params}
        if "checkpoint" not in taken:
            taken.pop("r", None)  # r is set only on a trained network (told_r)
        assert build_options(cls) == taken, cls.__name__
