"""One module per ``usplat`` command (``add_arguments(parser)`` and ``run(args) -> int``; the
table is ``usplat_dr.cli.COMMANDS``), and what several of them share (``budgets``,
``report``, ``arguments``). Jobs import anything below them; nothing imports jobs."""

#: How long ``usplat demo`` takes on 2 CPU cores from a fresh clone (installation excluded), the
#: range over the machine kinds it ran on (BENCHMARKS.md, "the demo"): stated once, read by the
#: CLI's help, ``jobs/demo.py`` and a README test.
DEMO_MINUTES = "4-10"
