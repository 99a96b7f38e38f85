"""The results table: one row per method; RMSE x, y, z, Average, post-switch Average, and, where
they apply, mode accuracy and the ratio of Average to the clairvoyant bound's. A method whose
estimate is not finite on a scored scan shows "diverged (K tracks)" instead of numbers."""

from __future__ import annotations

import math
from typing import Mapping

BOUND = "clairvoyant"
AXES = ("x", "y", "z", "avg")


def finite(x):
    """``x`` where it is a finite number, else ``None``."""
    return x if isinstance(x, (int, float)) and math.isfinite(x) else None


def table_rows(rows: Mapping[str, dict]) -> list[list]:
    """The table's numbers from ``runner.to_json``'s mapping, one row per method: its name, RMSE x, y, z, Average,
    post-switch Average, mode accuracy, the ratio of Average to the bound's and the diverged tracks (0 for a finite
    method); ``None`` where the table shows "-" (no labels, no mode probabilities, a diverged method)."""
    bound = finite(((rows.get(BOUND) or {}).get("rmse") or {}).get("avg"))
    out = []
    for method, r in rows.items():
        rm = r.get("rmse") or {}
        post = r.get("rmse_post_switch") or {}
        avg = finite(rm.get("avg"))
        out.append([method, *(finite(rm.get(a)) for a in AXES), finite(post.get("avg")),
                    finite(r.get("mode_accuracy")), avg / bound if avg is not None and bound else None,
                    int(r.get("diverged", 0))])
    return out


def _num(x) -> str:
    return "-" if x is None else f"{x:.3f}"


def _rows(results: Mapping[str, dict]):
    """Header and string cells (of :func:`table_rows`' numbers); ``results`` maps a method to its JSON row (see
    ``runner.to_json``)."""
    numbers = table_rows(results)
    has_mode = any(row[6] is not None for row in numbers)
    has_bound = any(row[7] is not None for row in numbers)  # where there is a bound, its own row's ratio is 1
    header = ["method", "x [m]", "y [m]", "z [m]", "Average [m]", "post-switch [m]"]
    if has_mode:
        header.append("mode acc.")
    if has_bound:
        header.append("/ bound")
    rows = []
    for name, *rmse, post, acc, ratio, diverged in numbers:
        if results[name]["rmse"] is None:  # a non-finite estimate on a scored scan: no number to show (runner.to_json)
            cells = ["-", "-", "-", f"diverged ({diverged} tracks)"]
        else:
            cells = [_num(v) for v in rmse]
        row = [name, *cells, _num(post)]
        if has_mode:
            row.append(f"{100 * acc:.1f} %" if acc is not None else "-")
        if has_bound:
            row.append(_num(ratio))
        rows.append(row)
    return header, rows


def format_table(results: Mapping[str, dict]) -> str:
    """A fixed-width text table for the terminal."""
    return text_table(*_rows(results))


def format_markdown(results: Mapping[str, dict]) -> str:
    """The same table in GitHub markdown (numbers right-aligned), for the README."""
    header, rows = _rows(results)
    return markdown_table(header, rows, "|" + "|".join([":---"] + ["---:"] * (len(header) - 1)) + "|")


def text_table(header: list[str], rows: list[list[str]]) -> str:
    """Fixed-width text: the first column left-aligned, the others right-aligned, a line of dashes under the header."""
    widths = [max(len(c[i]) for c in [header, *rows]) for i in range(len(header))]
    fmt = lambda cells: "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths)))  # noqa: E731
    lines = [fmt(header), "  ".join("-" * w for w in widths), *(fmt(r) for r in rows)]
    return "\n".join(lines)


def markdown_table(header: list[str], rows: list[list[str]], rule: str) -> str:
    """A GitHub markdown table, ``rule`` the line under its header (the columns' alignment)."""
    return "\n".join(["| " + " | ".join(header) + " |", rule, *("| " + " | ".join(r) + " |" for r in rows)])
