"""Throughput of ``usplat synth`` (scenes per minute, 24 frames) on this machine.

Baseline, measured in the same run and interleaved: Mitsuba rendering the same scenes' colour
images alone (no depth tracing, materials, PNG encoding, splits or chunk writing), so the ratio
is the cost of everything around the renderer. Prints wall and process CPU time.

    python train/bench/synth.py [--scenes 6] [--target [--jobs 2]]
"""

import argparse
import tempfile
import time

import numpy as np

from usplat_dr.data.synth import scene_seed, synthesize
from usplat_dr.data.synth.render import mitsuba_dict, set_variant
from usplat_dr.data.synth.scenes import KINDS, make_spec


def render_only(scenes: int, frames: int, res, spp: int = 64) -> None:
    mi = set_variant("llvm")
    for i in range(scenes):
        spec = make_spec(KINDS[i % 3], scene_seed(0, i), frames)
        scene = mi.load_dict(mitsuba_dict(spec, res, spp))
        for s in scene.sensors():
            np.array(mi.render(scene, sensor=s, spp=spp))


def timed(fn) -> tuple[float, float]:
    w, c = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - w, time.process_time() - c


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", type=int, default=6)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--target", action="store_true",
                    help="also time the 32-scene, 24-frame, 64x64 set (target <= 3 min)")
    ap.add_argument("--jobs", type=int, default=2,
                    help="worker processes for the second timing of the target set")
    args = ap.parse_args()
    n, f = args.scenes, args.frames
    render_only(1, 2, (16, 16))  # warm up: compile kernels once
    for res in [(64, 64), (128, 128)]:
        rows = {"synth": [], "mitsuba only": []}
        for _ in range(2):  # interleaved
            with tempfile.TemporaryDirectory() as d:
                rows["synth"].append(timed(lambda: synthesize(d, n, f, res, progress=False,  # noqa: B023 (called in this iteration)
                                                              previews=0)))
            rows["mitsuba only"].append(timed(lambda: render_only(n, f, res)))  # noqa: B023 (called in this iteration)
        base = min(w for w, _ in rows["mitsuba only"])
        for name, runs in rows.items():
            w = min(r[0] for r in runs)
            c = min(r[1] for r in runs)
            print(f"{res[0]}x{res[1]} {f} frames  {name:13s} {60 * n / w:6.1f} scenes/min  "
                  f"wall {w / n:5.2f} s/scene  cpu {c / n:5.2f} s/scene  "
                  f"{w / base:4.2f}x mitsuba-only")
    if args.target:
        walls = {}
        for jobs in (1, args.jobs):
            with tempfile.TemporaryDirectory() as d:
                w, c = timed(lambda: synthesize(d, 32, 24, (64, 64), progress=False, jobs=jobs))  # noqa: B023 (called in this iteration)
            walls[jobs] = w
            print(f"32 scenes x 24 frames 64x64, jobs={jobs}: wall {w:.0f} s (target <= 180 s), "
                  f"cpu of this process {c:.0f} s, {walls[1] / w:.2f}x jobs=1")


if __name__ == "__main__":
    main()
