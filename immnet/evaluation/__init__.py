"""Evaluation: the metrics of docs/spec.md section 5, methods by name, the runner, tables and figures.

    from immnet.evaluation import build_method, evaluate, format_table, to_json
    results = evaluate({"imm-accurate": build_method("imm-accurate")}, data)
    print(format_table(to_json(results)))
"""

from immnet.evaluation.methods import (
    Method,
    RawMeasurements,
    available_methods,
    build_method,
    configured_methods,
)
from immnet.evaluation.metrics import (
    MetricAccumulator,
    confusion,
    mode_accuracy,
    position_error,
    post_switch_mask,
    rmse,
    rmse_over_time,
    rmse_pooled,
    rmse_post_switch,
    scored_mask,
)
from immnet.evaluation.runner import evaluate, to_json
from immnet.evaluation.table import format_markdown, format_table

__all__ = [
    "Method", "MetricAccumulator", "RawMeasurements", "available_methods", "build_method",
    "configured_methods", "confusion", "evaluate", "format_markdown", "format_table", "mode_accuracy",
    "position_error", "post_switch_mask", "rmse", "rmse_over_time", "rmse_pooled", "rmse_post_switch",
    "scored_mask", "to_json",
]
