"""IMM-Tuned: the best IMM a careful engineer would configure from validation data alone.

A coordinate search (docs/spec.md section 3) over five knobs, scored by the Average RMSE (per-axis
position RMSE per trajectory ``sqrt(mean_t e^2)``, mean over trajectories, mean of the 3 axes) on
the validation trajectories given, never on test data:

* ``model_set``: imm3 (CV, CA, CT +5 deg/s), imm4 (CT +/-5), imm6 (CT +/-3, +/-8);
* ``sigma_q`` of CV and CT experts (white-noise acceleration): 0.2, 0.5, 1, 2, 4 (a fixed-rate CT
  expert meets turns of 1 to 10 deg/s, up to ~50 m/s^2 centripetal, so the useful range is wide);
* ``sigma_q`` of the CA expert (Wiener-process acceleration): 0.05, 0.1, 0.2, 0.5, 1;
* ``p_stay`` (transition matrix diagonal, the rest shared evenly): 0.8, 0.9, 0.95, 0.98;
* ``r``, the filter's assumed measurement std (m): 3, 4, 5.

From ``START`` it sweeps each knob in turn with the others held at the best so far, and repeats
the sweep until a full pass changes nothing (at most ``max_passes``; ``immnet.evaluation.search``'s
``coordinate_search``); settings already scored are not run again. Each run is one batched IMM over all
trajectories (float64).
"""

from __future__ import annotations

import datetime
from pathlib import Path

import yaml
from tensordict import TensorDict

from immnet import keys
from immnet.evaluation.search import average_rmse, coordinate_search
from immnet.filters.trackers import IMMTracker
from immnet.motion import ModelSet

MODEL_SETS = {
    "imm3": "configs/model_sets/imm3.yaml",
    "imm4": "configs/model_sets/imm4.yaml",
    "imm6": "configs/model_sets/imm6.yaml",
}
GRID = {
    "model_set": list(MODEL_SETS),
    "sigma_q_cv_ct": [0.2, 0.5, 1.0, 2.0, 4.0],
    "sigma_q_ca": [0.05, 0.1, 0.2, 0.5, 1.0],
    "p_stay": [0.8, 0.9, 0.95, 0.98],
    "r": [3.0, 4.0, 5.0],
}
START = {"model_set": "imm6", "sigma_q_cv_ct": 1.0, "sigma_q_ca": 0.2, "p_stay": 0.9, "r": 4.0}


def make_tracker(setting: dict) -> IMMTracker:
    """The IMM of one search setting (CA experts get ``sigma_q_ca``, all others ``sigma_q_cv_ct``)."""
    ms = ModelSet.from_config(MODEL_SETS[setting["model_set"]])
    sq = [setting["sigma_q_ca"] if m.mode == 1 else setting["sigma_q_cv_ct"] for m in ms]
    return IMMTracker(MODEL_SETS[setting["model_set"]], setting["r"], sq, setting["p_stay"], name="imm-tuned")


def tune_imm(val_batch: TensorDict, out_path, progress: bool = True, max_passes: int = 2, grid: dict | None = None,
             start: dict | None = None) -> dict:
    """Coordinate search on ``val_batch``; writes the winner to ``out_path`` (YAML, the search in its header) and
    returns ``{"best": setting, "score": avg_rmse, "table": [{**setting, "score", "seconds"}, ...]}``.

    ``grid`` / ``start`` replace (some knobs of) ``GRID`` / ``START`` for a cheaper search."""
    grid = {**GRID, **(grid or {})}
    start = {**START, **(start or {})}
    if keys.STATES not in val_batch.keys():
        raise ValueError("tune_imm needs 'states' (ground truth) in the validation data to score settings")
    # each setting scored by its IMM's Average RMSE on the batch, over the scans immnet evaluate scores
    best, best_score, table = coordinate_search(lambda setting: average_rmse(make_tracker(setting), val_batch), grid,
                                                start, max_passes, progress, tag="tune-imm")
    header = [
        "# IMM-Tuned (docs/spec.md section 3): written by immnet.evaluation.tuning.tune_imm, do not edit by hand.",
        f"# Coordinate search over {grid} ({len(table)} settings scored),",
        f"# chosen on validation data only: validation batch, {val_batch.batch_size[0]} trajectories.",
        f"# Validation Average RMSE {best_score:.4f} m; {datetime.date.today().isoformat()}.",
        f"# Setting: {best}",
    ]
    config = {
        "class_path": "immnet.filters.IMMTracker",
        "init_args": {
            "name": "imm-tuned",
            "model_set": MODEL_SETS[best["model_set"]],
            "r": float(best["r"]),
            "sigma_q": make_tracker(best).sigma_q,
            "p_stay": float(best["p_stay"]),
        },
    }
    Path(out_path).write_text("\n".join(header) + "\n" + yaml.safe_dump(config, sort_keys=False))
    return {"best": best, "score": best_score, "table": table}
