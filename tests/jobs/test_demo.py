"""``usplat demo --quick`` end to end, run from a wheel install: the package built as a wheel
(not editable), installed into a folder of its own, and run from another directory by a Python
that cannot see the repository; then the report, the CLI's video and PLY export of its
fine-tuned model, and ``usplat bench`` reusing its runs."""

import csv
import dataclasses
import json
import math
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from usplat_dr.training.checkpoints import SHIPPED

ROOT = Path(__file__).parents[2]


@pytest.fixture(scope="module")
def wheel_demo(tmp_path_factory) -> Path:
    """The output folder of ``usplat demo --quick`` run from a wheel install.

    ``python -S`` skips site-packages' ``.pth`` files, so the editable install of the test
    environment (a finder that maps ``usplat_dr`` to this repository) is not active: the
    dependencies come from the test environment's site-packages, given on ``PYTHONPATH`` after
    the wheel's folder, and ``usplat_dr`` can only come from the wheel."""
    tmp = tmp_path_factory.mktemp("wheel")
    # Built from a copy: setuptools reuses a source tree's build/ folder, where modules moved
    # or deleted since an earlier build would linger and hide a missing package.
    source = tmp / "source"
    shutil.copytree(ROOT, source, symlinks=True, ignore=shutil.ignore_patterns(
        ".git", ".venv", "build", "dist", "*.egg-info", "outputs", "__pycache__", ".*_cache"))
    run = dict(capture_output=True, text=True)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                    "--disable-pip-version-check", "-w", str(tmp / "dist"), str(source)],
                   check=True, **run)
    wheel, = (tmp / "dist").glob("usplat_dr-*.whl")
    site = tmp / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--target", str(site),
                    "--disable-pip-version-check", str(wheel)], check=True, **run)
    deps = sorted({sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]})
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), *deps])}
    elsewhere = tmp / "elsewhere"  # not the repository: nothing is read relative to it
    elsewhere.mkdir()
    out = tmp / "demo"
    # the console script the wheel installs (`usplat`), run by this Python without site
    proc = subprocess.run([sys.executable, "-S", str(site / "bin" / "usplat"), "demo",
                           "--quick", "--out", str(out)], cwd=elsewhere, env=env,
                          capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    where = subprocess.run([sys.executable, "-S", "-c",
                            "import usplat_dr; print(usplat_dr.__file__)"],
                           cwd=elsewhere, env=env, check=True, **run).stdout.strip()
    assert Path(where) == site / "usplat_dr" / "__init__.py"
    return out


@pytest.mark.slow
def test_demo_quick_end_to_end(wheel_demo):
    tmp_path = wheel_demo
    text = (tmp_path / "report.md").read_text()
    assert "| (a) primary network `study/tiny_baseline_continued`" in text
    assert "| (c) UniqueSplat `study/tiny_full`" in text
    assert "## Verdict on view conditioning" in text and "| standard | psnr | (c) - (a) |" in text
    assert "pre-registered multi-seed verdict" in text  # checkpoints/verdict.json, from the wheel
    assert (tmp_path / "training_curves.png").is_file() and (tmp_path / "verdict.png").is_file()
    for variant in SHIPPED:
        s = json.loads((tmp_path / f"eval_shipped_{variant}" / "summary.json").read_text())
        assert s["variant"] == variant and math.isfinite(s["splits"]["standard"]["psnr"])
    for variant in ("baseline", "full"):  # the brief fine-tuning from the shipped (a)
        assert (tmp_path / f"train_{variant}" / "checkpoints" / "last.ckpt").is_file()
    assert "sha256" in text and "drjit" in text  # where the numbers came from
    # the live (c)'s meter (whether it reads live at 32x32 is not asserted: it was trained at 64)
    assert "| (c) live (`study/tiny_full_live`" in text
    live = json.loads((tmp_path / "eval_shipped_live" / "summary.json").read_text())
    assert "view_specificity" in live["splits"]["standard"]
    # the (c) trained beyond the context: its meter where the demo's scenes have the split
    beyond = json.loads((tmp_path / "eval_shipped_beyond" / "summary.json").read_text())
    assert "view_specificity" in beyond["splits"]["standard"]
    assert "| (c) trained beyond the context (`full-64`), standard |" in text
    images = [line for line in text.splitlines() if line.startswith("![")]
    assert all((tmp_path / line.split("(")[1].rstrip(")")).is_file() for line in images)

    # the fine-tuned (c) model's video and PLY export through the CLI
    from usplat_dr.cli import main

    ckpt = str(tmp_path / "train_full" / "checkpoints" / "last.ckpt")
    common = ["--checkpoint", ckpt, "--data", str(tmp_path / "data"), "--image-shape", "32",
              "32"]
    assert main(["-q", "render", *common, "--frames", "6", "--out",
                 str(tmp_path / "video")]) == 0
    assert list((tmp_path / "video").glob("video.*"))  # --out is a folder
    assert len(list((tmp_path / "video" / "frames").glob("*.png"))) == 6
    assert main(["-q", "export-ply", *common, "--target", "1", "--out",
                 str(tmp_path / "g.ply")]) == 0
    from usplat_dr.model.ply import read_ply

    assert read_ply(tmp_path / "g.ply")["means"].shape == (2 * 32 * 32, 3)

    # the report's stress, bench and stability sections
    assert "### Worst cases" in text and "## Speed against accuracy" in text
    assert "view-specific H_s" in text  # gradient norms of the hypernetwork branches
    assert "Warning" not in text
    with open(tmp_path / "bench_demo" / "bench.csv") as f:
        rows = list(csv.DictReader(f))
    by = {(r["config"], r["prune"], r["render_size"]): r for r in rows}
    # 2 models x (6 prunings at 32 px + 16 px + 2 Gaussian budgets x learned/dither/opacity/
    # random: the budget stage's add-ons, with their importance head)
    # pruning settings + the half-size render + two budgets x five rankings, per model
    assert len(by) == len(rows) == 2 * (4 + 1 + 2 * 5)
    for ranking in ("learned", "dither", "footprint"):
        kept = float(by[("tiny (c)", f"{ranking}10%", "32")]["kept_fraction"])
        assert abs(kept - round(0.1 * 2048) / 2048) < 1e-9  # K = 205 of 2 x 32 x 32 per view
    assert "## Where the budget goes" in text and "allocation/standard/" in text
    assert "`rank_by=learned`" in text and "tiny_full_budget" in text
    assert "The automatic count (`--gaussians auto`" in text
    with open(tmp_path / "eval_auto_full" / "per_scene.csv") as f:
        auto = list(csv.DictReader(f))
    assert auto and all(0 < float(r["auto_keep"]) <= 1 for r in auto)
    for config in ("tiny (a)", "tiny (c)"):
        # exact culling: same PSNR (float32 summation order only)
        assert abs(float(by[(config, "cull", "32")]["psnr_change_db"])) < 1e-3
        assert float(by[(config, "cull", "32")]["gaussians_per_view"]) <= 2 * 32 * 32

    # `usplat bench` reuses the demo's trained runs (same folder) and adds nothing to train
    assert main(["-q", "bench", "--quick", "--out", str(tmp_path), "--configs",
                 "tiny:a,tiny:c", "--prunes", "all,cull", "--render-sizes", "32"]) == 0
    assert (tmp_path / "bench" / "bench.png").is_file()
    summary = json.loads((tmp_path / "bench" / "summary.json").read_text())
    assert summary["pruning"]["cull"]["safe"]


def test_registered_verdict_lines():
    from usplat_dr.jobs.report import registered_lines

    registered = {"date": "2026-11-25", "rule": "supports if ...", "sets": [
        {"set": "standard (seed 5000)", "arm": "equal steps", "mean": -0.05, "low": -0.1,
         "high": 0.01, "seed_low": -0.2, "seed_high": 0.08, "seeds": 3, "scenes": 60,
         "label": "refutes"},
        {"set": "cross-kind", "label": "not run", "why": "no (a) trained on one kind yet"}]}
    text = "\n".join(registered_lines(registered))
    assert "| standard (seed 5000) | equal steps | -0.050 | [-0.100, +0.010] | [-0.200, +0.080] " \
           "| 3 x 60 | **refutes** | not measured |" in text
    assert "| cross-kind | | | | | | not run: no (a) trained on one kind yet | |" in text
    registered["sets"][0]["branch_live"] = "no (0.0000 dB)"
    registered["note"] = "The labels test the protocol."
    text = "\n".join(registered_lines(registered))
    assert "| 3 x 60 | **refutes** | no (0.0000 dB) |" in text
    assert text.endswith("\n\nThe labels test the protocol.\n")  # the section ends blank
    assert "No multi-seed verdict" in registered_lines(None)[0]


def demo_results(out: Path, stable: dict):
    """A ``DemoResults`` of made-up numbers, with the files ``write_report`` reads."""
    from usplat_dr.evaluation.verdict import Comparison
    from usplat_dr.jobs.report import DemoResults
    from usplat_dr.training.checkpoints import BASE
    from usplat_dr.training.recipes import RECIPES

    (out / "bench_demo").mkdir(parents=True)
    (out / "bench_demo" / "bench.md").write_text("| the demo's bench |\n")
    for variant in ("baseline", "full"):
        renders = out / f"eval_shipped_{variant}" / "renders" / "standard"
        renders.mkdir(parents=True)
        for scene in ("s2", "s0", "s1"):
            (renders / f"{scene}.png").write_bytes(b"")

    def split(psnr):
        return {"psnr": psnr, "ssim": 0.5, "abs_rel": 0.1, "scenes": 3, "psnr_copy": 19.0,
                "psnr_over_copy": psnr - 19.0, "scenes_over_copy": 2}

    summaries = {v: {"parameters": 1.7e6, "time_per_scene_s": 0.12, "peak_memory_gib": 0.5,
                     "splits": {"standard": split(20.0 + i), "wide": split(18.0)}}
                 for i, v in enumerate(["base", *SHIPPED])}
    # the view-specificity meter's summary of (c) (evaluation.view_specificity.Summary)
    summaries["full"]["splits"]["standard"]["view_specificity"] = {
        "scenes": 3, "spread_rel_w": {"to_gaussians.0": 4.2e-6, "to_disparity.0": 1e-6},
        "d_mean_abs": {"mean_db": 0.00005, "low": 0.00003, "high": 0.00007},
        "d_zero": {"mean_db": 0.006, "low": -0.0058, "high": 0.0177}, "live": False}
    manifest = {n: {"name": n, "steps": 100, "sha256": "0123456789abcdef0123", "data": "synth"}
                for n in (BASE, *SHIPPED.values())}
    return DemoResults(
        out=out, recipe=RECIPES["quick"], recipe_name="quick", summaries=summaries,
        timings={"total": 99.6}, worst={"full": {"wide": out / "w.png", "wide_psnr": 14.25}},
        bench={"pruning": {"cull": {"worst_psnr_change_db": -0.001, "kept_fraction": 0.8,
                                    "safe": True}}},
        stable=stable, verdict=[Comparison("standard", "psnr", "full", 0.1, -0.1, 0.3, 3, 1,
                                           0.67)],
        tuned={"full": summaries["full"]}, provenance={"drjit": "1.0", "data": {"d": "abc"}},
        manifest=manifest)


def test_write_report_writes_a_section_each(tmp_path):
    # the report of made-up results, its training sections from a metrics.csv written by the
    # run log (the format's one writer and reader), without the slow demo
    from usplat_dr.jobs.report import write_report
    from usplat_dr.training.run_log import RunLog, curves, stability

    run = tmp_path / "train_full"
    fields = ["step", "loss", "psnr", "grad_norm", "grad_specific", "skipped"]
    with RunLog(run, fields, 0, 8, progress=False) as log:
        for step in range(1, 9):
            log.log(step, {"loss": 1 / step, "psnr": 10 + step, "grad_norm": 0.5,
                           "grad_specific": 0.01 * step}, skipped=int(step > 4))
    stable = {"full": stability(run)}
    assert stable["full"]["steps"] == 8 and stable["full"]["skipped"] == 1
    assert stable["full"]["parts"]["grad_specific"]["max"] == 0.08
    assert curves({"full": run}, tmp_path / "training_curves.png").stat().st_size > 0

    text = write_report(demo_results(tmp_path / "demo", stable)).read_text()
    headings = [line for line in text.splitlines() if line.startswith("#")]
    assert headings == [
        "# usplat-dr demo report", "## Summary", "## What the demo did",
        "## The shipped checkpoints on fresh scenes (standard split)",
        "## Verdict on view conditioning (these scenes, the shipped seed)",
        "## Is (c)'s view-specific branch live? (the view-specificity meter)",
        "## Per split (PSNR / SSIM / depth AbsRel)", "### Worst cases",
        "## Fine-tuning briefly from the shipped (a)", "## Speed against accuracy",
        "## Novel views", "## Where these numbers came from", "## Wall time"]
    assert text.endswith("|---|---|\n| total | 100 |\n")  # one final newline
    assert "\n\n\n" not in text  # sections one blank line apart
    assert "| (c) UniqueSplat | view-specific H_s | 0.045 | 0.08 |" in text
    assert "| wide | 3 | 18.00 / 0.500 / 0.100 |" in text
    assert "| 20.00 | +1.00 dB (19.00; 2 of 3) | 0.500 |" in text  # the margin over copying
    # the meter: the shipped (c) and the fine-tuned one (the same summary here), not live
    assert text.count("| 3 | 4.2e-06 | 0.0001 dB [0.0000, 0.0001] | +0.0060 dB [-0.0058, "
                      "+0.0177] | no |") == 2
    assert "tests the fine-tuning protocol, not weights that depend on the view" in text
    assert "(c) UniqueSplat, wide: w (14.25 dB)\n\n![wide](w.png)" in text
    assert "(a) primary network, s1:\n\n![s1](eval_shipped_baseline/renders/standard/s1.png)" \
        in text and "s2.png" not in text  # the first two renders
    assert "No multi-seed verdict is shipped" in text and "Full `usplat bench`" not in text


def test_the_report_opens_with_a_summary_that_fits_one_screen(tmp_path):
    from usplat_dr.jobs.report import SUMMARY_LINES, write_report
    from usplat_dr.training.checkpoints import CHECKPOINTS

    registered = json.loads((CHECKPOINTS / "verdict.json").read_text())
    results = dataclasses.replace(demo_results(tmp_path / "demo", {}), registered=registered)
    lines = write_report(results).read_text().splitlines()
    end = lines.index("## What the demo did")
    summary = lines[:end]
    assert summary[:3] == ["# usplat-dr demo report", "", "## Summary"]
    assert len(summary) <= SUMMARY_LINES == 40
    text = "\n".join(summary)
    # the models with their margin over copying, the time, the registered question's 4 rows
    assert "| 20.00 | +1.00 dB (19.00; 2 of 3) | 120 ms |" in text
    assert "100 s in all" in text
    rows = [line for line in summary if line.startswith(("| standard", "| extrapolation"))]
    assert len(rows) == 4 and rows[1] == (
        "| extrapolation (1-4 frames beyond) | 64x64 | +0.568 [+0.164, +0.972] | 4 | "
        "**supports** |")


def test_report_shows_the_live_c_meter_and_its_psnr_against_a(tmp_path):
    """The shipped live (c): its meter row (live: yes) beside the others, and a sentence with its
    PSNR against the shipped (a)'s and its signed per-target difference."""
    import dataclasses

    from usplat_dr.jobs.report import meter_lines

    results = demo_results(tmp_path / "demo", {})
    meter = {"scenes": 3, "spread_rel_w": {"to_disparity.0": 1.2e-2},
             "d_mean_abs": {"mean_db": 0.09, "low": 0.06, "high": 0.12},
             "d_mean": {"mean_db": 0.0056, "low": -0.008, "high": 0.019},
             "d_zero": {"mean_db": -0.03, "low": -0.17, "high": 0.11}, "live": True}
    live = {"splits": {"standard": {"psnr": 25.69, "ssim": 0.8, "abs_rel": 0.09, "scenes": 3,
                                    "view_specificity": meter}}}
    text = "\n".join(meter_lines(dataclasses.replace(results, live=live)))
    assert ("| (c) live (`study/tiny_full_live`: E_H reads the primary features) | 3 | 1.2e-02 | "
            "0.0900 dB [0.0600, 0.1200] | -0.0300 dB [-0.1700, +0.1100] | yes |") in text
    assert "renders 25.69 dB against the shipped (a)'s 20.00 dB" in text and "+0.0056 dB" in text
    assert "live (c)" not in "\n".join(meter_lines(results))  # no live summary: no row


def test_report_says_what_the_automatic_count_keeps_and_loses(tmp_path):
    import dataclasses

    from usplat_dr.jobs.report import auto_lines

    results = demo_results(tmp_path / "demo", {})
    auto = {"gaussians": {"auto": {"tolerance_db": 0.2, "merge": True}},
            "splits": {"standard": {"psnr": 21.25, "scenes": 3, "mean_auto_keep": 0.9,
                                    "mean_gaussians_rendered": 1536.0,
                                    "mean_gaussians_total": 2048.0}}}
    text = "\n".join(auto_lines(dataclasses.replace(results, auto=auto)))
    # the shipped (c)'s made-up standard PSNR is 20.0 + 3 (base, baseline, agnostic, full)
    assert ("chose 90% of (c)'s Gaussians per scene on average and rendered 75% after culling "
            "and merging: 21.25 dB against 23.00 dB with all of them (3 scenes") in text
    assert auto_lines(results) == []


def test_report_shows_the_beyond_c_meter_per_split_and_its_psnr_where_it_varies(tmp_path):
    """The (c) trained with extrapolated targets: a meter row per split it was evaluated on,
    and a sentence with its extrapolation PSNR against the shipped (a)'s there."""
    import dataclasses

    from usplat_dr.jobs.report import meter_lines

    results = demo_results(tmp_path / "demo", {})

    def meter(abs_db, signed, live):
        return {"scenes": 4, "spread_rel_w": {"to_disparity.0": 0.13},
                "d_mean_abs": {"mean_db": abs_db, "low": abs_db / 2, "high": abs_db * 1.5},
                "d_mean": {"mean_db": signed, "low": signed - 0.2, "high": signed + 0.2},
                "d_zero": {"mean_db": 2.4, "low": 2.1, "high": 2.7}, "live": live}
    beyond = {"splits": {
        "standard": {"psnr": 25.4, "scenes": 4, "view_specificity": meter(0.03, 0.0, False)},
        "extrapolation": {"psnr": 24.3, "scenes": 4,
                          "view_specificity": meter(1.9, 1.36, True)}}}
    base = {"splits": {**results.summaries["base"]["splits"],
                       "extrapolation": {"psnr": 21.9, "scenes": 4}}}
    summaries = {**results.summaries, "base": base}
    text = "\n".join(meter_lines(dataclasses.replace(results, beyond=beyond,
                                                      summaries=summaries)))
    assert ("| (c) trained beyond the context (`full-64`), extrapolation | 4 | 1.3e-01 | "
            "1.9000 dB [0.9500, 2.8500] | +2.4000 dB [+2.1000, +2.7000] | yes |") in text
    assert "beyond the context (`full-64`), standard | 4 |" in text
    assert "renders 24.30 dB against the shipped (a)'s 21.90 dB" in text and "+1.3600 dB" in text
    assert "full-64" not in "\n".join(meter_lines(results))  # no summary: no row
