"""One module per ``usplat`` command (``add_arguments(parser)`` and ``run(args) -> int``; the
table is ``usplat_dr.cli.COMMANDS``), and what several of them share (``report``,
``arguments``). Jobs import anything below them; nothing imports jobs."""
