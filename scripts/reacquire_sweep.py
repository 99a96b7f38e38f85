"""Re-acquisition's settings (immnet.imm.reacquire) on data sets of plots: for each set and setting, the robust IMM's (or
with `net` the band's shipped network's) Average RMSE (immnet evaluate's, --split all), its z, the worst 3D error of
any scan, the tracks ever above 1 km, and the restarts of the model-based loop (a start contradicted by its next plot;
a run of far plots; the network's count includes starting tracks it discards):

    python scripts/reacquire_sweep.py runs/radar/data/q5-out/val,runs/radar/data/q11-out/val \
        '[null, {"scans": 2, "gate": 25.0, "speed": 300.0}]' [net]

A set's band is 5 s where its directory names q5 or h5 (else 11 s).
"""
import sys, time, json, yaml, torch
from immnet import keys
from immnet.config import resolve_path
from immnet.evaluation.cli import load_split
from immnet.evaluation.metrics import position_error, rmse, scored_distance, scored_mask
from immnet.filters.trackers import IMMTracker
from immnet.tracking.methods import IMMNetMethod
import immnet.imm.reacquire as R_

count = [0, 0]
orig = R_.advance
def spy(rule, state, z, R, interval, maha, active=None):
    new, restart, rejected = orig(rule, state, z, R, interval, maha, active)
    starting = state.count < 0
    count[0] += int((restart & starting).sum()); count[1] += int((restart & ~starting).sum())
    return new, restart, rejected
R_.advance = spy

def row(method, data):
    count[0] = count[1] = 0
    out = method.track(data)
    mask = scored_mask(data[keys.STATES], data[keys.MEASUREMENTS])
    err = position_error(out[keys.STATE], data[keys.STATES])
    dist = scored_distance(err, mask).amax(1)
    r = rmse(err, mask)
    return {"avg": r["avg"], "z": r["z"], "worst": float(dist.max()), "over1km": int((dist > 1000).sum()),
            "n": int(dist.numel()), "start_restarts": count[0], "run_restarts": count[1]}

sets = sys.argv[1].split(",")
settings = json.loads(sys.argv[2])  # list of reacquire configs (None = off)
nets = len(sys.argv) > 3 and sys.argv[3] == "net"
for s in sets:
    band = "5s" if ("q5-" in s or "h5-" in s) else "11s"
    data, _ = load_split(s, "all", None)
    args = yaml.safe_load(resolve_path(f"configs/methods/radar-imm-robust-{band}.yaml").read_text())["init_args"]
    for re in settings:
        t0 = time.time()
        if nets:
            m = IMMNetMethod(f"immnet/pretrained/immnet-radar-{band}.ckpt", name="net", guard=None, reacquire=re)
        else:
            m = IMMTracker(**{**args, "reacquire": re})
        print(s, "net" if nets else "imm", json.dumps(re), json.dumps({k: (round(v, 1) if isinstance(v, float) else v) for k, v in row(m, data).items()}), f"{time.time()-t0:.0f}s", flush=True)
