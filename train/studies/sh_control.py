"""Does a set need view-dependent colour? (a) fine-tuned on it with spherical harmonics of
degree 2 (each Gaussian's colour may change with the viewing direction, as trained) against
the same with degree 0 (one colour per Gaussian: ``PrimaryNetworkCfg.colour_sh_degree = 0``),
from the same checkpoint for the same steps and seeds; PSNR on the held-out set's shiny and
matte pixels, paired by scene (``usplat_dr.evaluation.verdict``).

    python train/studies/sh_control.py --init checkpoints/tiny_baseline.pt \\
        --data outputs/big/vd_train120 --eval-data outputs/big/vd_test2000 \\
        --steps 1000 --seeds 0 --out outputs/sh_control

Both arms run at once, one thread each, through ``train/studies/verdict_study.py`` (resumable:
``<out>/sh2`` and ``<out>/sh0``); writes ``<out>/sh_control.md`` and ``.json`` (degree 0 minus
degree 2 per split and metric, with both intervals). On a view-dependent set degree 0 should
lose on shiny pixels and not on matte ones.
"""

import argparse
import subprocess
import sys
from contextlib import ExitStack
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--init", required=True, help="the trained (a) both arms start from")
    p.add_argument("--data", required=True, help="training set root")
    p.add_argument("--eval-data", required=True, help="held-out synthetic set root")
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--out", default="outputs/sh_control")
    args = p.parse_args(argv)
    out = Path(args.out)
    common = [sys.executable, str(HERE / "verdict_study.py"), "--init", args.init, "--data",
              args.data, "--eval-data", args.eval_data, "--steps", str(args.steps),
              "--variants", "baseline", "--jobs", "1", "--seeds", *map(str, args.seeds)]
    arms = {"sh2": [], "sh0": ["--model-override", "primary.colour_sh_degree=0"]}
    procs = {}
    with ExitStack() as logs:
        for arm, extra in arms.items():
            (out / arm).mkdir(parents=True, exist_ok=True)
            log = logs.enter_context(open(out / f"{arm}.log", "a"))
            procs[arm] = subprocess.Popen([*common, "--out", str(out / arm), *extra],
                                          stdout=log, stderr=log)
        failed = [arm for arm, proc in procs.items() if proc.wait() != 0]
    if failed:
        raise SystemExit(f"arms {failed} failed: see {out}/<arm>.log")

    from usplat_dr.evaluation.verdict import METRICS, as_dicts, compare, table
    from usplat_dr.io import write_json

    def csvs(arm):
        return [out / arm / f"baseline_seed{s}" / "eval" / "per_scene.csv" for s in args.seeds]

    rows = compare({"baseline": csvs("sh2"), "sh0": csvs("sh0")},
                   metrics={**METRICS, "psnr_matte": True})
    write_json(out / "sh_control.json", {"args": vars(args), "rows": as_dicts(rows)})
    text = (f"(a) with SH degree 0 minus (a) with SH degree 2, fine-tuned from `{args.init}` on "
            f"`{args.data}` for {args.steps} steps, held-out `{args.eval_data}`\n\n"
            + table(rows, rule=False) + "\n")
    (out / "sh_control.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
