"""glibc's allocator and a training step: a few steps of ``usplat train`` with the allocator as
it is and with blocks kept in the heap (``MALLOC_MMAP_THRESHOLD_`` and
``MALLOC_TRIM_THRESHOLD_`` at 4 GiB), each in its own process (glibc reads them at start),
alternating variant by variant over ``--rounds``. Per variant: the median seconds a step (wall,
from ``metrics.csv``'s ``time_s``; process CPU from its ``cpu_s``; the first step, which loads
and compiles, left out), the process's user and system CPU seconds, and whether the weights
after the last step equal the baseline's bit for bit (the allocator moves memory, not numbers).

    python train/bench/allocator.py --rounds 2 --steps 4 -- \\
        --config synthetic_tiny_depth.yaml 'dataset.roots=[outputs/big128/train480]' \\
        'dataset.image_shape=[128,128]' threads=1 data_loader.batch_size=8 \\
        model.init_from=tiny_baseline model.variant=full

Everything after ``--`` is passed to ``usplat train`` (``train.steps``, ``output_dir``,
``train.log_every`` and the validation are set here).
"""

import argparse
import csv
import hashlib
import itertools
import os
import resource
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

#: Larger than any tensor of these runs: every block stays in glibc's heap, and the heap's top
#: is not given back between steps.
KEEP = str(4 * 2**30)
VARIANTS = {"glibc as it is": {},
            "heap kept (mmap and trim thresholds 4 GiB)": {"MALLOC_MMAP_THRESHOLD_": KEEP,
                                                            "MALLOC_TRIM_THRESHOLD_": KEEP}}


def weights_digest(path: Path) -> str:
    """sha256 over the checkpoint's model tensors, by name."""
    import torch

    state = torch.load(path, map_location="cpu", weights_only=True)
    h = hashlib.sha256()
    for name, t in sorted(state["model"].items()):
        h.update(name.encode())
        h.update(t.detach().contiguous().numpy().tobytes())
    return h.hexdigest()


def one_run(train_args: list[str], env: dict, steps: int, out: Path) -> dict:
    """One ``usplat train`` process: its steps' wall and CPU seconds, its user and system CPU
    seconds, and the digest of its last weights."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    cmd = [sys.executable, "-m", "usplat_dr", "train", *train_args, f"train.steps={steps}",
           "train.log_every=1", "train.progress=false", f"train.validate_every={10**9}",
           f"output_dir={out}"]
    subprocess.run(cmd, env={**os.environ, **env}, check=True, stdout=subprocess.DEVNULL)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    with open(out / "metrics.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["time_s"]]
    wall = [float(b["time_s"]) - float(a["time_s"]) for a, b in itertools.pairwise(rows)]
    cpu = [float(b["cpu_s"]) - float(a["cpu_s"]) for a, b in itertools.pairwise(rows)]
    return {"wall": wall, "cpu": cpu, "user": after.ru_utime - before.ru_utime,
            "sys": after.ru_stime - before.ru_stime,
            "digest": weights_digest(out / "checkpoints" / "last.ckpt")}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ours, train_args = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv \
        else (argv, [])
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=2, help="runs of each variant, alternating")
    p.add_argument("--steps", type=int, default=4, help="training steps a run (>= 3)")
    args = p.parse_args(ours)
    if args.steps < 3:
        p.error("--steps must be at least 3 (the first step is left out of the medians)")
    if not train_args:
        p.error("give usplat train's arguments after --")
    from usplat_dr.evaluation.timing import machine_line  # the standard library only

    print(machine_line(), flush=True)
    found = {name: [] for name in VARIANTS}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            order = list(VARIANTS) if r % 2 == 0 else list(reversed(VARIANTS))
            for i, name in enumerate(order):
                run = one_run(train_args, VARIANTS[name], args.steps, Path(tmp) / f"{r}_{i}")
                found[name].append(run)
                print(f"round {r + 1} {name}: steps {' '.join(f'{w:.1f}' for w in run['wall'])}"
                      f" s, user {run['user']:.0f} s, system {run['sys']:.0f} s", flush=True)
    base = next(iter(VARIANTS))
    digest = found[base][0]["digest"]
    base_wall = statistics.median(w for run in found[base] for w in run["wall"])
    print("| allocator | s a step (wall) | CPU s a step | user s | system s | vs as it is | "
          "weights as the baseline's |")
    print("|---|---|---|---|---|---|---|")
    for name, runs in found.items():
        wall = statistics.median(w for run in runs for w in run["wall"])
        cpu = statistics.median(c for run in runs for c in run["cpu"])
        same = all(run["digest"] == digest for run in runs)
        user = statistics.median(r["user"] for r in runs)
        system = statistics.median(r["sys"] for r in runs)
        print(f"| {name} | {wall:.1f} | {cpu:.1f} | {user:.0f} | {system:.0f} | "
              f"{base_wall / wall:.2f}x | "
              f"{'bit for bit' if same else 'DIFFERENT'} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
