"""``usplat bench``'s decisions and measurements on rows and blocks built by hand (the
end-to-end run is in ``test_evaluation.test_demo_quick_end_to_end``)."""

import logging

import pytest
import torch

from usplat_dr.cli import main
from usplat_dr.evaluation.speed import BenchConfig, PeakMemory, budget_settings, choose
from usplat_dr.jobs.bench import configs_argument
from usplat_dr.jobs.report import pareto


def row(config, params, prune, psnr, size=64, change=None, kept=1.0):
    return {"config": config, "parameters": params, "prune": prune, "render_size": size,
            "psnr": psnr, "psnr_change_db": change, "kept_fraction": kept}


def test_choose_applies_the_issue_rules():
    rows = [row("tiny (a)", 3, "all", 20.0), row("small (c)", 10, "all", 20.5),
            row("paper (c)", 38, "all", 20.7), row("tiny (a)", 3, "all", 25.0, size=32),
            row("tiny (a)", 3, "cull", 20.0, change=0.0, kept=0.8),
            row("paper (c)", 38, "cull", 20.7, change=0.0, kept=0.7),
            row("tiny (a)", 3, "cull+merge2px", 19.0, change=-1.0, kept=0.5),
            row("paper (c)", 38, "cull+merge2px", 20.69, change=-0.01, kept=0.5)]
    d = choose(rows, 64)
    # best 20.7 at 64 px (the 25 dB row is another render size); 20.5 is within 0.3 dB, 20.0
    # is not: the smallest within is small (c)
    assert d["best"] == "paper (c)" and d["smallest_within_0.3dB"] == "small (c)"
    assert d["pruning"]["cull"]["safe"] and d["pruning"]["cull"]["kept_fraction"] == 0.75
    # safe only if every configuration loses less than 0.05 dB
    assert not d["pruning"]["cull+merge2px"]["safe"]
    assert d["pruning"]["cull+merge2px"]["worst_psnr_change_db"] == -1.0


def test_pareto_front_by_brute_force():
    g = torch.Generator().manual_seed(0)
    pts = [tuple(p) for p in torch.rand(40, 2, generator=g).tolist()]
    front = set(pareto(pts))
    for i, (x, y) in enumerate(pts):
        dominated = any(x2 <= x and y2 >= y and (x2, y2) != (x, y) for x2, y2 in pts)
        assert (i in front) == (not dominated)


def test_peak_memory_sees_an_allocation():
    with PeakMemory(torch.device("cpu")) as small:
        torch.ones(1000).sum()
    with PeakMemory(torch.device("cpu")) as big:
        x = torch.ones(64 * 2**20 // 4)  # 64 MiB, touched
        x.sum()
        del x
    if big.gib is None:
        pytest.skip("no /proc/self/clear_refs on this system")
    # the 64 MiB block shows (the allocator may reuse freed pages: at least 3/4 of it)
    assert big.gib >= 0.75 * 64 / 1024 and small.gib < big.gib


def test_config_parsing_names_the_choices(capsys):
    assert BenchConfig.parse("tiny:c") == BenchConfig("tiny", "full")
    assert BenchConfig.parse("paper:baseline").label == "paper (a)"
    with pytest.raises(ValueError, match="preset:variant"):
        BenchConfig.parse("huge:c")
    assert configs_argument("none") == ()  # only the --checkpoint models
    assert configs_argument("tiny:a,tiny:c") == (BenchConfig("tiny", "baseline"),
                                                BenchConfig("tiny", "full"))
    assert main(["bench", "--configs", "none", "--out", "unused"]) != 0
    assert "give at least one --checkpoint" in capsys.readouterr().err


def test_gaussians_takes_a_list_of_counts_or_fractions_and_the_old_name_says_so(caplog):
    import argparse

    from usplat_dr.jobs import bench

    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    with caplog.at_level(logging.WARNING, logger="usplat_dr.jobs.arguments"):
        assert parser.parse_args(["--gaussians", "0.1,5000,30%"]).gaussians == (0.1, 5000, 0.3)
        assert not caplog.records
        assert parser.parse_args(["--fractions", "0.1,0.3"]).gaussians == (0.1, 0.3)
    assert "--fractions is now --gaussians" in caplog.text
    assert [name for name, *_ in budget_settings((0.1, 5000), ("footprint",))] == [
        "footprint10%", "footprint5000"]


def test_measure_sweeps_gaussian_budgets_beside_pruning(tmp_path, caplog):
    """Budget rows for each fraction and ranking in the same table as the pruning rows: K
    Gaussians per view, a learned ranking only for a model with the head (whose untrained head
    is the dither ranking: the same numbers), and the decisions and chart written."""
    import csv
    import dataclasses
    import logging

    from usplat_dr.data.synth import synthesize
    from usplat_dr.evaluation.speed import measure
    from usplat_dr.jobs.report import write_results
    from usplat_dr.model import UniqueSplat
    from usplat_dr.training.loader import load

    caplog.set_level(logging.ERROR, logger="usplat_dr.model.uniquesplat")
    root = tmp_path / "data"
    synthesize(root, scenes=2, frames=10, resolution=(32, 32), seed=8, spp=4, stage="test",
               previews=0, progress=False, kinds=("indoor",))
    plain = load("tiny_baseline")
    headed = UniqueSplat(dataclasses.replace(plain.cfg, importance=True)).eval()
    headed.load_state_dict(plain.state_dict(), strict=False)
    a, budget = BenchConfig("tiny", "baseline"), BenchConfig("tiny", "baseline", "budget")
    rows = measure({a: plain, budget: headed}, root, 32, render_sizes=[32],
                   prunes={"all": None}, progress=False, gaussians=(0.1, 0.5))
    by = {(r["config"], r["prune"]): r for r in rows}
    assert budget.label == "tiny (a) budget"
    assert sorted(p for c, p in by if c == "tiny (a)") == [
        "all", "dither10%", "dither50%", "footprint10%", "footprint50%", "opacity10%",
        "opacity50%", "random10%", "random50%"]
    assert sorted(p for c, p in by if c == "tiny (a) budget") == sorted(
        ["learned10%", "learned50%"] + [p for c, p in by if c == "tiny (a)"])
    for (c, p), r in by.items():
        if p == "all":
            assert r["rank_by"] is None and r["kept_fraction"] == 1.0
            continue
        k = round(r["budget_fraction"] * 2 * 32 * 32)
        assert r["gaussians_per_view"] == k and r["rank_by"] in p and r["split"] == "standard"
    # the untrained head is the dither ranking: the same model's (a) rows agree
    for f in ("10%", "50%"):
        learned, dither = by[("tiny (a) budget", f"learned{f}")], by[("tiny (a)", f"dither{f}")]
        assert learned["psnr"] == dither["psnr"] and learned["ssim"] == dither["ssim"]
    decision = write_results(rows, 32, tmp_path / "bench")
    assert set(decision["budgets"]) >= {"learned10%", "opacity50%", "random10%"}
    assert "learned10%" not in decision["pruning"]  # budgets are not pruning settings
    with open(tmp_path / "bench" / "bench.csv") as f:
        header = next(csv.reader(f))
    assert {"budget_fraction", "rank_by", "split", "render_time_per_view_ms"} <= set(header)
    assert (tmp_path / "bench" / "bench.png").stat().st_size > 0


def test_measure_times_the_automatic_count_beside_fixed_budgets(tmp_path, caplog):
    """``--gaussians ...,auto``: a ``dither-auto`` row per model, rendered as the count renders
    (its budget, culled and merged), its kept fraction a real fraction of the Gaussians, and
    the results written."""
    import logging

    from usplat_dr.data.synth import synthesize
    from usplat_dr.evaluation.speed import measure
    from usplat_dr.jobs.report import write_results
    from usplat_dr.training.loader import load

    caplog.set_level(logging.ERROR, logger="usplat_dr.model.uniquesplat")
    root = tmp_path / "data"
    synthesize(root, scenes=1, frames=10, resolution=(32, 32), seed=8, spp=4, stage="test",
               previews=0, progress=False, kinds=("indoor",))
    a = BenchConfig("tiny", "baseline")
    rows = measure({a: load("tiny_baseline")}, root, 32, render_sizes=[32],
                   prunes={"all": None}, progress=False, gaussians=(0.5, "auto"),
                   rank_by=("dither",))
    by = {r["prune"]: r for r in rows}
    assert sorted(by) == ["all", "dither-auto", "dither50%"]
    auto = by["dither-auto"]
    assert auto["rank_by"] == "dither" and 0 < auto["kept_fraction"] <= 1
    # culled and merged: fewer than all 2 x 32 x 32, whatever budget the count chose
    assert auto["gaussians_per_view"] < 2 * 32 * 32
    decision = write_results(rows, 32, tmp_path / "bench")
    assert "dither-auto" in decision["budgets"]
