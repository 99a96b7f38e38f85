"""Checkpoints are read as plain data and carry a checksum of their weights (docs/checkpoints.md): a file
that would run code, that is not a checkpoint, or whose weights disagree with its checksum is refused by
name, through the Python API, ``immnet track`` / ``evaluate`` and Lightning's resume (``immnet fit``)."""

import builtins
import hashlib
import json
import os
import re
import shlex
import shutil

import numpy as np
import pytest
import torch

from immnet.checkpoints import CHECKSUM_KEY, CheckpointError, load_checkpoint
from immnet.cli import main
from immnet.config import REPO_ROOT
from immnet.data.generate import generate
from immnet.data.spec import DataSpec
from immnet.tracking.tracker import PRETRAINED, Tracker
from immnet.training import Stage2Module

from tiny_runs import TINY, write_quick_data

FAST = ["--trainer.max_steps", "4", "--trainer.val_check_interval", "2", "--trainer.limit_val_batches", "1",
        "--data.batch_size", "4", "--trainer.logger", "false"]
STAGE1, STAGE2 = (str(REPO_ROOT / f"recipes/quick-stage{i}.yaml") for i in (1, 2))


class _RunsCode:
    """Pickles as the call ``func(*args)``: what a hostile checkpoint holds."""

    def __init__(self, func, *args):
        self.func, self.args = func, args

    def __reduce__(self):
        return self.func, self.args


def _payloads(sentinel):
    """Two ways a pickle runs code on load, each creating ``sentinel``."""
    return {"os.system": _RunsCode(os.system, f"touch {shlex.quote(str(sentinel))}"),
            "builtins.exec": _RunsCode(builtins.exec, f"open({str(sentinel)!r}, 'w').close()")}


def _shipped() -> dict:
    return torch.load(PRETRAINED, map_location="cpu", weights_only=True)


def _hostile(tmp_path, how: str):
    """The shipped checkpoint with a code-running object in its hyper_parameters (a complete, loadable
    checkpoint otherwise): ``(path, sentinel)``."""
    sentinel = tmp_path / f"SENTINEL-{how.replace('.', '-')}"
    ckpt = _shipped()
    ckpt["hyper_parameters"]["note"] = _payloads(sentinel)[how]
    path = tmp_path / f"evil-{how}.ckpt"
    torch.save(ckpt, path)
    assert not sentinel.exists()
    return path, sentinel


def _tampered(src, out) -> tuple:
    """``src``'s checkpoint with one float moved by one ulp, its stored checksum kept."""
    ckpt = load_checkpoint(src)
    name = next(k for k, v in ckpt["state_dict"].items() if k.endswith(".weight") and v.is_floating_point())
    w = ckpt["state_dict"][name].view(-1)
    w[0] = torch.nextafter(w[0], torch.tensor(float("inf"), dtype=w.dtype))
    torch.save(ckpt, out)
    return out, name


def _sha256_by_hand(state_dict: dict) -> str:
    """docs/checkpoints.md's checksum, written out with numpy: per entry in sorted name order the JSON line
    ``[name, dtype, shape]`` and the little-endian bytes in C order."""
    h = hashlib.sha256()
    for name in sorted(state_dict):
        t = state_dict[name]
        a = np.ascontiguousarray(t.numpy())
        h.update(json.dumps([name, str(t.dtype), list(a.shape)]).encode() + b"\n")
        h.update(a.astype(a.dtype.newbyteorder("<"), copy=False).tobytes())
    return h.hexdigest()


def _one_error_line(err: str, command: str) -> str:
    lines = [s for s in err.splitlines() if s.strip() and "Warning" not in s and not s.startswith(" ")]
    assert "Traceback" not in err, err[-2000:]
    errors = [s for s in lines if s.startswith(f"immnet {command}: error: ")]
    assert len(errors) == 1, err[-2000:]
    return errors[0]


@pytest.mark.parametrize("how", ["os.system", "builtins.exec"])
def test_a_checkpoint_that_would_run_code_is_refused_by_the_tracker(tmp_path, how):
    """Issue 20, item 1: a pickled object whose ``__reduce__`` runs code is refused by
    ``Tracker.from_checkpoint`` and Stage2Module's checkpoints, and nothing runs (the sentinel file
    it would create does not exist)."""
    path, sentinel = _hostile(tmp_path, how)
    with pytest.raises(CheckpointError, match=rf"{path} is refused: it holds the global .*nothing in it was run"):
        Tracker.from_checkpoint(path)
    for arg in ("init_checkpoint", "stage1_checkpoint"):
        with pytest.raises(CheckpointError, match=f"{path} is refused"):
            Stage2Module(net=_shipped()["hyper_parameters"]["net"], **{arg: str(path)})
    assert not sentinel.exists()


def _refused_by_every_reader(path, why: str, tmp_path, capsys) -> None:
    """``path`` refused with ``why`` by the tracker, Stage2Module's ``init_checkpoint``, the exporter and ``immnet
    track`` (one error line, exit code 2), and nothing written."""
    from immnet.training.export import export_weights

    with pytest.raises(CheckpointError, match=why):
        Tracker.from_checkpoint(path)
    with pytest.raises(CheckpointError, match=why):
        Stage2Module(net=_shipped()["hyper_parameters"]["net"], init_checkpoint=str(path))
    with pytest.raises(CheckpointError, match=why):
        export_weights(path, tmp_path / "out.ckpt")
    np.savez(tmp_path / "in.npz", measurements=np.zeros((1, 5, 3), np.float32), dt=1.0)
    assert main(["track", "--input", str(tmp_path / "in.npz"), "--output", str(tmp_path / "o.npz"),
                 "--checkpoint", str(path)]) == 2
    assert why in _one_error_line(capsys.readouterr().err, "track")
    assert not (tmp_path / "out.ckpt").exists() and not (tmp_path / "o.npz").exists()


def _naming(tmp_path, monkeypatch, where: str):
    """The shipped checkpoint (a plain-data pickle, its checksum intact) whose config names, at ``where``, a class
    of a module that creates a sentinel file when imported: ``(path, sentinel, module)``."""
    sentinel, module = tmp_path / f"SENTINEL-{where}", f"lab_stages{where.strip('_')}"
    (tmp_path / f"{module}.py").write_text(f"open({str(sentinel)!r}, 'w').close()\nclass Gain:\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    ckpt = _shipped()
    net = ckpt["hyper_parameters"]["net"]
    if where == "gain":
        net["gain"] = {"class_path": f"{module}.Gain", "init_args": {}}
    elif where == "model_set":
        net["model_set"] = [*net["model_set"][:-1], {"class_path": f"{module}.Gain", "init_args": {}}]
    else:  # LightningCLI's form of the module itself
        ckpt["hyper_parameters"]["_class_path"] = f"{module}.Gain"
    path = tmp_path / f"foreign-{where}.ckpt"
    torch.save(ckpt, path)
    return path, sentinel, module


@pytest.mark.parametrize("where", ["gain", "model_set", "_class_path"])
def test_a_checkpoint_naming_a_class_outside_immnet_is_refused_before_anything_is_imported(tmp_path, monkeypatch,
                                                                                          capsys, where):
    """A checkpoint is rebuilt from the classes its config names, and naming one imports its module: a file naming
    a class outside the allowed packages (``ALLOWED_PACKAGES``: immnet) is refused by every reader (the tracker,
    Stage2Module's checkpoints, the exporter, ``immnet fit --ckpt_path``'s check, ``immnet track``), and the module
    is never imported (its sentinel file is not created). Added to the allowed packages, the same name loads as far
    as the import (the class is then refused as no gain)."""
    import sys

    from immnet.checkpoints import ALLOWED_PACKAGES
    from immnet.training.checkpoint_io import check_checkpoints

    path, sentinel, module = _naming(tmp_path, monkeypatch, where)
    why = f"{path} is refused: its config names the class '{module}.Gain', outside the packages"
    _refused_by_every_reader(path, why, tmp_path, capsys)
    with pytest.raises(CheckpointError, match=why):
        check_checkpoints({"subcommand": "fit", "fit": {"ckpt_path": str(path), "model": {}}})
    assert not sentinel.exists() and module not in sys.modules
    if where == "gain":  # one's own package, allowed: imported, then refused as no immnet gain, never built
        monkeypatch.setattr("immnet.checkpoints.ALLOWED_PACKAGES", (*ALLOWED_PACKAGES, module))
        with pytest.raises(ValueError, match=f"class_path '{module}.Gain' is not a immnet.stages.gain.Gain"):
            Tracker.from_checkpoint(path)
        assert sentinel.exists()
        sys.modules.pop(module)


def test_a_component_that_is_no_stage_is_never_called(tmp_path):
    """A component's ``class_path`` must name a stage class (a motion model's, a motion model): a function of the
    package that would build something else from the config (``immnet.config.instantiate``) is refused by name,
    not called."""
    from immnet.motion import ModelSet
    from immnet.stages import IMMNet

    net = _shipped()["hyper_parameters"]["net"]
    called = {"class_path": "immnet.config.instantiate", "init_args": {"entry": {"class_path": "builtins.print"}}}
    with pytest.raises(ValueError, match="'immnet.config.instantiate' is not a immnet.stages.classify.ModeUpdate"):
        IMMNet(**{**net, "classifier": called})
    with pytest.raises(ValueError, match="'immnet.config.instantiate' is not a immnet.stages.base.Stage"):
        IMMNet(**{**net, "correction": called})
    with pytest.raises(ValueError, match="'immnet.config.instantiate' is not a immnet.motion.base.MotionModel"):
        ModelSet.from_config([called])


def test_the_cli_refuses_every_bad_checkpoint_in_one_line(tmp_path, capsys):
    """Issue 20, item 1: ``immnet track`` and ``immnet evaluate`` refuse a checkpoint that would run code
    (nothing runs), an empty, truncated or non-checkpoint file, and a pickle of something else than a
    checkpoint, each with one line naming the file and the reason, exit code 2, no traceback, no output."""
    z = generate(2, seed=5, spec=DataSpec(T=30, min_segment=10))
    np.savez(tmp_path / "in.npz", measurements=z["measurements"].numpy(), states=z["states"].numpy(), dt=1.0)
    hostile = [_hostile(tmp_path, how) for how in ("os.system", "builtins.exec")]
    raw = PRETRAINED.read_bytes()
    bad = {tmp_path / "empty.ckpt": (b"", "not a readable checkpoint: the file is empty or cut short"),
           tmp_path / "cut.ckpt": (raw[: len(raw) // 2], "not a readable checkpoint: PytorchStreamReader failed"),
           tmp_path / "text.ckpt": (b"track_id,t,x,y,z\n", "not a readable checkpoint"),
           tmp_path / "list.ckpt": (None, "is not a checkpoint: it holds a list, not a dict")}
    for path, (content, _) in bad.items():
        torch.save([1, 2], path) if content is None else path.write_bytes(content)
    cases = [(p, "is refused: it holds the global") for p, _ in hostile] + [(p, why) for p, (_, why) in bad.items()]
    for path, why in cases:
        out = tmp_path / "out.npz"
        for argv in (["track", "--input", str(tmp_path / "in.npz"), "--output", str(out), "--checkpoint", str(path)],
                     ["evaluate", "--data", str(tmp_path / "in.npz"), "--split", "all", "--methods", "measurements,immnet",
                      "--checkpoint", f"immnet={path}", "--json", str(out), "--quiet"]):
            assert main(argv) == 2, argv
            line = _one_error_line(capsys.readouterr().err, argv[0])
            assert f"error: {path}" in line and why in line, line
            assert not out.exists()
    assert not any(s.exists() for _, s in hostile)


def test_weights_that_disagree_with_their_checksum_are_refused_by_name(tmp_path, capsys):
    """Issue 20, item 1: one float of the shipped weights moved by one ulp, the stored checksum kept:
    ``Tracker``, ``Stage2Module(init_checkpoint=...)``, the exporter, ``immnet track`` and the Lightning
    module's own ``on_load_checkpoint`` (whatever reader Lightning was given) refuse it by name."""
    path, name = _tampered(PRETRAINED, tmp_path / "tampered.ckpt")
    why = f"{path}: its weights do not match the checksum stored in it"
    _refused_by_every_reader(path, why, tmp_path, capsys)
    module = Stage2Module(net=_shipped()["hyper_parameters"]["net"])
    with pytest.raises(CheckpointError, match="the checkpoint: its weights do not match"):
        module.on_load_checkpoint(torch.load(path, weights_only=True))
    # the checksum sees that one ulp: the tampered weights hash (by hand) to something else than stored
    tampered = torch.load(path, weights_only=True)
    assert _sha256_by_hand(tampered["state_dict"]) != tampered[CHECKSUM_KEY]


def test_the_shipped_weights_carry_their_checksum_and_load_as_plain_data(tmp_path):
    """Issue 20, item 1: the shipped file holds nothing outside torch's weights-only set, carries the SHA-256
    of its weights (recomputed here by hand from docs/checkpoints.md's definition, and recorded in
    provenance.json), and loads; a copy without a checksum (a file written before checkpoints carried one)
    is still accepted, with the same weights."""
    assert torch.serialization.get_unsafe_globals_in_checkpoint(PRETRAINED) == []
    ckpt = load_checkpoint(PRETRAINED)
    stored = ckpt[CHECKSUM_KEY]
    assert stored == _sha256_by_hand(ckpt["state_dict"])
    assert stored == json.loads(PRETRAINED.with_name("provenance.json").read_text())["weights_sha256"]
    net = Tracker.pretrained("3dlast").net
    del ckpt[CHECKSUM_KEY]
    torch.save(ckpt, tmp_path / "old.ckpt")
    old = Tracker.from_checkpoint(tmp_path / "old.ckpt").net
    for (k, a), (k2, b) in zip(net.state_dict().items(), old.state_dict().items()):
        assert k == k2 and torch.equal(a, b), k


def test_fit_refuses_a_checkpoint_before_building_anything(tmp_path, capsys):
    """Issue 20, item 1: ``immnet fit --ckpt_path`` / ``validate --ckpt_path`` / ``--model.init_args.
    stage1_checkpoint`` (and ``init_checkpoint``, ``init_parameters``) naming a file that would run code: one line
    naming it, exit code 2, nothing runs."""
    path, sentinel = _hostile(tmp_path, "os.system")
    for argv in (["fit", "--config", STAGE1, *FAST, "--ckpt_path", str(path)],
                 ["validate", "--config", STAGE1, "--ckpt_path", str(path)],
                 ["fit", "--config", STAGE2, *FAST, "--model.init_args.stage1_checkpoint", str(path)],
                 ["fit", "--config", STAGE2, *FAST, "--model.init_args.init_checkpoint", str(path)],
                 ["fit", "--config", STAGE2, *FAST, "--model.init_args.init_parameters", str(path)]):
        assert main(argv) == 2, argv
        line = _one_error_line(capsys.readouterr().err, argv[0])
        assert f"error: {path} is refused" in line, line
    assert not sentinel.exists()


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny real stage-1 run (``immnet fit``, recipes/quick-stage1.yaml): ``(workdir, best.ckpt)``."""
    root = write_quick_data(tmp_path_factory.mktemp("fit"), TINY)
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(root)
        assert main(["fit", "--config", STAGE1, *FAST]) == 0
    best = root / "runs/quick/stage1/checkpoints/best.ckpt"
    assert best.is_file()
    return root, best


def _fresh_run_dir(tmp_path, trained):
    """An empty run directory with the trained run's data (so that ``--ckpt_path last`` finds only ours)."""
    (tmp_path / "runs/quick").mkdir(parents=True)
    (tmp_path / "runs/quick/data").symlink_to(trained[0] / "runs/quick/data")
    ckpts = tmp_path / "runs/quick/stage1/checkpoints"
    ckpts.mkdir(parents=True)
    return ckpts


@pytest.mark.slow
def test_a_trained_checkpoint_carries_its_checksum_and_resumes_through_the_safe_reader(trained, tmp_path, monkeypatch):
    """Issue 20, item 1: a checkpoint written by ``immnet fit`` holds nothing beyond torch's weights-only set,
    carries the SHA-256 of its weights (recomputed by hand), exports with the same weights and checksum, and
    ``immnet fit --ckpt_path`` resumes from it through ``SafeCheckpointIO``."""
    from immnet.training.checkpoint_io import SafeCheckpointIO
    from immnet.training.cli import _run
    from immnet.training.export import export_weights

    _, best = trained
    assert torch.serialization.get_unsafe_globals_in_checkpoint(best) == []
    ckpt = load_checkpoint(best)
    assert ckpt[CHECKSUM_KEY] == _sha256_by_hand(ckpt["state_dict"])
    assert {"optimizer_states", "lr_schedulers", "callbacks", "loops", "hyper_parameters"} <= ckpt.keys()
    slim = load_checkpoint(export_weights(best, tmp_path / "slim.ckpt"))
    assert slim[CHECKSUM_KEY] == ckpt[CHECKSUM_KEY] == _sha256_by_hand(slim["state_dict"])
    assert Tracker.from_checkpoint(tmp_path / "slim.ckpt").net.n_experts == 4

    _fresh_run_dir(tmp_path, trained)
    monkeypatch.chdir(tmp_path)
    reads = []
    original = SafeCheckpointIO.load_checkpoint

    def recording(self, path, *args, **kwargs):
        reads.append(str(path))
        return original(self, path, *args, **kwargs)

    monkeypatch.setattr(SafeCheckpointIO, "load_checkpoint", recording)
    cli = _run(["fit", "--config", STAGE1, *FAST, "--trainer.max_steps", "6", "--ckpt_path", str(best)])
    assert isinstance(cli.trainer.strategy.checkpoint_io, SafeCheckpointIO)
    assert reads == [str(best)]
    assert cli.trainer.global_step == 6  # resumed at step 4, two more steps


@pytest.mark.slow
@pytest.mark.parametrize("fault", ["tampered", "os.system"])
def test_resuming_from_a_bad_last_checkpoint_is_refused_by_name(trained, tmp_path, monkeypatch, capsys, fault):
    """Issue 20, item 1: ``immnet fit --ckpt_path last`` (Lightning's own resume, which finds last.ckpt
    itself) refuses a last.ckpt whose weights were altered or that would run code, in one line naming it;
    nothing runs and no training happens."""
    ckpts = _fresh_run_dir(tmp_path, trained)
    last = ckpts / "last.ckpt"
    if fault == "tampered":
        _tampered(trained[1], last)
        why, sentinel = f"{last}: its weights do not match the checksum", None
    else:
        path, sentinel = _hostile(tmp_path, fault)
        shutil.move(path, last)
        why = f"{last} is refused: it holds the global"
    monkeypatch.chdir(tmp_path)
    assert main(["fit", "--config", STAGE1, *FAST, "--ckpt_path", "last"]) == 2
    assert why in _one_error_line(capsys.readouterr().err, "fit")
    assert sorted(p.name for p in ckpts.iterdir()) == ["last.ckpt"]  # no new checkpoint: nothing trained
    assert sentinel is None or not sentinel.exists()


def test_export_sets_what_a_network_reports_and_nothing_it_learned(tmp_path):
    """``export_weights(..., settings)``: an output setting (the covariance consistency, docs/immnet.md) goes into the
    exported network's arguments with the weights and their checksum unchanged, so its estimates are the source's;
    a setting that would change what it estimates is refused by name."""
    from immnet import keys
    from immnet.checkpoints import shipped
    from immnet.training.export import export_weights

    src = load_checkpoint(shipped("real"))
    out = load_checkpoint(export_weights(shipped("real"), tmp_path / "c.ckpt", {"cov_consistency": 0.1}))
    assert out[CHECKSUM_KEY] == src[CHECKSUM_KEY]
    assert out["hyper_parameters"]["net"]["cov_consistency"] == 0.1
    assert src["hyper_parameters"]["net"].get("cov_consistency") is None  # the source reports its covariance as it is
    z = generate(4, seed=5, spec=DataSpec(T=30, min_segment=8))[keys.MEASUREMENTS]
    before, after = Tracker.from_checkpoint(shipped("real")), Tracker.from_checkpoint(tmp_path / "c.ckpt")
    assert after.net.fuse.consistency == 0.1 and before.net.fuse.consistency is None
    a, b = before.track(z, return_cov=True), after.track(z, return_cov=True)
    assert torch.equal(a[keys.STATE], b[keys.STATE])
    assert torch.isfinite(a[keys.STATE_COV]).all() and not torch.allclose(a[keys.STATE_COV][:, 10:], b[keys.STATE_COV][:, 10:])
    with pytest.raises(ValueError, match="export sets only cov_consistency, not p_stay"):
        export_weights(shipped("real"), tmp_path / "d.ckpt", {"p_stay": 0.9})
    assert not (tmp_path / "d.ckpt").exists()


def _resaved(ckpt: dict, path):
    """``ckpt`` saved as the project saves a checkpoint: its checksum recomputed (``add_checksum``), so that only
    what it holds can refuse it."""
    from immnet.checkpoints import add_checksum

    torch.save(add_checksum(ckpt), path)
    assert load_checkpoint(path)[CHECKSUM_KEY] == _sha256_by_hand(ckpt["state_dict"])  # the checksum is valid
    return path


def _refused_by_track_and_evaluate(path, why: str, tmp_path, capsys) -> None:
    """``immnet track`` (CSV and .npz) and ``immnet evaluate`` refuse ``path``: one line containing ``why``, exit 2,
    no output written."""
    z = generate(2, seed=5, spec=DataSpec(T=30, min_segment=10))
    np.savez(tmp_path / "in.npz", measurements=z["measurements"].numpy(), states=z["states"].numpy(), dt=1.0)
    (tmp_path / "in.csv").write_text("track_id,t,x,y,z\n" + "".join(
        f"a,{k},{x:.3f},{y:.3f},{h:.3f}\n" for k, (x, y, h) in enumerate(z["measurements"][0].tolist())))
    for argv, out in (
            (["track", "--input", str(tmp_path / "in.csv"), "--output", str(tmp_path / "o.csv"), "--checkpoint", str(path)],
             tmp_path / "o.csv"),
            (["track", "--input", str(tmp_path / "in.npz"), "--output", str(tmp_path / "o.npz"), "--checkpoint", str(path)],
             tmp_path / "o.npz"),
            (["evaluate", "--data", str(tmp_path / "in.npz"), "--split", "all", "--methods", "measurements,immnet",
              "--checkpoint", f"immnet={path}", "--json", str(tmp_path / "o.json"), "--quiet"], tmp_path / "o.json")):
        assert main(argv) == 2, argv
        line = _one_error_line(capsys.readouterr().err, argv[0])
        assert why in line, line
        assert not out.exists()


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_weights_that_are_not_finite_are_refused_by_file_and_weight(tmp_path, capsys, value):
    """Issue 60, item 4: weights holding a NaN or an infinity (a run that diverged), saved with a valid checksum,
    tracked to mostly empty output with exit code 0; now the tracker, the bank's members, Stage2Module's
    ``init_checkpoint``, ``immnet track`` and ``immnet evaluate`` refuse the file, naming it and its first
    non-finite weight in the file's order (two are spoilt here: the later one is not named)."""
    from immnet.tracking import NetworkBank

    ckpt = load_checkpoint(PRETRAINED)
    names = [k for k, v in ckpt["state_dict"].items() if v.is_floating_point() and v.numel() > 3]
    first, later = names[2], names[-1]
    ckpt["state_dict"][first].view(-1)[[0, 3]] = value
    ckpt["state_dict"][later].view(-1)[0] = value
    path = _resaved(ckpt, tmp_path / "diverged.ckpt")
    numel = ckpt["state_dict"][first].numel()
    why = f"{path}: its weight {first} holds 2 non-finite value(s) (NaN or inf) of {numel}"
    with pytest.raises(CheckpointError, match=re.escape(why)):
        Tracker.from_checkpoint(path)
    with pytest.raises(CheckpointError, match=re.escape(why)):
        NetworkBank.from_names(["general", str(path)])
    with pytest.raises(CheckpointError, match=re.escape(why)):
        Stage2Module(net=_shipped()["hyper_parameters"]["net"], init_checkpoint=str(path))
    _refused_by_track_and_evaluate(path, why, tmp_path, capsys)


@pytest.mark.parametrize("change", ["wider", "deeper", "foreign weights"])
def test_weights_of_another_architecture_are_refused_by_file_and_weight(tmp_path, capsys, change):
    """Issue 60, item 7: a checkpoint whose config builds another network than its weights fit (a wider or deeper
    classifier in its config, or another network's weights under it; checksum valid) ended ``immnet track`` in
    load_state_dict's RuntimeError traceback; now one line naming the file and the first weight that differs."""
    from immnet.checkpoints import shipped

    ckpt = load_checkpoint(PRETRAINED)
    args = ckpt["hyper_parameters"]["net"]["classifier"].setdefault("init_args", {})
    if change == "wider":
        args["d_model"] = 64
        why = "(net.classify."  # a weight of the classifier, in both shapes
    elif change == "deeper":
        args["layers"] = 3
        why = "(the file has no weight net.classify."
    else:
        ckpt["state_dict"] = load_checkpoint(shipped("real"))["state_dict"]
        why = "another architecture than the network its config builds ("
    path = _resaved(ckpt, tmp_path / "other.ckpt")
    with pytest.raises(CheckpointError, match=re.escape(why)) as err:
        Tracker.from_checkpoint(path)
    message = str(err.value)
    assert message.startswith(f"{path}: its weights are of another architecture than the network its config builds (")
    if change == "wider":  # the shapes named: the file's, and those of the network its changed config builds
        from immnet.stages import IMMNet
        from immnet.stages.network import net_arguments

        name = re.search(r"\(net\.(\S+) is ", message).group(1)
        built = IMMNet(**net_arguments(ckpt["hyper_parameters"]["net"])).state_dict()[name]
        file = ckpt["state_dict"]["net." + name]
        assert list(file.shape) != list(built.shape) and 64 in built.shape and 32 in file.shape
        assert f"is {list(file.shape)} in the file, {list(built.shape)} in the network)" in message
    _refused_by_track_and_evaluate(path, why, tmp_path, capsys)


def test_a_network_configuration_with_an_argument_immnet_does_not_take_is_refused_in_one_line(tmp_path, capsys):
    """A checkpoint whose network configuration holds an argument ``IMMNet`` does not take (another version's, e.g.
    the retired ``per_axis: true``, today ``modes: axis``) is refused by ``immnet track`` in one line naming the file
    and the argument, with nothing written; ``NET_ARGUMENTS`` is exactly IMMNet's arguments."""
    import inspect

    from immnet.stages import IMMNet
    from immnet.stages.network import NET_ARGUMENTS

    assert set(NET_ARGUMENTS) == set(inspect.signature(IMMNet).parameters)
    ckpt = _shipped()
    ckpt["hyper_parameters"]["net"].pop("modes", None)
    ckpt["hyper_parameters"]["net"]["per_axis"] = True
    path = tmp_path / "old.ckpt"
    torch.save(ckpt, path)
    z = generate(2, seed=5, spec=DataSpec(T=30, min_segment=10))
    np.savez(tmp_path / "in.npz", measurements=z["measurements"].numpy(), dt=1.0)
    assert main(["track", "--input", str(tmp_path / "in.npz"), "--output", str(tmp_path / "o.npz"),
                 "--checkpoint", str(path)]) == 2
    line = _one_error_line(capsys.readouterr().err, "track")
    assert f"{path}: the network's configuration holds 'per_axis', which IMMNet does not take" in line
    assert not (tmp_path / "o.npz").exists()
