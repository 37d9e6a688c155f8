"""Training throughput: one training step of the tiny preset at 64x64 (2 context + 4 target
views), variants (a) and (c), timed phase by phase (data to device, forward, loss, backward,
gradient norms + clipping, optimiser), the current trainer against the previous one (Adam
unfused, per-parameter float64 gradient norms, then torch's clip_grad_norm_) in the same
process, interleaved step by step.
Wall and process CPU time; medians over steps.

    python train/bench/training.py --data outputs/big/train480 --threads 1 --steps 20

``--clip N``: instead, the gradient norms and clipping alone, N times each on one step's
gradients (restored before every call), alternating the two calls the trainer made before
(``group_grad_norms`` then ``torch.nn.utils.clip_grad_norm_``) and
``usplat_dr.training.optim.clip_gradients``.

``--scatter``: instead, the whole training step (``Trainer.train_step``) with the rasteriser's
backward adding each pair's gradients as one packet record (``backward_scatter="packet"``, the
LLVM default) against ten scalar scatter-adds (``"lanes"``), two trainers from the same seed on
the same batches, interleaved step by step in ABBA order: medians, and how far the two loss
curves drift apart (float summation order only: the largest step's difference, and the means').

``--awake on|off``: instead, one process of train/bench/cores.py's comparison: the current
trainer's per-phase medians of ``--steps`` steps (after 3 warm-up steps) per variant, with the
cores kept awake (``usplat_dr.training.cores.CoreKeeper``, for the whole process) or not, as one
JSON line.
"""

import argparse
import json
import statistics
import sys
import time
from functools import partial

if "--torch-first" in sys.argv:  # users' order; usplat_dr cannot then shorten OpenMP's spin
    import torch  # noqa: F401

import usplat_dr  # noqa: F401  (libLLVM before drjit)

PHASES = ["data", "forward", "loss", "backward", "norms+clip", "optimiser", "total"]


def old_group_grad_norms(trainer) -> dict:
    """The previous trainer's per-group norms: a float64 sum per parameter."""
    import torch

    from usplat_dr.training.optim import GRAD_GROUPS

    sums: dict = {}
    for name, p in trainer.model.named_parameters():
        key = GRAD_GROUPS.get(name.split(".", 1)[0])
        if key is not None and p.grad is not None:
            sq = p.grad.detach().double().square().sum()
            sums[key] = sums[key] + sq if key in sums else sq
    return {k: torch.sqrt(v).item() for k, v in sums.items()}


# Own timing, not usplat_dr.evaluation.timing (whole calls): the phases inside one step.
def timed_step(trainer, batch, old: bool) -> dict:
    import torch

    from usplat_dr.data.types import model_inputs
    from usplat_dr.training.optim import clip_gradients

    t, c = {}, {}

    def mark(name, t0, c0):
        t[name], c[name] = time.perf_counter() - t0, time.process_time() - c0
        return time.perf_counter(), time.process_time()

    w0, p0 = time.perf_counter(), time.process_time()
    trainer.model.train()
    args = model_inputs(batch, trainer.device)
    trainer.optimizer.zero_grad(set_to_none=True)
    w, p = mark("data", w0, p0)
    out = trainer.model(*args, global_step=trainer.step)
    w, p = mark("forward", w, p)
    loss, _ = trainer.loss(out, batch)
    w, p = mark("loss", w, p)
    loss.backward()
    w, p = mark("backward", w, p)
    if old:
        old_group_grad_norms(trainer)
        torch.nn.utils.clip_grad_norm_(trainer.model.parameters(), 0.5)
    else:
        clip_gradients(trainer.model, 0.5)
    w, p = mark("norms+clip", w, p)
    trainer.optimizer.step()
    mark("optimiser", w, p)
    t["total"], c["total"] = time.perf_counter() - w0, time.process_time() - p0
    return {"wall": t, "cpu": c}


def make_trainer(data: str, variant: str, threads: int):
    """A trainer of the shipped recipe (tiny preset, 64x64) on ``data``, seeded."""
    import torch

    from usplat_dr.config import load_config
    from usplat_dr.training import Trainer

    torch.manual_seed(0)
    return Trainer(load_config(["synthetic_tiny_depth.yaml"], [
        f"dataset.roots=[{data}]", "output_dir=/tmp/bench_training",
        f"model.variant={variant}", f"threads={threads}", "train.progress=false"]))


def clip_ab(trainer, batch, repeats: int) -> tuple[float, float]:
    """Median ms of (group_grad_norms + clip_grad_norm_) and of clip_gradients."""
    import torch

    from usplat_dr.data.types import model_inputs
    from usplat_dr.training.optim import clip_gradients, group_grad_norms

    out = trainer.model(*model_inputs(batch, trainer.device), global_step=0)
    trainer.loss(out, batch)[0].backward()
    params = [p for p in trainer.model.parameters() if p.grad is not None]
    saved = [p.grad.clone() for p in params]
    clip = trainer.config.optimizer.gradient_clip
    times: tuple[list, list] = ([], [])
    # Own loop, not usplat_dr.evaluation.timing: gradients are restored, untimed, before each call.
    for _ in range(repeats):
        for i in (0, 1):
            for p, g in zip(params, saved):
                p.grad.copy_(g)
            t0 = time.perf_counter()
            if i == 0:
                group_grad_norms(trainer.model)
                torch.nn.utils.clip_grad_norm_(trainer.model.parameters(), clip)
            else:
                clip_gradients(trainer.model, clip)
            times[i].append(time.perf_counter() - t0)
    return tuple(1000 * statistics.median(t) for t in times)


def awake_medians(args) -> dict:
    """This process's medians (ms) per variant, with or without the cores kept awake."""
    import logging

    from usplat_dr.training.cores import CoreKeeper

    logging.basicConfig(level=logging.ERROR)
    logging.getLogger("usplat_dr").setLevel(logging.ERROR)
    keeper = CoreKeeper().start() if args.awake == "on" else None
    try:
        out = {}
        for variant in args.variants:
            tr = make_trainer(args.data, variant, args.threads)
            rs = [timed_step(tr, tr.batches.next(), False) for _ in range(args.steps + 3)][3:]
            out[variant] = {"wall": {ph: 1000 * statistics.median(r["wall"][ph] for r in rs)
                                     for ph in PHASES},
                            "cpu": 1000 * statistics.median(r["cpu"]["total"] for r in rs)}
        out["spinners"] = len(keeper.procs) if keeper else 0
        return out
    finally:
        if keeper is not None:
            keeper.stop()


def loss_step(trainer, batches, losses: list) -> None:
    """One training step of ``trainer`` on the next of ``batches``; its loss goes to ``losses``."""
    losses.append(trainer.train_step(next(batches))["loss"])
    trainer.step += 1


def scatter_ab(args) -> None:
    """``--scatter``: the training step with the packet backward against the lanes one."""
    from usplat_dr.evaluation.timing import interleaved, machine_line
    from usplat_dr.model.decoder import DecoderSplatting
    from usplat_dr.render import RasterSettings

    print(machine_line())
    print(f"threads={args.threads}, {args.steps} steps per configuration after 3 warm-up, "
          f"medians (ms); CPU = process CPU time")
    print("| variant | lanes ms (CPU ms) | packet ms (CPU ms) | packet / lanes | largest loss "
          "difference (relative) | mean loss, packet / lanes - 1 |")
    print("|---|---|---|---|---|---|")
    for variant in args.variants:
        pair = {}
        # --scatter-control: "packet" runs the lanes backward too, so that the columns show
        # how far two runs of the same code drift apart (2 threads: atomics' order)
        modes = {"lanes": "lanes", "packet": "lanes" if args.scatter_control else "packet"}
        for name, mode in modes.items():
            tr = make_trainer(args.data, variant, args.threads)  # seeded: the same start
            tr.model.decoder = DecoderSplatting(RasterSettings(sh_basis="mvsplat",
                                                               backward_scatter=mode))
            pair[name] = tr
        batches = [pair["lanes"].batches.next() for _ in range(args.steps + 3)]
        losses = {m: [] for m in pair}
        # 3 warm-up steps, then ABBA (usplat_dr.evaluation.timing.interleaved): the trainer
        # that runs second in a step pays ~3-5% (measured: cache and allocator state)
        t = interleaved({m: partial(loss_step, tr, iter(batches), losses[m])
                         for m, tr in pair.items()}, args.steps, warmup=3)
        med = {m: (t[m].wall, t[m].cpu) for m in pair}
        drift = max(abs(a - b) / abs(b) for a, b in zip(losses["packet"], losses["lanes"]))
        means = {m: statistics.fmean(v) for m, v in losses.items()}
        print(f"| {variant} | {med['lanes'][0]:.0f} ({med['lanes'][1]:.0f}) | "
              f"{med['packet'][0]:.0f} ({med['packet'][1]:.0f}) | "
              f"{med['packet'][0] / med['lanes'][0]:.3f} | {drift:.1e} | "
              f"{means['packet'] / means['lanes'] - 1:+.1e} |", flush=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="a synthetic training set (64x64)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--steps", type=int, default=20, help="timed steps per configuration")
    p.add_argument("--variants", nargs="+", default=["baseline", "full"])
    p.add_argument("--clip", type=int, default=0, metavar="N",
                   help="time the gradient norms and clipping alone, N times each")
    p.add_argument("--scatter", action="store_true",
                   help="the training step with the packet backward against the lanes one")
    p.add_argument("--scatter-control", action="store_true",
                   help="with --scatter: both trainers with the lanes backward (the noise)")
    p.add_argument("--awake", choices=["on", "off"],
                   help="one process of train/bench/cores.py: the current trainer with the "
                        "cores kept awake or not; medians per phase as JSON")
    p.add_argument("--torch-first", action="store_true",
                   help="import torch before usplat_dr, as users write (the default imports "
                   "usplat_dr first, which shortens torch's OpenMP spin)")
    args = p.parse_args(argv)
    if args.awake:
        print(json.dumps(awake_medians(args)))
        return 0
    import logging

    import torch

    logging.basicConfig(level=logging.ERROR)
    logging.getLogger("usplat_dr").setLevel(logging.ERROR)

    if args.scatter:
        scatter_ab(args)
        return 0
    if args.clip:
        print(f"threads={args.threads}, medians of {args.clip} calls each (ms)")
        print("| variant | group_grad_norms + clip_grad_norm_ | clip_gradients | ratio |")
        print("|---|---|---|---|")
        for variant in args.variants:
            tr = make_trainer(args.data, variant, args.threads)
            two, one = clip_ab(tr, tr.batches.next(), args.clip)
            print(f"| {variant} | {two:.2f} | {one:.2f} | {one / two:.2f} |")
        return 0
    trainers = {}
    for variant in args.variants:
        for old in (True, False):
            tr = make_trainer(args.data, variant, args.threads)
            if old:
                tr.optimizer = torch.optim.Adam(tr.model.parameters(), lr=1e-3)
            trainers[(variant, old)] = tr
    batches = [next(iter(trainers.values())).batches.next() for _ in range(args.steps + 3)]
    results = {k: [] for k in trainers}
    for i, batch in enumerate(batches):  # interleaved: a busy machine slows all alike
        for (variant, old), tr in trainers.items():
            r = timed_step(tr, batch, old)
            if i >= 3:  # warm-up: kernels compile, allocator settles
                results[(variant, old)].append(r)
    print(f"threads={args.threads}, {args.steps} steps per configuration, medians (ms); "
          f"CPU = process CPU time")
    print("| variant | trainer | " + " | ".join(PHASES) + " | steps/s | CPU ms/step |")
    print("|---|---|" + "---|" * (len(PHASES) + 2))
    for (variant, old), rs in results.items():
        med = {ph: 1000 * statistics.median(r["wall"][ph] for r in rs) for ph in PHASES}
        cpu = 1000 * statistics.median(r["cpu"]["total"] for r in rs)
        print(f"| {variant} | {'previous' if old else 'current'} | "
              + " | ".join(f"{med[ph]:.1f}" for ph in PHASES)
              + f" | {1000 / med['total']:.2f} | {cpu:.0f} |")
    for variant in args.variants:
        old = statistics.median(r["wall"]["total"] for r in results[(variant, True)])
        new = statistics.median(r["wall"]["total"] for r in results[(variant, False)])
        print(f"{variant}: current / previous = {new / old:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
