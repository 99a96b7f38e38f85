"""The results table: one row per method; RMSE x, y, z, Average, post-switch Average, and, where
they apply, mode accuracy and the ratio of Average to the clairvoyant bound's. A method whose
estimate is not finite on a scored scan shows "diverged (K tracks)" instead of numbers."""

from __future__ import annotations

from typing import Mapping

BOUND = "clairvoyant"


def _num(x) -> str:
    return "-" if x is None else f"{x:.3f}"


def _rows(results: Mapping[str, dict]):
    """Header and string cells; ``results`` maps a method to its JSON row (see ``runner.to_json``)."""
    has_mode = any(r.get("mode_accuracy") is not None for r in results.values())
    bound = (results.get(BOUND, {}).get("rmse") or {}).get("avg")
    header = ["method", "x [m]", "y [m]", "z [m]", "Average [m]", "post-switch [m]"]
    if has_mode:
        header.append("mode acc.")
    if bound:
        header.append("/ bound")
    rows = []
    for name, r in results.items():
        rm = r["rmse"]
        post = r.get("rmse_post_switch")
        if rm is None:  # a non-finite estimate on a scored scan: no number to show (runner.to_json)
            cells = ["-", "-", "-", f"diverged ({r.get('diverged', '?')} tracks)"]
        else:
            cells = [_num(rm[a]) for a in ("x", "y", "z", "avg")]
        row = [name, *cells, _num(post["avg"]) if post else "-"]
        if has_mode:
            acc = r.get("mode_accuracy")
            row.append(f"{100 * acc:.1f} %" if acc is not None else "-")
        if bound:
            row.append(_num(rm["avg"] / bound) if rm is not None and rm["avg"] is not None else "-")
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
