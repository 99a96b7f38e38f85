"""Build the W&B report of configs/wandb/report.yaml from the synced runs of a W&B project.

    pip install "wandb[workspaces]"          # wandb_workspaces: W&B's reports API (not an IMMNet dependency)
    wandb login && wandb sync runs/wandb/offline-run-*
    .venv/bin/python scripts/wandb_report.py [--entity ENTITY] [--project immnet] [--definition configs/wandb/report.yaml]

Needs network and a W&B login (it saves the report to W&B and prints its URL); `--check` only reads and
checks the definition, offline. Every other part of IMMNet runs W&B offline (docs/wandb.md).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
DEFINITION = ROOT / "configs/wandb/report.yaml"
KINDS = ("table", "chart", "media", "bar", "line")
LINE_SERIES = {"chart_name": "wandb/lineseries/v0", "fields": {"step": "step", "lineKey": "lineKey", "lineVal": "lineVal"}}
"""The chart ``wandb.plot.line_series`` logs: its Vega spec and fields (``immnet.evaluation.wandb_log``)."""


def load(path=DEFINITION) -> dict:
    """The report definition, checked: a title and sections, each with a heading, a runs filter and panels
    of one known kind each; ``ValueError`` naming what is wrong."""
    spec = yaml.safe_load(Path(path).read_text())
    if not isinstance(spec, dict) or not spec.get("title") or not isinstance(spec.get("sections"), list):
        raise ValueError(f"{path}: a report definition has a `title` and a list of `sections`")
    for i, sec in enumerate(spec["sections"]):
        missing = [k for k in ("heading", "runs", "panels") if not sec.get(k)]
        if missing:
            raise ValueError(f"{path}: section {i + 1} lacks {', '.join(missing)}")
        for panel in sec["panels"]:
            kinds = [k for k in KINDS if k in panel]
            if len(kinds) != 1 or set(panel) - {*KINDS, "w"}:
                raise ValueError(f"{path}: section {i + 1}: a panel is one of {', '.join(KINDS)} (and `w`), got {panel}")
    return spec


def panel(wr, p: dict):
    """A ``wandb_workspaces.reports.v2`` panel from one entry of the definition."""
    layout = wr.Layout(w=p.get("w", 12), h=10)
    if "table" in p:
        return wr.WeavePanelSummaryTable(table_name=p["table"], layout=layout)
    if "chart" in p:  # the table line_series logged under KEY is KEY_table
        return wr.CustomChart(query={"summaryTable": {"tableKey": f"{p['chart']}_table"}}, chart_name=LINE_SERIES["chart_name"],
                              chart_fields=LINE_SERIES["fields"], chart_strings={"title": p["chart"]}, layout=layout)
    if "media" in p:
        return wr.MediaBrowser(media_keys=list(p["media"]), layout=layout)
    if "bar" in p:
        return wr.BarPlot(title=p["bar"], metrics=[p["bar"]], orientation="h", layout=layout)
    return wr.LinePlot(x="Step", y=list(p["line"]), layout=layout)


def build(spec: dict, entity: str | None, project: str):
    """The report (unsaved) of ``spec`` over ``entity/project``."""
    import wandb_workspaces.reports.v2 as wr

    blocks = [wr.P(spec.get("description", ""))]
    for sec in spec["sections"]:
        runset = wr.Runset(project=project, name=sec["heading"], filters=sec["runs"], **({"entity": entity} if entity else {}))
        blocks += [wr.H2(sec["heading"]), wr.PanelGrid(runsets=[runset], panels=[panel(wr, p) for p in sec["panels"]])]
    kw = {"entity": entity} if entity else {}
    return wr.Report(project=project, title=spec["title"], description=spec.get("description", ""), blocks=blocks, **kw)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--entity", default=None, help="W&B entity (default: your default entity)")
    p.add_argument("--project", default="immnet", help="W&B project the runs were synced to (default immnet)")
    p.add_argument("--definition", type=Path, default=DEFINITION, help="the report definition (YAML)")
    p.add_argument("--check", action="store_true", help="only check the definition (offline)")
    a = p.parse_args()
    spec = load(a.definition)
    if a.check:
        print(f"{a.definition}: {len(spec['sections'])} sections, "
              f"{sum(len(s['panels']) for s in spec['sections'])} panels", file=sys.stderr)
        return 0
    try:
        import wandb_workspaces  # noqa: F401
    except ImportError:
        raise SystemExit('scripts/wandb_report.py needs wandb_workspaces: pip install "wandb[workspaces]"') from None
    report = build(spec, a.entity, a.project)
    report.save()
    print(report.url)
    return 0


if __name__ == "__main__":
    sys.exit(main())
