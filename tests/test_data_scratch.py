"""Temporary siblings of data outputs (immnet/data/scratch.py): ``immnet data generate`` killed mid-way
(SIGTERM, ``kill -9``), then run again, leaves exactly what an uninterrupted run leaves."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from immnet.config import REPO_ROOT
from immnet.data.scratch import remove_stale
from immnet.data.spec import DataSpec
from immnet.data.storage import export_npz, write_dataset

TINY = REPO_ROOT / "configs/data/tiny.yaml"
N = 20000  # a few seconds of generation at T = 50: long enough to be killed mid-way


def _hidden(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir() if p.name.startswith("."))


def _files(d: Path) -> dict[str, bytes]:
    return {str(p.relative_to(d)): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()}


def _dead_pid() -> int:
    """The id of a process that has exited (and been reaped)."""
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _generate(out: Path, seed: int) -> list[str]:
    return [sys.executable, "-m", "immnet.cli", "data", "generate", "--out", str(out), "--n", str(N),
            "--seed", str(seed), "--config", str(TINY), "--quiet"]


def _start_and_wait_for_tmp(cmd, parent: Path, name: str) -> subprocess.Popen:
    """Start ``cmd`` and return once its temporary sibling ``.NAME.tmp-*`` holds allocated tensors."""
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    while not any(parent.glob(f".{name}.tmp-*/tensors/*.memmap")):
        if proc.poll() is not None:
            pytest.fail(f"the run ended (code {proc.returncode}) before it could be killed: {proc.stderr.read()[-2000:]}")
        time.sleep(0.02)
    return proc


def test_kill_9_during_generate_then_next_run_cleans_and_matches(tmp_path):
    """Issue 20, item 5: `kill -9` during `immnet data generate` leaves a hidden `.NAME.tmp-PID-*`
    directory nothing can remove at the time; the next run writing NAME removes it (its PID is dead)
    and writes the very bytes of an uninterrupted run, leaving nothing hidden behind."""
    out = tmp_path / "ds"
    proc = _start_and_wait_for_tmp(_generate(out, seed=5), tmp_path, "ds")
    proc.kill()
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists() and len(_hidden(tmp_path)) == 1  # the killed run's partial directory
    done = subprocess.run(_generate(out, seed=5), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert _hidden(tmp_path) == []
    ref = write_dataset(tmp_path / "ref", N, seed=5, spec=DataSpec.from_yaml(TINY))
    got, want = _files(out), _files(ref)
    assert sorted(got) == sorted(want) and all(got[k] == want[k] for k in want)


def test_sigterm_during_generate_removes_its_own_tmp(tmp_path):
    """Issue 20, item 5: SIGTERM during `immnet data generate` becomes an exception inside the writer,
    which removes its temporary directory; the command says so and exits with 128 + 15."""
    out = tmp_path / "ds"
    proc = _start_and_wait_for_tmp(_generate(out, seed=6), tmp_path, "ds")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate()
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert "terminated" in err.decode()
    assert list(tmp_path.iterdir()) == []


def test_a_live_writers_tmp_is_never_removed(tmp_path):
    """Issue 20, item 5: the next writer of NAME removes `.NAME.tmp-PID-*` only when PID is no running
    process; a concurrent writer's sibling (here this test's own PID), and other names' siblings, stay."""
    dead, live = _dead_pid(), os.getpid()
    for name in (f".ds.tmp-{dead}-00c0ffee", f".ds.tmp-{live}-0000beef", f".other.tmp-{dead}-0000cafe"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "x").write_bytes(b"partial")
    write_dataset(tmp_path / "ds", 10, seed=0, spec=DataSpec(T=20, min_segment=5))
    assert _hidden(tmp_path) == [f".ds.tmp-{live}-0000beef", f".other.tmp-{dead}-0000cafe"]
    assert remove_stale(tmp_path / "other") == [tmp_path / f".other.tmp-{dead}-0000cafe"]


def test_export_removes_a_killed_exports_tmp_file(tmp_path):
    """Issue 20, item 5: a stale temporary `.npz` of a killed `immnet data export` is removed by the
    next export to the same file."""
    ds = write_dataset(tmp_path / "ds", 10, seed=0, spec=DataSpec(T=20, min_segment=5))
    stale = tmp_path / f".x.npz.tmp-{_dead_pid()}-0badf00d.npz"
    stale.write_bytes(b"PK partial")
    export_npz(ds, tmp_path / "x.npz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds", "x.npz"]
