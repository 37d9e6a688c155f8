"""``usplat bench``'s decisions and measurements on rows and blocks built by hand (the
end-to-end run is in ``test_evaluation.test_demo_quick_end_to_end``)."""

import pytest
import torch

from usplat_dr.jobs.bench import BenchConfig, PeakMemory, choose
from usplat_dr.jobs.report import pareto


def row(config, params, prune, psnr, size=64, change=None, kept=1.0):
    return {"config": config, "parameters": params, "prune": prune, "render_size": size,
            "psnr": psnr, "psnr_change_db": change, "kept_fraction": kept}


def test_choose_applies_the_issue_rules():
    rows = [row("tiny (a)", 3, "all", 20.0), row("small (c)", 10, "all", 20.5),
            row("paper (c)", 38, "all", 20.7), row("tiny (a)", 3, "all", 25.0, size=32),
            row("tiny (a)", 3, "cull", 20.0, change=0.0, kept=0.8),
            row("paper (c)", 38, "cull", 20.7, change=0.0, kept=0.7),
            row("tiny (a)", 3, "keep50%", 19.0, change=-1.0, kept=0.5),
            row("paper (c)", 38, "keep50%", 20.69, change=-0.01, kept=0.5)]
    d = choose(rows, 64)
    # best 20.7 at 64 px (the 25 dB row is another render size); 20.5 is within 0.3 dB, 20.0
    # is not: the smallest within is small (c)
    assert d["best"] == "paper (c)" and d["smallest_within_0.3dB"] == "small (c)"
    assert d["pruning"]["cull"]["safe"] and d["pruning"]["cull"]["kept_fraction"] == 0.75
    # safe only if every configuration loses less than 0.05 dB
    assert not d["pruning"]["keep50%"]["safe"]
    assert d["pruning"]["keep50%"]["worst_psnr_change_db"] == -1.0


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


def test_config_parsing_names_the_choices():
    assert BenchConfig.parse("tiny:c") == BenchConfig("tiny", "full")
    assert BenchConfig.parse("paper:baseline").label == "paper (a)"
    with pytest.raises(ValueError, match="preset:variant"):
        BenchConfig.parse("huge:c")
