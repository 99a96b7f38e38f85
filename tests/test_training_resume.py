"""Crash-safe training (immnet/training/resume.py, callbacks.LastCheckpoint, cli.run_stages): what
`immnet fit` does with an earlier run's checkpoints, `kill -9` of a fit and of a chained recipe's parent,
then the resumed run, in scratch directories laid out as `bash scripts/main.sh` lays out the repository."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import lightning as L
import pytest
import torch

from immnet.checkpoints import load_checkpoint
from immnet.cli import main
from immnet.config import REPO_ROOT
from immnet.data.spec import DataSpec
from immnet.data.storage import write_dataset
from immnet.training import resume
from tests.tiny_runs import StopAt

TINY = DataSpec(T=20, min_segment=5)  # one TBPTT chunk of 20 scans: one optimizer step per batch
# 46 training trajectories in batches of 8: 6 batches a pass; validation (and last.ckpt) every 3 batches;
# 7 steps cross a pass boundary, and end on a step that is no validation's
# each training batch a fresh view (immnet.data.augment, seeded by the step): a resumed run must see the same views
ARGS = ["--trainer.max_steps", "7", "--trainer.val_check_interval", "3", "--trainer.limit_val_batches", "1",
        "--data.batch_size", "8", "--trainer.logger", "false", "--data.augment", "immnet.data.augment.FlightAugment"]
STAGE1 = str(REPO_ROOT / "recipes/quick-stage1.yaml")
CKPTS = Path("runs/quick/stage1/checkpoints")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    d = tmp_path_factory.mktemp("data")
    write_dataset(d / "train", 48, seed=11, spec=TINY)
    for i, mode in enumerate(("cv", "ca", "ct+", "ct-")):
        write_dataset(d / f"single-{mode}", 8, seed=12 + i, spec=TINY, single_mode=mode)
    return d


def _workdir(root: Path, data: Path) -> Path:
    (root / "runs/quick").mkdir(parents=True)
    (root / "runs/quick/data").symlink_to(data)
    return root


def _fit(*args: str) -> list[str]:
    return [sys.executable, "-m", "immnet.cli", "fit", *args]


def _env(tmp: Path) -> dict:
    tmp.mkdir(exist_ok=True)
    return {**os.environ, "TMPDIR": str(tmp), "WANDB_MODE": "offline", "WANDB_SILENT": "true"}


def _wait_for(path: Path, proc: subprocess.Popen) -> None:
    while not path.exists():
        if proc.poll() is not None:
            pytest.fail(f"the run ended (code {proc.returncode}) before {path} was written")
        time.sleep(0.05)


def _weights(path: Path) -> dict:
    return load_checkpoint(path)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory, data):
    """The tiny stage-1 run, start to end: its final state (last.ckpt) and best checkpoint."""
    work = _workdir(tmp_path_factory.mktemp("whole"), data)
    done = subprocess.run(_fit("--config", STAGE1, *ARGS), cwd=work, env=_env(work / "tmp"), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    return _weights(work / CKPTS / "last.ckpt"), _weights(work / CKPTS / "best.ckpt")


@pytest.mark.slow
def test_kill_9_during_fit_then_ckpt_path_last_ends_as_an_uninterrupted_run(tmp_path, data, uninterrupted):
    """Issue 20, item 5: `kill -9` of `immnet fit` after its first validation, then `--ckpt_path last`:
    the run resumes at the step of its last checkpoint (not at step 0) and ends with the very weights,
    optimizer state and best score of an uninterrupted run of the same seed. The tolerance is zero:
    training draws no random numbers but the batch order, which a resumed run restores (a pass is a
    function of its epoch, the loader's state says where in the pass it stopped), and a CPU run
    repeats its float operations exactly; a resume that replayed batches would differ."""
    work = _workdir(tmp_path, data)
    last = work / CKPTS / "last.ckpt"
    proc = subprocess.Popen(_fit("--config", STAGE1, *ARGS), cwd=work, env=_env(work / "tmp"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _wait_for(last, proc)
    proc.kill()
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    step = _weights(last)["global_step"]
    assert 0 < step < 7
    done = subprocess.run(_fit("--config", STAGE1, *ARGS, "--ckpt_path", "last"), cwd=work, env=_env(work / "tmp"),
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"resuming from {last}" in done.stderr and "Restored all states" in done.stderr
    got, want = _weights(last), uninterrupted[0]
    assert got["global_step"] == want["global_step"] == 7
    assert got["state_dict"].keys() == want["state_dict"].keys()
    assert all(torch.equal(got["state_dict"][k], want["state_dict"][k]) for k in want["state_dict"])
    for a, b in zip(got["optimizer_states"][0]["state"].values(), want["optimizer_states"][0]["state"].values()):
        assert torch.equal(a["exp_avg_sq"], b["exp_avg_sq"])
    best, want_best = _weights(work / CKPTS / "best.ckpt"), uninterrupted[1]
    assert best["global_step"] == want_best["global_step"]
    assert all(torch.equal(best["state_dict"][k], want_best["state_dict"][k]) for k in want_best["state_dict"])
    assert (work / CKPTS / resume.FINISHED).is_file()
    names = {p.name for p in (work / CKPTS).iterdir()}
    assert {"best.ckpt", "finished.json", "last.ckpt"} <= names and not [n for n in names if n.startswith(".")]


def test_ckpt_path_last_without_a_last_checkpoint_is_an_error(tmp_path, data, capsys, monkeypatch):
    """Issue 20, item 5: `--ckpt_path last` with no last checkpoint does not start silently at step 0:
    it names the directory it looked in, exit code 2, and writes nothing."""
    monkeypatch.chdir(_workdir(tmp_path, data))
    assert main(["fit", "--config", STAGE1, *ARGS, "--ckpt_path", "last"]) == 2
    err = capsys.readouterr().err
    assert "no last checkpoint (last.ckpt) in " in err and "runs/quick/stage1/checkpoints, so nothing to resume" in err and "Traceback" not in err
    assert not (tmp_path / CKPTS).exists()


def test_a_fresh_run_never_overwrites_an_earlier_best_checkpoint(tmp_path, data, capsys, monkeypatch):
    """Issue 20, item 5: a fresh run (no --ckpt_path) into a directory holding an earlier run's
    best.ckpt is refused, naming what it holds and the two ways on; the checkpoint is untouched."""
    monkeypatch.chdir(_workdir(tmp_path, data))
    (tmp_path / CKPTS).mkdir(parents=True)
    (tmp_path / CKPTS / "best.ckpt").write_bytes(b"an earlier run's best")
    assert main(["fit", "--config", STAGE1, *ARGS]) == 2
    err = capsys.readouterr().err
    assert "holds best.ckpt of an earlier run" in err and "--ckpt_path last" in err and "--overwrite_checkpoints" in err
    assert (tmp_path / CKPTS / "best.ckpt").read_bytes() == b"an earlier run's best"


def test_overwrite_starts_afresh_without_the_earlier_last_checkpoint(tmp_path):
    """Issue 20, item 5: told to overwrite, a fresh run first removes the earlier run's last.ckpt and
    finished.json (a later `--ckpt_path last` must not resume the other run); a chained stage resumes
    from last.ckpt, and is skipped once finished.json says it has ended."""
    d = tmp_path / "ckpt"
    trainer = L.Trainer(callbacks=[L.pytorch.callbacks.ModelCheckpoint(dirpath=d)], logger=False)
    d.mkdir()
    for name in ("best.ckpt", "last.ckpt"):
        (d / name).write_bytes(b"old")
    with pytest.raises(FileExistsError, match="holds best.ckpt, last.ckpt of an earlier run"):
        resume.plan(trainer, None)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(resume.CHAIN_ENV, "2/2")
        assert resume.plan(trainer, None) == "last"
        (d / resume.FINISHED).write_text('{"best": "B"}')
        done = resume.plan(trainer, None)
        assert isinstance(done, resume.Finished) and done.best == "B"
    assert resume.plan(trainer, None, overwrite=True) is None
    assert sorted(p.name for p in d.iterdir()) == ["best.ckpt"]


def _children(pid: int) -> list[int]:
    return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def _alive(pid: int, grace: float = 10.0) -> bool:
    """Whether ``pid`` still runs ``grace`` seconds from now (a process that closed its pipes is still
    finishing its exit for a moment; an orphan that trains on stays alive)."""
    import time

    end = time.monotonic() + grace
    while True:
        try:
            running = Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
        except FileNotFoundError:
            running = False
        if not running or time.monotonic() > end:
            return running
        time.sleep(0.1)


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG and /proc are Linux's")
def test_kill_9_of_a_chain_stops_its_stage_and_the_rerun_resumes_that_stage(tmp_path, data):
    """Issue 20, item 5: `kill -9` of a chained recipe's process (recipes/quick.yaml) while its second
    stage trains: the stage gets SIGTERM, saves its last checkpoint and stops (no orphan trains on), and
    no temporary file is left; the same command then skips the finished first stage (saying so, its
    checkpoint untouched) and resumes the second from its last checkpoint to its end."""
    work = _workdir(tmp_path, data)
    cmd = _fit("--config", str(REPO_ROOT / "recipes/quick.yaml"), *ARGS)
    s1, s2 = work / "runs/quick/stage1/checkpoints", work / "runs/quick/stage2/checkpoints"
    parent = subprocess.Popen(cmd, cwd=work, env=_env(work / "tmp"), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              text=True)
    _wait_for(s2 / "last.ckpt", parent)
    (child,) = _children(parent.pid)
    parent.kill()
    err = parent.communicate()[1]  # the pipe closes once the stage, which shares it, has ended too
    assert parent.returncode == -signal.SIGKILL and not _alive(child)
    assert "[immnet fit] stopped by SIGTERM at step" in err and f"its last checkpoint is {s2 / 'last.ckpt'}" in err
    assert (s1 / resume.FINISHED).is_file() and not (s2 / resume.FINISHED).exists()
    stopped = _weights(s2 / "last.ckpt")["global_step"]
    stage1 = (s1 / "best.ckpt").read_bytes()
    done = subprocess.run(cmd, cwd=work, env=_env(work / "tmp"), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "stage 1/2 has finished earlier" in done.stderr and f"resuming from {s2 / 'last.ckpt'}" in done.stderr
    assert (s1 / "best.ckpt").read_bytes() == stage1
    assert 0 < stopped < _weights(s2 / "last.ckpt")["global_step"] == 7
    assert (s2 / resume.FINISHED).is_file()
    assert [p.name for p in (work / "tmp").iterdir() if "immnet" in p.name] == []  # (wandb's own stay there)
    assert [p for p in (work / "runs").rglob("*") if p.name.startswith(".") or ".tmp" in p.name] == []


def _boring_fit(tmp_path: Path, *callbacks, **limits) -> L.Trainer:
    from lightning.pytorch.demos.boring_classes import BoringModel

    d = tmp_path / "ckpt"
    trainer = L.Trainer(callbacks=[L.pytorch.callbacks.ModelCheckpoint(dirpath=d), *callbacks], logger=False,
                        enable_progress_bar=False, enable_model_summary=False, limit_val_batches=0, **limits)
    trainer.fit(BoringModel())
    return trainer


def test_a_run_stopped_short_of_its_budget_is_not_marked_finished(tmp_path):
    """Issue 60, item 10: a run that a callback stopped at step 3 of its 10 is not finished: mark_finished
    refuses it, naming the step and the budget, and writes no finished.json (a chain rerun then resumes it
    from last.ckpt instead of skipping it); one that reached max_steps, or max_epochs, or that EarlyStopping
    stopped, is marked."""
    from lightning.pytorch.callbacks import EarlyStopping

    short = _boring_fit(tmp_path / "short", StopAt(3), max_steps=10)
    assert short.global_step == 3
    with pytest.raises(resume.StoppedShort, match=r"training stopped at step 3 of 10 \(a callback stopped the trainer\), "
                                                  r"short of its budget: the run is not finished"):
        resume.mark_finished(short)
    assert not (tmp_path / "short/ckpt" / resume.FINISHED).exists()
    timed = _boring_fit(tmp_path / "timed", max_steps=10, max_time={"days": 1, "hours": 2, "minutes": 3, "seconds": 4})
    resume.mark_finished(timed)  # reached its steps well within its time: finished
    assert (tmp_path / "timed/ckpt" / resume.FINISHED).is_file()
    out_of_time = _boring_fit(tmp_path / "out", max_steps=10, max_time="00:00:00:00")  # stops before its first step
    with pytest.raises(resume.StoppedShort, match=r"training stopped at step 0 of 10 \(its time limit max_time "
                                                  r"\(00:00:00:00\) ran out\)"):
        resume.mark_finished(out_of_time)
    assert not (tmp_path / "out/ckpt" / resume.FINISHED).exists()
    whole = _boring_fit(tmp_path / "whole", max_steps=10)
    resume.mark_finished(whole)
    assert (tmp_path / "whole/ckpt" / resume.FINISHED).is_file()
    epochs = _boring_fit(tmp_path / "epochs", max_epochs=2, limit_train_batches=4)
    assert epochs.global_step == 8
    resume.mark_finished(epochs)
    assert (tmp_path / "epochs/ckpt" / resume.FINISHED).is_file()
    # EarlyStopping on the training loss (BoringModel logs none: stop on a metric that never improves)
    early = EarlyStopping(monitor="flat", patience=1, check_on_train_epoch_end=True)

    class Flat(L.Callback):
        def on_train_epoch_end(self, trainer, pl_module):
            trainer.callback_metrics["flat"] = torch.tensor(1.0)

    stopped = _boring_fit(tmp_path / "early", Flat(), early, max_steps=1000, limit_train_batches=4)
    assert stopped.global_step < 1000 and early.stopped_epoch > 0
    resume.mark_finished(stopped)
    assert (tmp_path / "early/ckpt" / resume.FINISHED).is_file()


@pytest.mark.slow
def test_a_chain_stage_stopped_short_stops_the_chain_and_the_rerun_resumes_it(tmp_path, data):
    """Issue 60, item 10: recipes/quick.yaml whose stage 1 a callback stops at step 4 of its 7 (as max_time
    did on a busy machine) is not reused as finished: the stage says where it stopped and what that means,
    writes no finished.json, and the chain stops there (exit STOPPED_SHORT, no stage 2); the same command
    without that callback resumes stage 1 from its last.ckpt (not from step 0) and runs the chain to its end."""
    work = _workdir(tmp_path, data)
    s1, s2 = work / "runs/quick/stage1/checkpoints", work / "runs/quick/stage2/checkpoints"
    cmd = _fit("--config", str(REPO_ROOT / "recipes/quick.yaml"), *ARGS)
    env = _env(work / "tmp")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), env.get("PYTHONPATH")]))  # tests.tiny_runs
    cut = subprocess.run([*cmd, "--trainer.callbacks+=tests.tiny_runs.StopAt", "--trainer.callbacks.step=4"], cwd=work,
                         env=env, capture_output=True, text=True)
    assert cut.returncode == resume.STOPPED_SHORT, cut.stderr[-3000:]
    assert ("[immnet fit] training stopped at step 4 of 7 (a callback stopped the trainer), short of its budget: the "
            "run is not finished (no finished.json is written), its best checkpoint so far "
            f"({s1 / 'best.ckpt'}) is not the config's model, and the same command resumes it from last.ckpt") in cut.stderr
    assert "stage 1/2 (" in cut.stderr and "stopped short of its budget (above): the chain stops here" in cut.stderr
    assert not (s1 / resume.FINISHED).exists() and _weights(s1 / "last.ckpt")["global_step"] == 4
    assert not s2.exists()
    done = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert f"resuming from {s1 / 'last.ckpt'}" in done.stderr and "has finished earlier" not in done.stderr
    assert _weights(s1 / "last.ckpt")["global_step"] == 7 and (s1 / resume.FINISHED).is_file()
    assert (s2 / resume.FINISHED).is_file()
