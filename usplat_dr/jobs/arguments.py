"""Argument types shared by the jobs' parsers: a bad value is a usage error from argparse."""

import argparse
import logging
from pathlib import Path

from usplat_dr.model.budget import RANKINGS

log = logging.getLogger(__name__)

#: ``--device``'s help, the same for every command that takes one.
DEVICE_HELP = ("cpu: torch and Dr.Jit's LLVM backend on the CPU; cuda: a GPU (Dr.Jit's CUDA "
               "backend)")
#: ``--dataset``'s help, the same for every command that takes one.
DATASET_HELP = "the data's kind (its cameras' conventions and default near/far)"

#: ``--checkpoint``'s help, the same for every command that takes one (one loader behind them:
#: ``usplat_dr.training.loader.load``).
CHECKPOINT_HELP = ("a shipped model's name (full-64, baseline-64: usplat models; study ones: "
                   "usplat models --all), a file usplat train wrote "
                   "(OUTPUT_DIR/checkpoints/last.ckpt) or an official MVSplat .ckpt (default: "
                   "the shipped (c) for the size asked, said)")


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


def positive_float(text: str) -> float:
    """An argparse ``type``: a finite number > 0.

    Examples:
        >>> positive_float("2.5")
        2.5
    """
    try:
        value = float(text)
    except ValueError:
        value = None
    if value is None or not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a number > 0, got {text!r}")
    return value


positive_float.__name__ = "number > 0"  # argparse names the type in its message


def gaussians_argument(text: str) -> int | float | str:
    """An argparse ``type`` for ``--gaussians``: a count (an integer >= 1), a fraction in
    (0, 1] of the model's Gaussians (``0.3`` or ``30%``; ``1`` is one Gaussian, ``1.0`` all)
    or ``auto`` (each scene's own count, model/auto_budget.py).

    Examples:
        >>> gaussians_argument("5000"), gaussians_argument("0.3"), gaussians_argument("25%")
        (5000, 0.3, 0.25)
        >>> gaussians_argument("auto")
        'auto'
        >>> gaussians_argument("1.5")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        argparse.ArgumentTypeError: must be a count (an integer >= 1), a fraction in ...
    """
    if text.strip() == "auto":
        return "auto"
    value: int | float | None = None
    try:
        if text.endswith("%"):
            value = float(text[:-1]) / 100
        elif text.strip().lstrip("+").isdigit():
            value = int(text)
        else:
            value = float(text)
    except ValueError:
        value = None
    ok = value is not None and (value >= 1 if isinstance(value, int) else 0 < value <= 1)
    if not ok:
        raise argparse.ArgumentTypeError(f"must be a count (an integer >= 1), a fraction in "
                                         f"(0, 1] (0.3 or 30%) or auto, got {text!r}")
    return value


class RenamedOption(argparse.Action):
    """Stores the value as usual; given under an old name (any option string but the first),
    says once that the option was renamed."""

    def __call__(self, parser, namespace, values, option_string=None):
        if option_string is not None and option_string != self.option_strings[0]:
            log.warning("%s is now %s (the same values); the old name is accepted for one "
                        "more release", option_string, self.option_strings[0])
        setattr(namespace, self.dest, values)


def add_image_shape_option(p: argparse.ArgumentParser, default, help_text: str) -> None:
    """``--image-shape H W`` (``args.image_shape``), the one name every command gives the
    image size; ``--resolution``, its old name in ``synth``, ``import`` and ``fit``, still
    works, with a line saying so."""
    p.add_argument("--image-shape", "--resolution", dest="image_shape", type=at_least(4),
                   nargs=2, default=default, metavar=("H", "W"), action=RenamedOption,
                   help=help_text)


class _SquareSizeOption(argparse.Action):
    """An old one-number size option (``--size N``): stores ``[N, N]`` as the image shape and
    says once that the option is now ``--image-shape H W``."""

    def __call__(self, parser, namespace, values, option_string=None):
        log.warning("%s N is now --image-shape N N; the old name is accepted for one more "
                    "release", option_string)
        setattr(namespace, self.dest, [values, values])


def add_square_size_alias(p: argparse.ArgumentParser, name: str = "--size") -> None:
    """``name`` N, a command's old square image size, kept for one release beside
    ``--image-shape`` (``add_image_shape_option``): the same as ``--image-shape N N``."""
    p.add_argument(name, dest="image_shape", type=at_least(4), action=_SquareSizeOption,
                   default=argparse.SUPPRESS,
                   metavar="N", help="the old name of --image-shape N N (one more release)")


def check_budget_arguments(args: argparse.Namespace) -> None:
    """The budget arguments' mistakes that need no model: ``--tolerance`` without
    ``--gaussians auto``."""
    if getattr(args, "tolerance", None) is not None and args.gaussians != "auto":
        raise ValueError(f"--tolerance applies to --gaussians auto only (got --gaussians "
                         f"{args.gaussians}): add --gaussians auto or drop --tolerance")


def tolerance_db(text: str) -> float:
    """An argparse ``type`` for ``--tolerance``: a number of dB >= 0.

    Examples:
        >>> tolerance_db("0.5")
        0.5
    """
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not value >= 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a number of dB >= 0 (0.2 by default), got "
                                         f"{text!r}")
    return value


def add_budget_arguments(p: argparse.ArgumentParser) -> None:
    """``--gaussians``, ``--rank-by`` and ``--tolerance``: a Gaussian budget per target view
    (``UniqueSplat.forward``'s ``budget`` and ``rank_by``; docs/model.md)."""
    p.add_argument("--gaussians", type=gaussians_argument, metavar="K",
                   help="keep K Gaussians per target view: a count (5000) or a fraction of "
                   "them (0.3 or 30%%), the most important by --rank-by, or auto: per scene "
                   "the fewest whose loss is predicted within --tolerance, near-duplicates "
                   "merged (default: all)")
    p.add_argument("--tolerance", type=tolerance_db, metavar="DB",
                   help="with --gaussians auto: the loss against all Gaussians the count may "
                   "predict, in dB (default 0.2); the merging of near-duplicates after it "
                   "changes the render a little more (held out: by -0.01 to +0.01 dB)")
    p.add_argument("--rank-by", choices=RANKINGS,
                   help="how --gaussians ranks them: learned (the model's importance head, "
                   "the kept ones adapted to the budget), dither (the head's untrained start: "
                   "ordered dithering of opacity, the coverage rule; the better one for "
                   "budgets of 50%% and more), footprint (opacity x screen area for the "
                   "target camera), opacity or random (seeded), the controls "
                   "(default: learned where the model has the head, else dither, with a "
                   "warning)")


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
