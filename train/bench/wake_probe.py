"""The core keeper's start-up probe (``usplat_dr.training.cores.probe_wake_latency``) on this
machine: how long an idle core takes to wake a blocked thread, with the cores left to halt and
with them kept awake (``CoreKeeper``), at the probe's idle gaps and at gaps shorter than a KVM
guest's halt polling (a script, not a test; run it on a quiet machine: a busy core never
halts, so a loaded machine reads as fast).

Where idle vCPUs halt, the first row reads above ``WAKE_THRESHOLD_US`` and the keeper's row
well below it (its spinners keep the core running, so the wake is a preemption); on bare metal
all rows read alike. Alternated round by round; medians over rounds of each probe's median.

    python train/bench/wake_probe.py --rounds 10
"""

import argparse
import statistics
import sys

from usplat_dr.training import cores


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rounds", type=int, default=10)
    p.add_argument("--wakes", type=int, default=cores.PROBE_ROUNDS, help="wake-ups per probe")
    args = p.parse_args(argv)
    gaps = {"probe's (ms)": cores.PROBE_GAPS_MS, "short (ms)": (0.05, 0.1)}
    rows = {(g, awake): [] for g in gaps for awake in ("halts", "kept awake")}
    for r in range(args.rounds):
        for (g, awake), medians in rows.items():
            keeper = cores.CoreKeeper().start() if awake == "kept awake" else None
            try:
                probe = cores.probe_wake_latency(rounds=args.wakes, gaps_ms=gaps[g])
            finally:
                if keeper is not None:
                    keeper.stop()
            if probe is None:
                sys.exit("the probe could not run here (not Linux, or one CPU)")
            medians.append(probe.median_us)
        print(f"round {r + 1}/{args.rounds}: " + ", ".join(
            f"{g} {awake} {m[-1]:.0f} us" for (g, awake), m in rows.items()), flush=True)
    print(f"\nhypervisor flag: {cores.hypervisor()}, cpuidle driver: {cores.cpuidle_driver()}, "
          f"threshold {cores.WAKE_THRESHOLD_US:.0f} us")
    print("| gaps | cores | median wake-up (us) | rounds' medians |")
    print("|---|---|---|---|")
    for (g, awake), m in rows.items():
        print(f"| {g} {','.join(map(str, gaps[g]))} | {awake} | {statistics.median(m):.0f} | "
              f"{min(m):.0f}-{max(m):.0f} |")
    on, why = cores.decide("auto", len(cores.available_cpus()), "cpu")
    print(cores.log_line(on, why))
    return 0


if __name__ == "__main__":
    sys.exit(main())
