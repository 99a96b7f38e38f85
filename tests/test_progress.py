"""Progress of data generation and evaluation outside a terminal (immnet/progress.py): plain lines, at least
one a minute, on a fake clock."""

import io
import re

from immnet.progress import LineProgress, duration, progress

SECONDS_PER_UNIT = 25.0


def test_line_progress_prints_at_least_every_minute_with_count_elapsed_and_time_left():
    """Issue 60, item 10: 10 units of 25 s each: a line at the start, one as soon as a minute has passed
    since the last (after units 3, 6, 9: count, elapsed, time left = elapsed / k * (10 - k), computed here),
    and one at the end with the total time."""
    clock, out = [0.0], io.StringIO()
    bar = progress(range(10), desc="   imm-tuned", unit="batch", file=out, clock=lambda: clock[0])
    assert isinstance(bar, LineProgress)
    for _ in bar:
        clock[0] += SECONDS_PER_UNIT
    lines = out.getvalue().splitlines()
    want = ["[imm-tuned] 0/10 batch"]
    for k in (3, 6, 9):
        elapsed = SECONDS_PER_UNIT * k
        want.append(f"[imm-tuned] {k}/10 batch, elapsed {duration(elapsed)}, left ~{duration(elapsed / k * (10 - k))}")
    want.append(f"[imm-tuned] 10 batch in {duration(SECONDS_PER_UNIT * 10)}")
    assert lines == want
    assert want[1] == "[imm-tuned] 3/10 batch, elapsed 1m15s, left ~2m55s"


def test_line_progress_by_update_and_a_terminal_gets_tqdm():
    """The update/close form (data generation: blocks of trajectories); a terminal gets tqdm's bar, and
    disable prints nothing."""
    clock, out = [0.0], io.StringIO()
    bar = progress(total=3000, desc="3D-LAST -> train", unit="traj", file=out, clock=lambda: clock[0])
    for _ in range(3):
        clock[0] += 70.0
        bar.update(1000)
    bar.close()
    bar.close()
    assert out.getvalue().splitlines() == [
        "[3D-LAST -> train] 0/3000 traj",
        "[3D-LAST -> train] 1000/3000 traj, elapsed 1m10s, left ~2m20s",
        "[3D-LAST -> train] 2000/3000 traj, elapsed 2m20s, left ~1m10s",
        "[3D-LAST -> train] 3000/3000 traj, elapsed 3m30s, left ~0s",
        "[3D-LAST -> train] 3000 traj in 3m30s",
    ]

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    assert type(progress(range(3), file=Terminal())).__name__ == "tqdm"
    quiet = io.StringIO()
    list(progress(range(3), file=quiet, disable=True))
    assert quiet.getvalue() == ""


def test_data_generate_and_evaluate_print_plain_lines_in_a_log(tmp_path, capsys):
    """`immnet data generate` and `immnet evaluate` with stderr not a terminal (a log file, here pytest's
    capture): a start and an end line per data set and per method, no carriage returns."""
    from immnet.cli import main

    assert main(["data", "generate", "--out", str(tmp_path / "d"), "--n", "8", "--seed", "1"]) == 0
    err = capsys.readouterr().err
    assert "\r" not in err
    assert re.search(r"^\[3D-LAST -> d\] 0/8 traj$", err, re.M) and re.search(r"^\[3D-LAST -> d\] 8 traj in \d+s$", err, re.M)
    assert main(["evaluate", "--data", str(tmp_path / "d"), "--split", "all", "--methods", "measurements,imm-tuned"]) == 0
    err = capsys.readouterr().err
    assert "\r" not in err
    for name in ("measurements", "imm-tuned"):
        assert re.search(rf"^\[{name}\] 0/1 batch$", err, re.M) and re.search(rf"^\[{name}\] 1 batch in \d+s$", err, re.M)
