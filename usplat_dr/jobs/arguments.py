"""Argument types shared by the jobs' parsers: a bad value is a usage error from argparse."""

import argparse


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
