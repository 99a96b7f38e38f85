"""IMMNet speed: inference track-steps/s (eager and ``torch.compile``), training trajectory-steps/s.

Run:  .venv/bin/python benchmarks/bench_immnet.py [--steps 40] [--no-compile]
It prints a table and rewrites the ``## IMMNet`` section of BENCHMARKS.md (other sections are kept).
Inference runs the streaming step (``IMMNet.scan``) over already-started tracks, the per-scan cost
of tracking; training runs forward + backward + Adam over TBPTT chunks of 20 scans at batch 64.
Three models are measured in one run: the quick and pretrained recipes' (filter experts with the IMM
interaction and the range guard, the Bayes-corrected Transformer classifier), the same without the
guard (``configs/ablations/no-guard.yaml``), and the paper's (``KalmanNetGain`` experts, the Transformer).
"""

from __future__ import annotations

import argparse
import datetime
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import machine, write_section  # noqa: E402

from immnet.data.generate import generate  # noqa: E402
from immnet.data.spec import DataSpec  # noqa: E402
from immnet.stages import IMMNet  # noqa: E402
from immnet.training import Stage1Module, Stage2Module  # noqa: E402


def scans(B: int, T: int) -> torch.Tensor:
    td = generate(min(B, 256), seed=0, spec=DataSpec(T=T, min_segment=T // 3))
    z = td["measurements"].float()
    return z.repeat((B + z.shape[0] - 1) // z.shape[0], 1, 1)[:B]


def median_seconds(fn, repeats: int) -> float:
    """The median wall time of ``repeats`` calls of ``fn()``."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


@torch.no_grad()
def inference(net: IMMNet, B: int, steps: int, step_fn) -> float:
    z = scans(B, max(steps, 3) + 2)
    carry = net.initial_carry(B)
    for t in range(2):  # start the tracks
        carry = net.scan(carry, z[:, t])
    for t in range(2, 5):  # warm-up (and compilation)
        carry = step_fn(carry, z[:, t])

    def timed_pass():  # the same scans each time, from the same carry
        c = carry
        for t in range(2, steps + 2):
            c = step_fn(c, z[:, t])

    return B * steps / median_seconds(timed_pass, 3)


def training(module, batch, repeats: int = 5) -> float:
    """Trajectory-steps/s of a ``training_step`` (forward, backward and Adam per TBPTT chunk), the
    median of ``repeats`` timed calls after one warm-up."""
    opt = torch.optim.Adam(module.trainable_parameters(), 1e-4)
    module.optimizers = lambda: opt  # Lightning is not attached: the module's own loop, our optimizer
    module.manual_backward = lambda loss: loss.backward()
    module.log = lambda *a, **k: None
    T = batch["measurements"].shape[-2]
    module.training_step(batch, 0)  # warm-up
    return batch.batch_size[-1] * T / median_seconds(lambda: module.training_step(batch, 0), repeats)


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


def measure(model_set: str, gain: dict, classifier: dict | None, steps: int, compile_: bool, expert_weight: float):
    """Inference rows ``[(B, eager, compiled)]`` and training ``(stage 1, stage 2, stage 2 + own-mode term)``."""
    torch._dynamo.reset()
    torch.manual_seed(0)
    # training first, eager, before anything is compiled in this process
    td = generate(64, seed=1, spec=DataSpec(T=40, min_segment=12))  # two TBPTT chunks of 20
    td = td.apply(lambda v: v.float() if v.is_floating_point() else v)
    cfg = {"model_set": model_set, "gain": gain, "classifier": classifier}
    s1 = Stage1Module(net=cfg)
    train = (
        training(s1, td.unsqueeze(0).expand(s1.net.n_experts, 64)),
        training(Stage2Module(net=cfg), td),
        training(Stage2Module(net=cfg, expert_weight=expert_weight), td),
    )
    print("  training: stage 1 {:,.0f}, stage 2 {:,.0f}, with the own-mode term {:,.0f} trajectory-steps/s".format(*train), flush=True)
    net = IMMNet(model_set=model_set, gain=gain, classifier=classifier).eval()
    rows = []
    for B in (1, 64, 1024):
        eager = inference(net, B, steps, net.scan)
        compiled = None
        if compile_:
            torch._dynamo.reset()  # each (gain, batch) compiles afresh, within dynamo's recompile limit
            step = torch.compile(net.step, fullgraph=False, dynamic=False)

            def compiled_scan(carry, z, step=step):
                td = carry.copy()
                td.set("measurement", z)
                return step(td)

            compiled = inference(net, B, steps, compiled_scan)
        rows.append((B, eager, compiled))
        print(f"  inference batch {B}: eager {eager:,.0f}, compiled {compiled or 0:,.0f} track-steps/s", flush=True)
    return net.model_set.names, rows, train


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=40, help="scans timed per inference run")
    p.add_argument("--no-compile", action="store_true")
    p.add_argument("--model-set", default="configs/model_sets/imm4-adaptive.yaml",
                   help="experts (default: the quick and pretrained recipes' set)")
    p.add_argument("--expert-weight", type=float, default=0.3,
                   help="stage 2's own-mode term for the second stage-2 row (the quick recipe's value)")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    results = {}
    for label, (gain, classifier) in MODELS.items():
        print(label, flush=True)
        results[label] = measure(args.model_set, gain, classifier, args.steps, not args.no_compile, args.expert_weight)
    names = next(iter(results.values()))[0]
    cmd = "`.venv/bin/python benchmarks/bench_immnet.py" + "".join(f" {a}" for a in (argv if argv is not None else sys.argv[1:])) + "`"
    labels = list(results)
    lines = [
        f"{cmd} ({datetime.date.today().isoformat()}; {machine()}); experts {', '.join(names)}.",
        "",
        "| inference (streaming step; median of 3 passes), track-steps/s | " + " | ".join(f"{l}: eager | compiled" for l in labels) + " |",
        "|---|" + "---:|---:|" * len(labels),
        *[
            f"| batch {B} | " + " | ".join(
                f"{results[l][1][i][1]:,.0f} | " + ("-" if results[l][1][i][2] is None else f"{results[l][1][i][2]:,.0f}") for l in labels
            ) + " |"
            for i, B in enumerate((1, 64, 1024))
        ],
        "",
        "| training (batch 64, TBPTT 20, forward + backward + Adam; median of 5 calls), trajectory-steps/s | " + " | ".join(labels) + " |",
        "|---|" + "---:|" * len(labels),
        "| stage 1 (experts alone; a step = one trajectory through every expert) | " + " | ".join(f"{results[l][2][0]:,.0f}" for l in labels) + " |",
        "| stage 2 (end to end, the paper's loss) | " + " | ".join(f"{results[l][2][1]:,.0f}" for l in labels) + " |",
        f"| stage 2 with the own-mode term (expert_weight {args.expert_weight:g}, as the quick recipe) | " + " | ".join(f"{results[l][2][2]:,.0f}" for l in labels) + " |",
        "",
        "One run on a machine other jobs may share (see the load average): repeated runs have differed by up to",
        "a quarter, so compare rows of one run, not numbers across runs.",
    ]
    write_section("IMMNet", "\n".join(lines), args.out or Path(__file__).resolve().parents[1] / "BENCHMARKS.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
