"""What every benchmark shares: a description of the machine and rewriting one section of BENCHMARKS.md; for the
benchmarks whose rows take turns, their arguments, rates, table and section."""

from __future__ import annotations

import argparse
import os
import platform
import re
import statistics
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "BENCHMARKS.md"


def machine() -> str:
    cpu = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    load = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    return f"{os.cpu_count()} CPUs ({cpu}), torch {torch.__version__}, {torch.get_num_threads()} threads, load average {load}"


def write_section(title: str, text: str, path: Path = BENCHMARKS) -> None:
    """Replace (or append) the measured text of the section ``## title`` of ``path``: from its heading to the next
    ``## `` or ``### `` heading. Every other section is kept, and so are the section's own ``### `` notes, written
    by hand under its measured text (a rerun replaces the numbers, not what was written about them)."""
    old = path.read_text() if path.exists() else "# Benchmarks\n"
    section = f"## {title}\n\n" + text.strip() + "\n"
    pattern = re.compile(rf"^## {re.escape(title)}\n.*?(?=^##{{1,2}} |\Z)", re.S | re.M)
    new = pattern.sub(lambda _: section + "\n", old) if pattern.search(old) else old.rstrip() + "\n\n" + section
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(new.rstrip() + "\n")
    tmp.replace(path)


def rows_arguments(doc: str, argv=None) -> argparse.Namespace:
    """The arguments of a benchmark whose rows take turns (``bench_modes``, ``bench_correction``): ``--steps``,
    ``--batches``, ``--rounds`` and ``--out``, with ``doc``'s first line as the description."""
    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--steps", type=int, default=40, help="scans timed per run")
    p.add_argument("--batches", type=lambda v: tuple(int(b) for b in v.split(",")), default=(1, 64, 1024))
    p.add_argument("--rounds", type=int, default=3, help="rounds the rows take turns over (each row its median)")
    p.add_argument("--out", type=Path, default=None, help="BENCHMARKS.md to rewrite (default: the repository's)")
    return p.parse_args(argv)


def rates_in_turns(nets, a: argparse.Namespace, rate) -> dict:
    """``{(row, batch): median rate}``: ``rate(net, batch)`` of every network at every batch, the rows taking turns
    over ``a.rounds`` rounds (a shared machine's load falls on every row alike), each its median round."""
    rates = {(i, B): [] for i in range(len(nets)) for B in a.batches}
    for r in range(a.rounds):
        for i, net in enumerate(nets):
            for B in a.batches:
                rates[i, B].append(rate(net, B))
        print(f"round {r + 1} of {a.rounds} done", file=sys.stderr, flush=True)
    return {key: statistics.median(values) for key, values in rates.items()}


def rates_table(a: argparse.Namespace, head: list[str], rows: list[list[str]], rates: dict) -> list[str]:
    """A Markdown table: the ``head`` columns, then one column per batch of ``a.batches``; row ``i`` its leading cells
    ``rows[i]`` then its rates ``rates[i, batch]`` (track-steps/s), each row printed as it is made."""
    lines = ["| " + " | ".join([*head, *(f"batch {b}" for b in a.batches)]) + " |",
             "|" + "---|" * (len(head) + len(a.batches))]
    for i, lead in enumerate(rows):
        lines.append("| " + " | ".join([*lead, *(f"{rates[i, B]:,.0f}" for B in a.batches)]) + " |")
        print(lines[-1], flush=True)
    return lines


def write_rates(script: str, title: str, what: str, a: argparse.Namespace, lines: list[str]) -> None:
    """Rewrite the section ``## title`` with the command that measured it (``benchmarks/script``, its non-default
    ``--steps`` and ``--rounds``), the date, the machine, ``what`` was timed and the table ``lines``."""
    import datetime

    cmd = f"OMP_NUM_THREADS=1 .venv/bin/python benchmarks/{script}" + "".join(
        f" --{k} {v}" for k, v, d in (("steps", a.steps, 40), ("rounds", a.rounds, 3)) if v != d)
    text = (f"`{cmd}` ({datetime.date.today().isoformat()}; {machine()}). {what}; the median of {a.rounds} rounds taken "
            "in turns:\n\n" + "\n".join(lines))
    write_section(title, text, *([a.out] if a.out else []))
