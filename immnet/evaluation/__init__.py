"""Evaluation: the metrics of docs/spec.md section 5, methods by name, the runner, tables and figures.

    from immnet.evaluation import build_method, evaluate, format_table, to_json
    results = evaluate({"imm-accurate": build_method("imm-accurate")}, data)
    print(format_table(to_json(results)))

The names below load their modules (torch) when first asked for, so that ``immnet.evaluation.cli`` builds
``immnet evaluate --help`` without them.
"""

from immnet.lazy import lazy_names

__getattr__, __dir__, __all__ = lazy_names(__name__, {
    **dict.fromkeys(("Method", "RawMeasurements", "available_methods", "build_method"), "immnet.filters.methods"),
    "configured_methods": "immnet.filters.registry",
    **dict.fromkeys(("MetricAccumulator", "confusion", "mode_accuracy", "position_error", "post_switch_mask", "rmse",
                     "rmse_over_time", "rmse_pooled", "rmse_post_switch", "scored_mask"), "immnet.evaluation.metrics"),
    "gospa": "immnet.evaluation.gospa", "track_metrics": "immnet.evaluation.gospa",
    "evaluate": "immnet.evaluation.runner", "to_json": "immnet.evaluation.runner",
    "format_markdown": "immnet.evaluation.table", "format_table": "immnet.evaluation.table",
})

