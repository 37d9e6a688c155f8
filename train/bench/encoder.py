"""Primary-network (MVSplat encoder) forward time and peak memory: 2 views at 256x256, batch 1,
2 threads (``--threads``), ``inference_mode``, the RealEstate10K configuration with random weights.

Each configuration runs in its own process (so its peak RSS is its own), interleaved
``--rounds`` times; each process times ``--repeats`` forwards after one warm-up
(``usplat_dr.evaluation.timing.interleaved``, this checkout's) and reports the median wall time,
process CPU time per forward, peak RSS and the line naming the machine (printed with the
table). Baseline, measured in the same run: our network with the reference's plane sweep
(``cost_volume_method="warp"`` with all 128 candidates warped at once, i.e. the full warped
feature volume the official code builds).
Then the default one under bfloat16 autocast (the model's ``inference_precision =
"bfloat16"``), the default one under other allocator settings (environment variables), and,
with ``--previous DIR``, the default one with the code of an earlier checkout (ratios against
the previous code in the same run).
The official code's numbers on another 2-core machine (docs/mvsplat_notes.md sec. 2) are printed
for reference: 4.9 s, 1.7 GiB.

    python train/bench/encoder.py [--rounds 2] [--repeats 3] [--size 256] [--previous DIR]
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

#: This checkout's timing helper, loaded from its file in every measuring process (``timing``).
TIMING = Path(__file__).resolve().parents[2] / "usplat_dr" / "evaluation" / "timing.py"

CONFIGS = {
    "baseline: full warped volume": {"cost_volume_method": "warp", "cost_volume_chunk": 128},
    "ours: warp, 16-candidate chunks": {"cost_volume_method": "warp", "cost_volume_chunk": 16},
    "ours (default): gram": {},
    # bfloat16 autocast (UniqueSplat.inference_precision = "bfloat16"; not a config field)
    "ours: gram, bfloat16 autocast": {"_precision": "bfloat16"},
    # glibc/torch allocator settings (environment of the measuring process, not a config
    # field): torch's 2 MiB-aligned, huge-page-advised allocations of >= 2 MiB, and glibc's
    # mmap threshold fixed at 16 MiB (the default moves up to 32 MiB and then keeps every
    # smaller tensor in a heap that fragments)
    "ours: gram, THP + 16 MiB mmap threshold": {
        "_env": {"THP_MEM_ALLOC_ENABLE": "1", "MALLOC_MMAP_THRESHOLD_": str(16 * 2**20)}},
}


def timing():
    """This checkout's ``usplat_dr.evaluation.timing``, loaded from its file (it needs only the
    standard library): a ``--previous`` process imports that checkout's usplat_dr, which may
    predate the helper (2026-11-27) or time differently, and every configuration of a run must
    be timed alike."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("usplat_bench_timing", TIMING)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # the dataclass decorator looks its module up
    spec.loader.exec_module(module)
    return module


def child(cfg: dict, size: int, repeats: int, out: str, threads: int) -> None:
    import contextlib
    import resource

    import torch

    import usplat_dr
    from usplat_dr.model import PrimaryNetwork, PrimaryNetworkCfg

    torch.set_num_threads(threads)
    precision = cfg.pop("_precision", "float32")
    cfg.pop("_env", None)
    autocast = (torch.autocast("cpu", dtype=torch.bfloat16) if precision == "bfloat16"
                else contextlib.nullcontext())
    torch.manual_seed(0)
    net = PrimaryNetwork(PrimaryNetworkCfg.from_dict(cfg)).eval()
    e = torch.eye(4).repeat(1, 2, 1, 1)
    e[0, 1, 0, 3] = 0.1
    k = torch.tensor([[0.86, 0, 0.5], [0, 0.86, 0.5], [0, 0, 1]]).repeat(1, 2, 1, 1)
    x = torch.rand(1, 2, 3, size, size, generator=torch.Generator().manual_seed(1))
    args = (x, e, k, torch.ones(1, 2), 100 * torch.ones(1, 2))
    # (each forward runs while the previous one's Gaussians are still held, as in an
    # evaluation loop: ~60 MiB at 256x256)
    held = [None]
    helper = timing()

    def forward():
        held[0] = net(*args)

    with torch.inference_mode(), autocast:
        t = helper.interleaved({"forward": forward}, repeats, warmup=1)["forward"]
    torch.save(held[0].means, out + ".means.pt")
    with open(out, "w") as f:
        json.dump({"wall": t.wall / 1e3, "cpu": t.cpu / 1e3,
                   "rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
                   "package": os.path.dirname(usplat_dr.__file__),
                   "machine": helper.machine_line()}, f)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--threads", type=int, default=2, help="torch threads")
    ap.add_argument("--previous", metavar="DIR",
                    help="also measure the default configuration with the usplat_dr of DIR (a "
                         "checkout of earlier code, e.g. `git worktree add DIR COMMIT`)")
    ap.add_argument("--child", help=argparse.SUPPRESS)  # internal: one measurement
    ap.add_argument("--child-out", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        cfg, out = json.loads(args.child), args.child_out
        return child(cfg, args.size, args.repeats, out, args.threads)
    import torch

    configs = dict(CONFIGS)
    if args.previous:
        prev = os.path.abspath(args.previous)
        if not os.path.isdir(os.path.join(prev, "usplat_dr")):
            raise SystemExit(f"--previous {args.previous}: no usplat_dr package there; make one "
                             f"with `git worktree add {args.previous} COMMIT`")
        configs[f"previous code ({args.previous}): gram"] = {"_pythonpath": prev}
    results = {name: [] for name in configs}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for i, (name, cfg) in enumerate(configs.items()):
                out = f"{tmp}/{i}.json"
                cfg = dict(cfg)
                env = {**os.environ, **cfg.get("_env", {})}
                if "_pythonpath" in cfg:  # earlier code first on the path
                    env["PYTHONPATH"] = os.pathsep.join(
                        [cfg.pop("_pythonpath"), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
                subprocess.run([sys.executable, __file__, "--size", str(args.size),
                                "--repeats", str(args.repeats), "--threads", str(args.threads),
                                "--child", json.dumps(cfg),
                                "--child-out", out], check=True, env=env)
                with open(out) as f:
                    results[name].append(json.load(f))
                if r == 0:
                    results[name][-1]["means"] = torch.load(out + ".means.pt")
        ref_means = results["baseline: full warped volume"][0]["means"]
        base_wall = min(x["wall"] for x in results["baseline: full warped volume"])
        base_rss = min(x["rss_gib"] for x in results["baseline: full warped volume"])
        print(results["baseline: full warped volume"][0]["machine"])  # a measuring process's
        print(f"encoder forward, 2 views {args.size}x{args.size}, batch 1, {args.threads} "
              f"thread(s), best of "
              f"{args.rounds} processes (median of {args.repeats} forwards each)")
        for name, runs in results.items():
            wall = min(x["wall"] for x in runs)
            cpu = min(x["cpu"] for x in runs)
            rss = min(x["rss_gib"] for x in runs)
            diff = (runs[0]["means"] - ref_means).abs().max().item()
            if name.startswith("previous"):
                print(f"  (the previous code imported from {runs[0]['package']})")
            print(f"{name:40s} wall {wall:5.2f} s ({wall / base_wall:4.2f}x)  cpu {cpu:5.2f} s  "
                  f"peak RSS {rss:4.2f} GiB ({rss / base_rss:4.2f}x)  "
                  f"max |means - baseline| {diff:.2g}")
        print("official MVSplat code (docs/mvsplat_notes.md sec. 2, another 2-core machine): "
              "4.9 s, 1.7 GiB; target <= 4.0 s and <= 1.0 GiB")


if __name__ == "__main__":
    main()
