"""Argument types shared by the jobs' parsers: a bad value is a usage error from argparse."""

import argparse
from pathlib import Path

#: ``--checkpoint``'s help, the same for every command that takes one (one loader behind them:
#: ``usplat_dr.training.checkpoints.load``).
CHECKPOINT_HELP = ("a shipped checkpoint's name (tiny_full, tiny_baseline, ...: "
                   "checkpoints/manifest.json), a file usplat train wrote "
                   "(OUTPUT_DIR/checkpoints/last.ckpt) or an official MVSplat .ckpt")


def at_least(minimum: int):
    """An argparse ``type``: an int >= ``minimum``.

    Examples:
        >>> at_least(1)("3")
        3
        >>> at_least(1)("0")
        Traceback (most recent call last):
        ...
        argparse.ArgumentTypeError: must be an integer >= 1, got '0'
    """
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum:
            raise argparse.ArgumentTypeError(f"must be an integer >= {minimum}, got {text!r}")
        return value

    parse.__name__ = f"integer >= {minimum}"  # argparse names the type in its message
    return parse


positive_int = at_least(1)
non_negative_int = at_least(0)


def out_folder(text: str) -> str:
    """An argparse ``type``: a folder to write into (it may not exist yet); an existing file
    there is a usage error, not a traceback from ``mkdir``."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{text!r} is an existing file, not a folder: name a "
                                         "folder to write into")
    return text


def out_file(text: str) -> str:
    """An argparse ``type``: a file to write (created or replaced); a folder, device or FIFO
    there is a usage error (it is never replaced)."""
    from usplat_dr.io.atomic import refuse_special  # the writers' own check

    try:
        refuse_special(Path(text))
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text
