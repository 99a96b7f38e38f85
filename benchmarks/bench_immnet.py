"""IMMNet speed: inference track-steps/s (eager and ``torch.compile``), training trajectory-steps/s.

Run:  .venv/bin/python benchmarks/bench_immnet.py [--steps 40] [--no-compile] [--device cuda] [--parts inference]
It prints tables and rewrites the ``## IMMNet`` section of BENCHMARKS.md (``## IMMNet on cuda`` with ``--device
cuda``; other sections are kept). ``--device``: where the networks, carries and batches live; on a GPU every timing
waits for the device's queued work (``torch.cuda.synchronize``) before the clock is read. ``--parts``: which tables
(inference, stages, training), e.g. only inference where device time is short.
Inference runs the streaming step (``IMMNet.scan``) over already-started tracks, the per-scan cost
of tracking, eager and compiled (``torch.compile`` of ``IMMNet.running_step``, the step without the track start's
two stages, a ``TensorDictSequential``, as one graph; where that fails, with graph breaks, and where that fails, eager), for the shipped weights
(``immnet/pretrained/immnet.ckpt``) and IMM-EKF (IMMNet with nothing learned, ``immnet.filters.IMMEKF``);
then where the time of one scan of the shipped weights goes at batch 1024, stage by stage. Training
runs forward + backward + Adam over TBPTT chunks of 20 scans at batch 64, for the quick and pretrained
recipes' model (filter experts with the IMM interaction and the range guard, the Bayes-corrected
Transformer classifier), the same without the guard, and the paper's. On a shared machine run it with
``OMP_NUM_THREADS=1`` (the command it records names it): under other jobs' load two threads stall.
"""

from __future__ import annotations

import argparse
import datetime
import os
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine, write_section  # noqa: E402

from immnet.data.generate import generate  # noqa: E402
from immnet.data.spec import DataSpec  # noqa: E402
from immnet.filters import IMMEKF  # noqa: E402
from immnet.stages import IMMNet  # noqa: E402
from immnet.tracking.tracker import load_network  # noqa: E402
from immnet.training import Stage1Module, Stage2Module  # noqa: E402

PRETRAINED = Path(__file__).resolve().parents[1] / "immnet" / "pretrained" / "immnet.ckpt"
PARTS = ("training", "inference", "stages")
ROLES = ("start", "interact", "predict", "gain", "update", "classify", "fuse", "join")


def parts(text: str) -> tuple[str, ...]:
    """``--parts``: a comma-separated subset of ``PARTS``."""
    chosen = tuple(v.strip() for v in text.split(",") if v.strip())
    unknown = [v for v in chosen if v not in PARTS]
    if unknown or not chosen:
        raise argparse.ArgumentTypeError(f"unknown part(s) {unknown or text!r}: choose from {', '.join(PARTS)}")
    return chosen


def stage_names(net) -> list[str]:
    """The role of each stage of ``net.step`` (a track's start opens and closes it; filter experts' steps mix in
    their interaction before the predict)."""
    return [next(r for r in ROLES if getattr(net, r, None) is stage) for stage in net.step.module]


def scans(B: int, T: int, device="cpu") -> torch.Tensor:
    td = generate(min(B, 256), seed=0, spec=DataSpec(T=T, min_segment=T // 3))
    z = td["measurements"].float()
    return z.repeat((B + z.shape[0] - 1) // z.shape[0], 1, 1)[:B].to(device)


def wait(device) -> None:
    """Let the device finish its queued work (CUDA runs asynchronously; the CPU needs nothing)."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def median_seconds(fn, repeats: int, device="cpu") -> float:
    """The median wall time of ``repeats`` calls of ``fn()``, each from an idle device to an idle device."""
    times = []
    for _ in range(repeats):
        wait(device)
        t0 = time.perf_counter()
        fn()
        wait(device)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


@torch.no_grad()
def inference(net: IMMNet, B: int, steps: int, step_fn, device="cpu") -> float:
    z = scans(B, max(steps, 3) + 2, device)
    carry = net.initial_carry(B, device=device)
    for t in range(2):  # start the tracks
        carry = net.scan(carry, z[:, t])
    for t in range(2, 5):  # warm-up (and compilation)
        carry = step_fn(carry, z[:, t])

    def timed_pass():  # the same scans each time, from the same carry
        c = carry
        for t in range(2, steps + 2):
            c = step_fn(c, z[:, t])

    return B * steps / median_seconds(timed_pass, 3, device)


def training(module, batch, repeats: int = 5, device="cpu") -> float:
    """Trajectory-steps/s of a ``training_step`` (forward, backward and Adam per TBPTT chunk), the
    median of ``repeats`` timed calls after one warm-up."""
    opt = torch.optim.Adam(module.trainable_parameters(), 1e-4)
    module.optimizers = lambda: opt  # Lightning is not attached: the module's own loop, our optimizer
    module.manual_backward = lambda loss: loss.backward()
    module.log = lambda *a, **k: None
    T = batch["measurements"].shape[-2]
    module.training_step(batch, 0)  # warm-up
    return batch.batch_size[-1] * T / median_seconds(lambda: module.training_step(batch, 0), repeats, device)


MODELS = {  # label: the gain's and the classifier's YAML entries (None: IMMNet's default classifier)
    "the recipes' (filter experts, IMM interaction with the range guard, Bayes + Transformer)": (
        {"class_path": "immnet.stages.filtering.KalmanNetFilterGain", "init_args": {"interaction": "imm", "guard": True}},
        {"class_path": "immnet.stages.BayesTransformerClassifier"},
    ),
    "the same without the guard": (
        {"class_path": "immnet.stages.filtering.KalmanNetFilterGain", "init_args": {"interaction": "imm"}},
        {"class_path": "immnet.stages.BayesTransformerClassifier"},
    ),
    "the paper's (KalmanNetGain, Transformer)": ({"class_path": "immnet.stages.KalmanNetGain"}, None),
}

INFERENCE = {  # label: a function of the model set that builds the network
    "the shipped weights (immnet/pretrained/immnet.ckpt)": lambda model_set: load_network(PRETRAINED),
    "IMM-EKF (IMMNet with nothing learned)": lambda model_set: IMMEKF(model_set=model_set, dtype="float32").network(),
}


def compiled_step(net: IMMNet, carry, z):
    """``(scan, how)``: a scan of started tracks through ``torch.compile`` of ``net.running_step`` (the step without
    the track start's two stages, what ``IMMNet.scan`` runs for them) as one graph (``how`` "fullgraph"), else with
    graph breaks ("graph breaks"), else eager ("eager"), whichever first runs on ``carry, z``."""
    for fullgraph in (True, False):
        torch._dynamo.reset()
        step = torch.compile(net.running_step, fullgraph=fullgraph, dynamic=False)

        def scan(carry, z, step=step):
            td = carry.copy()
            td.set("measurement", z)
            return step(td)

        try:
            scan(carry, z)
        except Exception as err:  # noqa: BLE001 - any failure to compile falls back
            print(f"  torch.compile(fullgraph={fullgraph}) failed: {type(err).__name__}: {str(err)[:200]}", flush=True)
            continue
        return scan, "fullgraph" if fullgraph else "graph breaks"
    return net.scan, "eager"


@torch.no_grad()
def stage_times(net: IMMNet, B: int, compile_: bool, device="cpu") -> list[float]:
    """Milliseconds of each stage of one scan at batch ``B`` (median of 5 calls), each stage compiled alone
    with ``compile_`` (as one graph, else with graph breaks)."""
    z = scans(B, 12, device)
    carry = net.initial_carry(B, device=device)
    for t in range(10):
        carry = net.scan(carry, z[:, t])
    td = carry.copy()
    td.set("measurement", z[:, 10])
    out = []
    for stage in net.step.module:
        fn = torch.compile(stage, fullgraph=True, dynamic=False) if compile_ else stage
        try:
            fn(td.copy())
        except Exception:  # noqa: BLE001 - a stage that does not trace as one graph compiles with breaks
            torch._dynamo.reset()
            fn = torch.compile(stage, dynamic=False)
            fn(td.copy())
        fn(td.copy())
        out.append(1e3 * median_seconds(lambda fn=fn: fn(td.copy()), 5, device))
        td = stage(td)
    return out


def measure_inference(net: IMMNet, steps: int, compile_: bool, batches=(1, 64, 1024), device="cpu"):
    """Rows ``[(B, eager, compiled, how)]`` of inference track-steps/s."""
    net = net.eval().to(device)
    rows = []
    for B in batches:
        eager = inference(net, B, steps, net.scan, device)
        compiled, how = None, "-"
        if compile_:
            with torch.no_grad():
                z = scans(B, 3, device)
                carry = net.initial_carry(B, device=device)
                for t in range(2):
                    carry = net.scan(carry, z[:, t])
                step, how = compiled_step(net, carry, z[:, 2])
            compiled = inference(net, B, steps, step, device)
        rows.append((B, eager, compiled, how))
        print(f"  inference batch {B}: eager {eager:,.0f}, compiled ({how}) {compiled or 0:,.0f} track-steps/s", flush=True)
    return rows


def measure_training(model_set: str, gain: dict, classifier: dict | None, expert_weight: float, device="cpu"):
    """Training trajectory-steps/s ``(stage 1, stage 2, stage 2 + own-mode term)``, eager."""
    torch._dynamo.reset()
    torch.manual_seed(0)
    td = generate(64, seed=1, spec=DataSpec(T=40, min_segment=12))  # two TBPTT chunks of 20
    td = td.apply(lambda v: v.float() if v.is_floating_point() else v).to(device)
    cfg = {"model_set": model_set, "gain": gain, "classifier": classifier}
    s1 = Stage1Module(net=cfg).to(device)
    train = (
        training(s1, td.unsqueeze(0).expand(s1.net.n_experts, 64), device=device),
        training(Stage2Module(net=cfg).to(device), td, device=device),
        training(Stage2Module(net=cfg, expert_weight=expert_weight).to(device), td, device=device),
    )
    print("  training: stage 1 {:,.0f}, stage 2 {:,.0f}, with the own-mode term {:,.0f} trajectory-steps/s".format(*train), flush=True)
    return train


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=40, help="scans timed per inference run")
    p.add_argument("--no-compile", action="store_true")
    p.add_argument("--model-set", default="configs/model_sets/imm4-adaptive.yaml",
                   help="experts (default: the quick and pretrained recipes' set)")
    p.add_argument("--expert-weight", type=float, default=0.3,
                   help="stage 2's own-mode term for the second stage-2 row (the quick recipe's value)")
    p.add_argument("--batches", type=lambda v: tuple(int(b) for b in v.split(",")), default=(1, 64, 1024),
                   help="inference batch sizes, comma-separated (default 1,64,1024)")
    p.add_argument("--stage-batch", type=int, default=1024, help="batch of the stage-by-stage table")
    p.add_argument("--device", default="cpu", help="where to run: cpu (default), cuda, cuda:1, ...")
    p.add_argument("--parts", type=parts, default=PARTS, help=f"tables to measure, comma-separated (default {','.join(PARTS)})")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        p.error(f"--device {args.device}: this torch ({torch.__version__}) sees no CUDA device")
    train = {}  # training first, eager, before anything is compiled in this process
    if "training" in args.parts:
        for label, (gain, classifier) in MODELS.items():
            print(label, flush=True)
            train[label] = measure_training(args.model_set, gain, classifier, args.expert_weight, device)
    infer = {}
    if "inference" in args.parts:
        for label, make in INFERENCE.items():
            print(label, flush=True)
            infer[label] = measure_inference(make(args.model_set), args.steps, not args.no_compile, args.batches, device)
    net = INFERENCE["the shipped weights (immnet/pretrained/immnet.ckpt)"](args.model_set).eval().to(device)
    STAGES = stage_names(net)
    if "stages" in args.parts:
        print(f"stages of one scan at batch {args.stage_batch} (ms)", flush=True)
        eager_ms = stage_times(net, args.stage_batch, False, device)
        compiled_ms = stage_times(net, args.stage_batch, True, device) if not args.no_compile else [None] * len(STAGES)
        print("  eager " + ", ".join(f"{n} {v:.1f}" for n, v in zip(STAGES, eager_ms)), flush=True)
    names = net.model_set.names
    env = "".join(f"{k}={os.environ[k]} " for k in ("OMP_NUM_THREADS",) if k in os.environ)
    # the interpreter that ran (the checkout's venv, or e.g. a GPU image's python3), without --out
    exe = ".venv/bin/python" if ".venv" in sys.executable else Path(sys.executable).name
    given = list(argv if argv is not None else sys.argv[1:])
    if "--out" in given:
        del given[given.index("--out"):given.index("--out") + 2]
    cmd = f"`{env}{exe} benchmarks/bench_immnet.py" + "".join(f" {a}" for a in given) + "`"
    where = machine() + (f", {torch.cuda.get_device_name(device)}" if device.type == "cuda" else "")
    labels, tlabels = list(infer), list(train)
    fmt = lambda v: "-" if v is None else f"{v:,.0f}"  # noqa: E731
    lines = [f"{cmd} ({datetime.date.today().isoformat()}; {where}); experts {', '.join(names)}."]
    if infer:
        lines += [
            "",
            "| inference (streaming step; median of 3 passes), track-steps/s | " + " | ".join(f"{l}: eager | compiled" for l in labels) + " |",
            "|---|" + "---:|---:|" * len(labels),
            *[
                f"| batch {B} | " + " | ".join(f"{fmt(infer[l][i][1])} | {fmt(infer[l][i][2])}" for l in labels) + " |"
                for i, B in enumerate(args.batches)
            ],
            "",
            "Compiled: " + "; ".join(f"{l}: {', '.join(sorted({r[3] for r in infer[l]}))}" for l in labels) + ".",
        ]
    if "stages" in args.parts:
        lines += [
            "",
            f"| one scan of the shipped weights at batch {args.stage_batch}, ms (median of 5 calls; compiled: each stage alone) | "
            + " | ".join(STAGES) + " | sum |",
            "|---|" + "---:|" * (len(STAGES) + 1),
            "| eager | " + " | ".join(f"{v:.1f}" for v in eager_ms) + f" | {sum(eager_ms):.1f} |",
            "| compiled | " + " | ".join("-" if v is None else f"{v:.1f}" for v in compiled_ms)
            + (" | - |" if compiled_ms[0] is None else f" | {sum(compiled_ms):.1f} |"),
        ]
    if train:
        lines += [
            "",
            "| training (batch 64, TBPTT 20, forward + backward + Adam; median of 5 calls), trajectory-steps/s | " + " | ".join(tlabels) + " |",
            "|---|" + "---:|" * len(tlabels),
            "| stage 1 (experts alone; a step = one trajectory through every expert) | " + " | ".join(fmt(train[l][0]) for l in tlabels) + " |",
            "| stage 2 (end to end, the paper's loss) | " + " | ".join(fmt(train[l][1]) for l in tlabels) + " |",
            f"| stage 2 with the own-mode term (expert_weight {args.expert_weight:g}, as the quick recipe) | " + " | ".join(fmt(train[l][2]) for l in tlabels) + " |",
        ]
    lines += [
        "",
        "One run on a machine other jobs may share (see the load average): repeated runs have differed by up to",
        "a quarter, so compare rows of one run, not numbers across runs.",
    ]
    title = "IMMNet" if device.type == "cpu" else f"IMMNet on {device.type}"
    write_section(title, "\n".join(lines), args.out or Path(__file__).resolve().parents[1] / "BENCHMARKS.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
