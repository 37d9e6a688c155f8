"""Throughput of ``usplat synth`` (scenes per minute, 24 frames) on this machine.

Baseline, measured in the same run and interleaved: Mitsuba rendering the same scenes' colour
images alone (no depth tracing, materials, PNG encoding, splits or chunk writing), so the ratio
is the cost of everything around the renderer. Prints wall and process CPU time
(``usplat_dr.evaluation.timing.interleaved``: after a warm-up round, the best wall time and the
median CPU time of two rounds, the second in reverse order) under a line naming the machine.

    python train/bench/synth.py [--scenes 6] [--target [--jobs 2]]
"""

import argparse
import tempfile
from functools import partial

import numpy as np

from usplat_dr.data.synth import scene_seed, synthesize
from usplat_dr.data.synth.render import mitsuba_dict, set_variant
from usplat_dr.data.synth.scenes import KINDS, make_spec
from usplat_dr.evaluation.timing import interleaved, machine_line


def render_only(scenes: int, frames: int, res, spp: int = 64) -> None:
    mi = set_variant("llvm")
    for i in range(scenes):
        spec = make_spec(KINDS[i % 3], scene_seed(0, i), frames)
        scene = mi.load_dict(mitsuba_dict(spec, res, spp))
        for s in scene.sensors():
            np.array(mi.render(scene, sensor=s, spp=spp))


def synth_set(tmp: str, scenes: int, frames: int, res, **kwargs) -> None:
    """``usplat synth``'s work: a new set in a new folder under ``tmp``."""
    synthesize(tempfile.mkdtemp(dir=tmp), scenes, frames, res, progress=False, **kwargs)


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
    print(machine_line())
    for res in [(64, 64), (128, 128)]:
        with tempfile.TemporaryDirectory() as tmp:
            rows = interleaved({"synth": partial(synth_set, tmp, n, f, res, previews=0),
                                "mitsuba only": partial(render_only, n, f, res)},
                               rounds=2, warmup=1)  # the first set's call is cold
        base = rows["mitsuba only"].best / 1e3
        for name, t in rows.items():
            w, c = t.best / 1e3, t.cpu / 1e3
            print(f"{res[0]}x{res[1]} {f} frames  {name:13s} {60 * n / w:6.1f} scenes/min  "
                  f"wall {w / n:5.2f} s/scene  cpu {c / n:5.2f} s/scene  "
                  f"{w / base:4.2f}x mitsuba-only")
    if args.target:  # one run per process count (minutes each)
        jobs = list(dict.fromkeys((1, args.jobs)))
        with tempfile.TemporaryDirectory() as tmp:
            runs = interleaved({f"jobs={j}": partial(synth_set, tmp, 32, 24, (64, 64), jobs=j)
                                for j in jobs}, rounds=1, warmup=0)
        for j in jobs:
            w, c = runs[f"jobs={j}"].wall / 1e3, runs[f"jobs={j}"].cpu / 1e3
            print(f"32 scenes x 24 frames 64x64, jobs={j}: wall {w:.0f} s (target <= 180 s), "
                  f"cpu of this process {c:.0f} s, {runs['jobs=1'].wall / 1e3 / w:.2f}x jobs=1")


if __name__ == "__main__":
    main()
