"""What every benchmark shares: a description of the machine and rewriting one section of BENCHMARKS.md."""

from __future__ import annotations

import os
import platform
import re
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
