"""Inference time per scene of UniqueSplat's variants (a) baseline, (b) agnostic, (c) full:
2 context views, 3 target views, batch 1, 2 threads, ``inference_mode``, random weights.

Two timings per variant: the model (encoder once, Gaussians for every target) and the model
plus rendering the 3 targets with the Dr.Jit rasteriser (LLVM on ``--device cpu``, CUDA on
``--device cuda``, where each call ends with ``torch.cuda.synchronize``). Times: one process
builds all variants and alternates them run by run, the order reversed every other run (a, b,
c, c, b, a, ...: ``usplat_dr.evaluation.timing.interleaved``), so machine load hits them alike;
``--processes`` such processes, the best median reported, under the timing process's line
naming the machine. Memory: on a CPU the peak RSS of one process per variant; on a GPU, per
variant, its weights plus the peak the torch allocator reached above what was allocated before
one call, after the timed runs (every variant's weights stay resident in the timing process;
Dr.Jit's own CUDA memory is not counted).
Ratios are against (a) measured in the same run. The paper (A6000):
(c)/(a) = 65.2 / 48.5 = 1.34, (b)/(a) = 1.002. (c) is the default model: W + Delta W on the
four convolutions of both heads; ``--layers`` adds (c) with Delta W on fewer layers and with
a full-rank Delta W, the cost of each choice.

    python train/bench/uniquesplat.py [--processes 2] [--repeats 5] [--setting paper256 tiny64]
        [--layers] [--threads 1] [--device cpu|cuda]
"""

import argparse
import json
import subprocess
import sys
import tempfile
from functools import partial

VARIANTS = {"(a) baseline": ("baseline", {}), "(b) agnostic": ("agnostic", {}),
            "(c) full": ("full", {})}
#: ``--layers``: (c) with Delta W on fewer layers (W from H_a on all four in every row), to
#: price each layer choice against the default (both heads' four convolutions).
LAYER_CHOICES = {
    "(c) Delta W on to_gaussians.2 only": ("full", {"specific_layers": ["to_gaussians.2"]}),
    "(c) Delta W on the Gaussian head": (
        "full", {"specific_layers": ["to_gaussians.0", "to_gaussians.2"]}),
    "(c) Delta W on the disparity head": (
        "full", {"specific_layers": ["to_disparity.0", "to_disparity.2"]}),
    "(c) full-rank Delta W": ("full", {"delta_rank": None}),
}
SETTINGS = {"paper256": ("paper", 256), "tiny64": ("tiny", 64), "paper64": ("paper", 64)}


def scene(size: int, device: str = "cpu"):
    import torch

    from usplat_dr.data.types import SceneInputs

    e = torch.eye(4).repeat(1, 2, 1, 1)
    e[0, 1, 0, 3] = 0.1
    k = torch.tensor([[0.86, 0, 0.5], [0, 0.86, 0.5], [0, 0, 1]]).repeat(1, 2, 1, 1)
    te = torch.eye(4).repeat(1, 3, 1, 1)
    te[0, :, 0, 3] = torch.tensor([0.025, 0.05, 0.075])
    x = torch.rand(1, 2, 3, size, size, generator=torch.Generator().manual_seed(1))
    args = SceneInputs.of(images=x, extrinsics=e, intrinsics=k, near=torch.ones(1, 2),
                       far=100 * torch.ones(1, 2), target_extrinsics=te,
                       target_intrinsics=k[:, :1].expand(1, 3, 3, 3),
                       target_near=torch.ones(1, 3), target_far=100 * torch.ones(1, 3))
    return args.to(device)


def build(preset: str, variant: str, overrides: dict):
    import torch

    from usplat_dr.model import UniqueSplat

    torch.manual_seed(0)
    overrides = {k: tuple(v) if isinstance(v, list) else v for k, v in overrides.items()}
    return UniqueSplat.from_preset(preset, variant=variant, **overrides).eval()


def synchronize(device: str) -> None:
    import torch

    if device == "cuda":
        torch.cuda.synchronize()


def cuda_peak_gib(model, args) -> float:
    """The model's weights plus the peak the torch allocator reached above what was allocated
    before one call with rendering, GiB."""
    import torch

    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    before = torch.cuda.memory_allocated()
    model(*args, render=True)
    torch.cuda.synchronize()
    weights = sum(p.numel() * p.element_size() for p in model.parameters())
    return (torch.cuda.max_memory_allocated() - before + weights) / 2**30


def child_times(preset: str, size: int, configs: dict, device: str, repeats: int,
                out: str) -> None:
    import torch

    from usplat_dr.evaluation.timing import interleaved, machine_line

    models = {name: build(preset, *cfg).to(device) for name, cfg in configs.items()}
    args = scene(size, device)
    result = {name: {"params": sum(p.numel() for p in m.parameters())}
              for name, m in models.items()}

    def call(model, render):
        model(*args, render=render)
        synchronize(device)

    with torch.inference_mode():
        for render in (False, True):
            key = "render" if render else "model"
            # warm-up: oneDNN primitives, the rasteriser's kernels
            times = interleaved({name: partial(call, m, render) for name, m in models.items()},
                                repeats, warmup=2)
            for name, t in times.items():
                result[name][key] = {"wall": t.wall / 1e3, "cpu": t.cpu / 1e3}
        if device == "cuda":  # one process is enough on a GPU
            for name, m in models.items():
                result[name]["gib"] = cuda_peak_gib(m, args)
    with open(out, "w") as f:
        json.dump({"machine": machine_line(), **result}, f)


def child_memory(preset: str, size: int, cfg: list, out: str) -> None:
    """Peak RSS of one variant on the CPU (on a GPU, ``child_times`` reads the memory)."""
    import resource

    import torch

    model = build(preset, *cfg)
    with torch.inference_mode():
        model(*scene(size), render=True)
    with open(out, "w") as f:
        json.dump({"rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}, f)


def run_child(mode: str, payload: list, repeats: int, out: str, threads: int = 2) -> dict:
    subprocess.run([sys.executable, __file__, "--repeats", str(repeats), "--threads",
                    str(threads), "--child", mode, "--payload", json.dumps(payload + [out])],
                   check=True)
    with open(out) as f:
        return json.load(f)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--setting", nargs="+", default=["paper256", "tiny64"],
                    choices=sorted(SETTINGS))
    ap.add_argument("--layers", action="store_true",
                    help="also (c) with Delta W on fewer layers, and full rank")
    ap.add_argument("--threads", type=int, default=2,
                    help="torch and Dr.Jit threads (1: how training runs, and a fair "
                         "measurement while another one-thread job holds the other core)")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                    help="cpu: torch on CPU, the LLVM rasteriser; cuda: both on the GPU")
    ap.add_argument("--child", help=argparse.SUPPRESS)  # internal: one measurement
    ap.add_argument("--payload", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.threads < 1:
        ap.error(f"--threads must be >= 1, got {args.threads}")
    import logging

    logging.disable(logging.WARNING)  # the ResNet18 random-initialisation warning
    if args.child:
        import torch

        import usplat_dr  # noqa: F401  (points Dr.Jit at libLLVM before drjit is imported)

        # isort: split
        import drjit as dr

        torch.set_num_threads(args.threads)
        dr.set_thread_count(args.threads)
        payload = json.loads(args.payload)
        if args.child == "times":
            return child_times(*payload[:4], args.repeats, payload[4])
        return child_memory(*payload)

    configs = {**VARIANTS, **(LAYER_CHOICES if args.layers else {})}
    for setting in args.setting:
        preset, size = SETTINGS[setting]
        with tempfile.TemporaryDirectory() as tmp:
            runs = [run_child("times", [preset, size, configs, args.device], args.repeats,
                              f"{tmp}/t{i}.json", args.threads)
                    for i in range(args.processes)]
            if args.device == "cuda":  # the allocator's peak, read in the timing process
                rss = {name: max(r[name]["gib"] for r in runs) for name in configs}
            else:  # RSS: one process per variant (its own peak)
                rss = {name: run_child("memory", [preset, size, list(cfg)], 0,
                                       f"{tmp}/m.json", args.threads)["rss_gib"]
                       for name, cfg in configs.items()}
        where = (f"{args.threads} thread(s)" if args.device == "cpu"
                 else f"CUDA ({torch_device_name()})")
        memory = "peak RSS" if args.device == "cpu" else "peak torch CUDA memory"
        print(f"\n{preset} preset, {size}x{size}, 2 context + 3 targets, batch 1, "
              f"{where}; variants alternated run by run, best of "
              f"{args.processes} processes (median of {args.repeats} runs each)")
        print(runs[0]["machine"])  # the first timing process's

        def best(name, key, what, runs=runs):  # B023: this iteration's values
            return min(r[name][key][what] for r in runs)

        base = {key: best("(a) baseline", key, "wall") for key in ("model", "render")}
        for name in configs:
            cells = [f"{key}: wall {best(name, key, 'wall'):6.3f} s "
                     f"({best(name, key, 'wall') / base[key]:4.2f}x) cpu "
                     f"{best(name, key, 'cpu'):6.3f} s" for key in ("model", "render")]
            print(f"  {name:38s} {runs[0][name]['params'] / 1e6:6.2f}M params  "
                  + "  |  ".join(cells) + f"  {memory} {rss[name]:4.2f} GiB")
        print("  the paper on a GPU: (c)/(a) 1.34, (b)/(a) 1.002")


def torch_device_name() -> str:
    import torch

    return torch.cuda.get_device_name(0)


if __name__ == "__main__":
    main()
