"""Outputs that cannot be written (issue 60, item 6): a read-only folder, a path under a file or a full disk end
``immnet track``, ``immnet evaluate`` and ``immnet data generate|export`` in one line naming the path and the
system's reason, exit code 2, refused before the work where it can be known then, and nothing left behind (no
partial output, no temporary sibling, no "Bus error" from a memory-mapped write on a full disk)."""

import builtins
import csv
import errno
import io
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from immnet.cli import main
from immnet.data.generate import generate
from immnet.data.spec import DataSpec

NOSPC = os.strerror(errno.ENOSPC)


def _error(capsys, command: str) -> str:
    """The one error line of ``immnet <command>``, with no traceback."""
    err = capsys.readouterr().err
    assert "Traceback" not in err, err[-2000:]
    lines = [s for s in err.splitlines() if s.strip()]
    errors = [s for s in lines if s.startswith(f"immnet {command}: error: ")]
    assert len(errors) == 1, err[-2000:]
    return errors[0][len(f"immnet {command}: error: "):]


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A tracks CSV, an .npz of measurements and truth, and a small data set directory."""
    d = tmp_path_factory.mktemp("inputs")
    data = generate(3, seed=4, spec=DataSpec(T=40, min_segment=10))
    z = data["measurements"].double().numpy()
    with open(d / "in.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["track_id", "t", "x", "y", "z"])
        w.writerows([f"t{i}", k, *(repr(float(v)) for v in z[i, k])] for i in range(3) for k in range(40))
    np.savez(d / "in.npz", measurements=z.astype(np.float32), states=data["states"].numpy(), dt=1.0)
    return d


def _commands(inputs, out: Path) -> dict:
    """Each command writing into the folder ``out``: ``(argv, what it writes)``."""
    return {
        "track-csv": (["track", "--input", str(inputs / "in.csv"), "--output", str(out / "o.csv"), "--method", "imm-ekf"],
                      out / "o.csv"),
        "track-npz": (["track", "--input", str(inputs / "in.npz"), "--output", str(out / "o.npz"), "--weights", "3dlast",
                       "--guard", "none"], out / "o.npz"),
        "evaluate-json": (["evaluate", "--data", str(inputs / "in.npz"), "--split", "all", "--methods", "measurements",
                           "--quiet", "--json", str(out / "r.json")], out / "r.json"),
        "evaluate-markdown": (["evaluate", "--data", str(inputs / "in.npz"), "--split", "all", "--methods",
                               "measurements", "--quiet", "--markdown", str(out / "r.md")], out / "r.md"),
        "evaluate-figures": (["evaluate", "--data", str(inputs / "in.npz"), "--split", "all", "--methods",
                              "measurements", "--quiet", "--figures", str(out / "figs")], out / "figs"),
        "data-generate": (["data", "generate", "--out", str(out / "ds"), "--n", "5", "--seed", "0", "--quiet",
                           "--config", "configs/data/tiny.yaml"], out / "ds"),
        "data-export": (["data", "export", "--data", str(inputs / "in.npz"), "--out", str(out / "x.npz")], out / "x.npz"),
    }


COMMANDS = ["track-csv", "track-npz", "evaluate-json", "evaluate-markdown", "evaluate-figures", "data-generate",
            "data-export"]


@pytest.fixture
def no_work(monkeypatch):
    """The work of each command fails the test if it starts: the output is to be refused before it."""

    def work(*args, **kwargs):
        raise AssertionError("the work started before the output was checked")

    import immnet.tracking.cli  # the names patched where the command reads them (bound when it is imported)

    monkeypatch.setattr(immnet.tracking.cli, "track_rows", work)
    monkeypatch.setattr(immnet.tracking.cli, "track_segments", work)
    monkeypatch.setattr("immnet.tracking.tracker.Tracker.track", work)
    monkeypatch.setattr("immnet.evaluation.runner.evaluate", work)
    monkeypatch.setattr("immnet.data.storage.generate_block", work)
    monkeypatch.setattr("immnet.data.storage.load_dataset", work)


@pytest.fixture
def read_only(monkeypatch):
    """``read_only(folder)``: nothing can be created in ``folder``, as for a user without write permission on it. Not
    root: ``chmod 0o555``. Root, whom permissions do not stop (these tests' container): ``open`` for writing,
    ``os.open`` with ``O_CREAT`` and ``os.mkdir`` of a path in it raise the ``PermissionError`` the system would."""
    chmodded = []
    folders = []

    def denied(path) -> bool:
        return not isinstance(path, int) and Path(os.fspath(path)).absolute().parent in folders

    def refuse(path):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fspath(path))

    real_open, real_os_open, real_mkdir = builtins.open, os.open, os.mkdir

    def fake_open(file, mode="r", *args, **kwargs):
        if any(c in mode for c in "wxa+") and denied(file):
            refuse(file)
        return real_open(file, mode, *args, **kwargs)

    def fake_os_open(path, flags, *args, **kwargs):
        if flags & os.O_CREAT and denied(path):
            refuse(path)
        return real_os_open(path, flags, *args, **kwargs)

    def fake_mkdir(path, *args, **kwargs):
        if denied(path):
            refuse(path)
        return real_mkdir(path, *args, **kwargs)

    def make(folder: Path) -> None:
        if os.geteuid() != 0:
            folder.chmod(0o555)
            chmodded.append(folder)
            return
        if not folders:
            monkeypatch.setattr(builtins, "open", fake_open)
            monkeypatch.setattr(io, "open", fake_open)
            monkeypatch.setattr(os, "open", fake_os_open)
            monkeypatch.setattr(os, "mkdir", fake_mkdir)
        folders.append(folder.absolute())

    yield make
    for folder in chmodded:
        folder.chmod(0o755)


@pytest.mark.parametrize("command", COMMANDS)
def test_a_read_only_output_folder_is_refused_before_the_work(inputs, tmp_path, command, read_only, no_work, capsys,
                                                              monkeypatch):
    """A folder in which nothing can be created: ``track``, ``evaluate`` (after all its scoring) and ``data
    generate`` ended in PermissionError tracebacks; now one line naming the folder, before any work, nothing
    written."""
    monkeypatch.chdir(Path(__file__).resolve().parents[1])  # configs/data/tiny.yaml
    out = tmp_path / "ro"
    out.mkdir()
    argv, _ = _commands(inputs, out)[command]
    read_only(out)
    assert main(argv) == 2
    assert _error(capsys, argv[0]) == f"{out}: {os.strerror(errno.EACCES)}, so {_commands(inputs, out)[command][1].name} " \
                                      f"cannot be written there"
    assert os.listdir(out) == []


@pytest.mark.parametrize("command", [c for c in COMMANDS if not c.startswith("track")])
def test_an_output_under_a_file_is_refused_before_the_work(inputs, tmp_path, command, no_work, capsys, monkeypatch):
    """An output path whose folder is a file (``FILE/sub/out``): a NotADirectoryError traceback after the work;
    now one line naming the file (``immnet track`` already refused an --output whose folder does not exist)."""
    monkeypatch.chdir(Path(__file__).resolve().parents[1])
    (tmp_path / "afile").write_text("not a folder\n")
    argv, _ = _commands(inputs, tmp_path / "afile" / "sub")[command]
    assert main(argv) == 2
    assert _error(capsys, argv[0]) == f"{tmp_path / 'afile'}: {os.strerror(errno.ENOTDIR)}"
    assert sorted(os.listdir(tmp_path)) == ["afile"]


def _set_bytes(n: int, T: int) -> int:
    """The bytes of a generated data set, from docs/data.md's dtypes: states [T, 9], measurements [T, 3] and
    turn_rate [T] float32, mode [T] int64, t [T] float64, r and dt float32, per trajectory."""
    return n * (T * (9 + 3 + 1) * 4 + T * 8 + T * 8 + 4 + 4)


def test_generate_on_a_disk_without_room_is_refused_before_the_work(tmp_path, no_work, monkeypatch, capsys):
    """A full disk: ``immnet data generate`` died with "Bus error" (SIGBUS, exit 135: a memory-mapped page that
    cannot be stored) and left its temporary directory; now the room is checked first: one line with what the set
    needs and what is free, nothing left."""
    import shutil

    free = 123_456
    real = shutil.disk_usage
    monkeypatch.setattr(shutil, "disk_usage", lambda p: real(p)._replace(free=free))
    assert main(["data", "generate", "--out", str(tmp_path / "ds"), "--n", "300", "--seed", "0", "--quiet"]) == 2
    need = _set_bytes(300, DataSpec().T)
    assert _error(capsys, "data") == (f"{tmp_path}: {NOSPC}: the data set (300 trajectories of {DataSpec().T} scans) "
                                      f"needs {need / 1e6:.1f} MB, {free / 1e6:.1f} MB free")
    assert os.listdir(tmp_path) == []


def test_generate_whose_disk_fills_up_meanwhile_ends_in_one_line_and_leaves_nothing(tmp_path, monkeypatch, capsys):
    """The disk filled by another writer after the check: the set's files are allocated before they are written
    through memory maps, so the allocation fails (naming the file) where the writes would have been a SIGBUS; the
    temporary directory is removed."""
    allocated = []

    def fallocate(fd, offset, length):
        allocated.append(length)
        raise OSError(errno.ENOSPC, NOSPC)

    monkeypatch.setattr(os, "posix_fallocate", fallocate)
    assert main(["data", "generate", "--out", str(tmp_path / "ds"), "--n", "300", "--seed", "0", "--quiet"]) == 2
    line = _error(capsys, "data")
    assert line.startswith(f"{tmp_path}/.ds.tmp-") and line.endswith(f"/tensors/states.memmap: {NOSPC}"), line
    assert allocated == [300 * DataSpec().T * 9 * 4]  # the first file, states [n, T, 9] float32
    assert os.listdir(tmp_path) == []


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="names the allocated files by /proc/self/fd")
def test_generate_allocates_every_byte_it_writes(tmp_path, monkeypatch):
    """What is allocated ahead is the whole set (the files' sizes, and the bytes computed from the dtypes), so no
    page written through a memory map is left to find the disk full."""
    allocated = {}
    real = os.posix_fallocate

    def fallocate(fd, offset, length):
        allocated[os.readlink(f"/proc/self/fd/{fd}")] = (offset, length)
        return real(fd, offset, length)

    monkeypatch.setattr(os, "posix_fallocate", fallocate)
    assert main(["data", "generate", "--out", str(tmp_path / "ds"), "--n", "30", "--seed", "0", "--quiet",
                 "--config", str(Path(__file__).resolve().parents[1] / "configs/data/tiny.yaml")]) == 0
    files = {p.name: p.stat().st_size for p in (tmp_path / "ds" / "tensors").glob("*.memmap")}
    got = {Path(k).name: v for k, v in allocated.items()}
    assert got == {name: (0, size) for name, size in files.items()} and len(files) == 7
    T = DataSpec.from_yaml(Path(__file__).resolve().parents[1] / "configs/data/tiny.yaml").T
    assert sum(files.values()) == _set_bytes(30, T)


class _FullDisk:
    """A file opened for writing on a file system that fills up after ``room`` characters: the write that would pass
    them writes what fits and raises ENOSPC, as a write to an open file does (no file name)."""

    real = Path.open

    def __init__(self, f, room: int = 500):
        self.f, self.room = f, room

    @staticmethod
    def open(path, mode="r", *args, **kwargs):
        f = _FullDisk.real(path, mode, *args, **kwargs)
        return _FullDisk(f) if set(mode) & set("wxa") else f

    def write(self, text: str) -> int:
        if len(text) > self.room:
            self.f.write(text[: self.room])
            self.room = 0
            raise OSError(errno.ENOSPC, NOSPC)
        self.room -= len(text)
        return self.f.write(text)

    def writelines(self, lines) -> None:
        for line in lines:
            self.write(line)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return self.f.__exit__(*exc)

    def __getattr__(self, name):
        return getattr(self.f, name)


def test_track_on_a_full_disk_ends_in_one_line_and_leaves_nothing(inputs, tmp_path, monkeypatch, capsys):
    """``immnet track`` onto a disk that fills up while it writes: an OSError traceback; now one line naming the
    output and the reason, no output, no temporary file (CSV: the file's writes; .npz: numpy's savez)."""
    monkeypatch.setattr(Path, "open", _FullDisk.open)
    out = tmp_path / "o.csv"
    assert main(["track", "--input", str(inputs / "in.csv"), "--output", str(out), "--method", "imm-ekf"]) == 2
    assert _error(capsys, "track") == f"{out}: {NOSPC}"

    def savez(file, **arrays):
        Path(file).write_bytes(b"PK\x03\x04 part of an archive")
        raise OSError(errno.ENOSPC, NOSPC)

    monkeypatch.setattr(np, "savez", savez)
    out = tmp_path / "o.npz"
    assert main(["track", "--input", str(inputs / "in.npz"), "--output", str(out), "--weights", "3dlast",
                 "--guard", "none"]) == 2
    assert _error(capsys, "track") == f"{out}: {NOSPC}"
    assert os.listdir(tmp_path) == []


def test_evaluate_on_a_full_disk_ends_in_one_line_and_leaves_no_partial_json(inputs, tmp_path, monkeypatch, capsys):
    """``immnet evaluate --json`` onto a full disk: an OSError traceback and an empty (partial) file; now written
    through a temporary sibling: one line, no file."""
    real = Path.write_text

    def write_text(self, text, *args, **kwargs):
        real(self, text[: len(text) // 2], *args, **kwargs)
        raise OSError(errno.ENOSPC, NOSPC)

    monkeypatch.setattr(Path, "write_text", write_text)
    out = tmp_path / "r.json"
    assert main(["evaluate", "--data", str(inputs / "in.npz"), "--split", "all", "--methods", "measurements", "--quiet",
                 "--json", str(out)]) == 2
    assert _error(capsys, "evaluate") == f"{out}: {NOSPC}"
    assert os.listdir(tmp_path) == []


def test_the_edge_names_the_path_of_any_os_error():
    """``immnet.cli``'s one line for an OSError: ``PATH: reason`` where the system named a path (both for a
    rename), the message otherwise (the project's own FileNotFoundError / FileExistsError messages)."""
    from immnet.cli import _reason

    assert _reason(PermissionError(errno.EACCES, "Permission denied", "/x/y")) == "/x/y: Permission denied"
    assert _reason(OSError(errno.EXDEV, "Invalid cross-device link", "/a", None, "/b")) == \
        "/a -> /b: Invalid cross-device link"
    assert _reason(FileNotFoundError("input not found: in.csv")) == "input not found: in.csv"
