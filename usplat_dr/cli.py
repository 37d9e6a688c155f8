"""The ``usplat`` command line: a table of commands, each one module of ``usplat_dr.jobs`` with
``add_arguments(parser)`` and ``run(args) -> int``.

Only the chosen command's module is imported (its imports, torch and Mitsuba among them, cost
seconds), so ``usplat doctor`` and ``usplat --help`` start at once.
"""

import argparse
import errno
import importlib
import keyword
import logging
import sys

from usplat_dr import DEMO_MINUTES, __version__, _threads, portable

#: ``usplat`` command -> help line. Each command is the module of ``usplat_dr.jobs`` named after
#: it (``job_module``).
COMMANDS = {
    "demo": ("the main job: synthetic data, train (a) and (c), evaluate, write a report "
             f"({DEMO_MINUTES} minutes on 2 CPU cores)"),
    "synth": ("render procedural scenes with known geometry (Mitsuba) into the field's chunk "
              "format, with evaluation and stress splits"),
    "import": ("a COLMAP model or a nerfstudio transforms.json (and its images) into the chunk "
               "format, with an evaluation index"),
    "pose": ("photos without cameras posed by COLMAP (pycolmap) into a COLMAP model folder that "
             "import, render and view read"),
    "train": ("train UniqueSplat (any variant) with the field's recipe; also under torchrun "
              "(DistributedDataParallel)"),
    "eval": ("evaluate a trained model with the field's protocol (per-scene CSV, summary JSON, "
             "renders)"),
    "render": ("novel views of a dataset scene or of your own images and cameras along a path: "
               "PNG frames, a video (mp4 with the video extra or ffmpeg, else GIF), a PLY"),
    "view": ("an interactive viewer in the browser (viser): move the camera and the model "
             "predicts and renders that view's own Gaussians; (a)/(c), colour/depth/opacity; "
             "or a 3DGS PLY"),
    "export-ply": "the Gaussians predicted for one target view, as a standard 3DGS PLY",
    "models": ("the shipped models, one line each (name, variant, size, purpose, default); "
               "--all with the study ones"),
    "bench": ("speed against accuracy: train (or reuse) size presets x variants on the demo's "
              "data, measure time per view, memory, Gaussians and accuracy; CSV + chart in "
              "OUT/bench"),
    "fit": ("per-scene Gaussian optimisation on a synthetic scene (renderer check): held-out "
            "PSNR/SSIM and a PNG of renders"),
    "params": "parameter count of a UniqueSplat configuration, per part",
    "render-demo": "render a procedural Gaussian scene from several cameras to PNGs",
    "doctor": "report versions, libLLVM, backends, GPU; exit 1 on problems",
}


def job_module(command: str) -> str:
    """The module of ``usplat_dr.jobs`` that runs ``command``: its name with ``-`` as ``_``, and
    a trailing ``_`` where that is a Python keyword (PEP 8).

    Examples:
        >>> job_module("export-ply"), job_module("import"), job_module("eval")
        ('export_ply', 'import_', 'eval')
    """
    name = command.replace("-", "_")
    return f"{name}_" if keyword.iskeyword(name) else name


#: User mistakes (a missing file, a bad config key or value, a checkpoint that does not fit,
#: invalid input data; also a full disk, any ``OSError`` with ``errno.ENOSPC``): one line and
#: exit status 2 instead of a traceback (``--debug`` shows it). The library raises these with
#: messages that name the argument and the fix.
USER_ERRORS = (FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError,
               ValueError)


#: A full disk, a full quota, a file-size limit: the same mistake to fix (free space).
FULL_DISK = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def is_user_error(e: BaseException) -> bool:
    """Whether ``e`` is a user mistake (``USER_ERRORS``) or a full disk."""
    return isinstance(e, USER_ERRORS) or (isinstance(e, OSError) and e.errno in FULL_DISK)


def shows_default(action: argparse.Action) -> bool:
    """Whether ``--help`` states the option's default: one that is not None, False, empty or
    suppressed (a flag's False and an unset path say nothing)."""
    return (bool(action.option_strings) and action.default not in (None, False, [], ())
            and action.default is not argparse.SUPPRESS)


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """Help lines end in "(default: X)" wherever ``shows_default`` says so and the help does
    not already state it (in its own words: "(default: ...")."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "%(default)" not in text and "(default:" not in text and shows_default(action):
            text = f"{text.strip()} (default: %(default)s)".strip()
        return text


#: Commands that choose no threads here: ``doctor`` reports the choice, and ``train``'s trainer
#: makes it (its ``threads`` setting first; ``usplat_dr.training.distributed``).
NO_THREADS = {"doctor", "models", "train"}


def use_free_cores() -> None:
    """torch's and Dr.Jit's threads: one per core other processes leave free, or
    ``USPLAT_THREADS`` (``usplat_dr._threads``); a command's ``--threads`` option sets its own
    after this."""
    choice = _threads.choose()
    import drjit as dr  # not at the top: ``usplat --help`` stays fast
    import torch

    # ``training.distributed.set_threads`` less its ``require_llvm``: a command that never
    # renders on the CPU (a CUDA-only machine) must not fail for want of libLLVM here
    torch.set_num_threads(choice.threads)
    if dr.has_backend(dr.JitBackend.LLVM):
        dr.set_thread_count(choice.threads)
    logging.getLogger("usplat_dr").info("%s", choice.line())


def asks_bfloat16(argv: list[str]) -> bool:
    """Whether the command line asks for ``--precision bfloat16`` (read before the parser:
    torch's pins must be decided before torch is imported).

    Examples:
        >>> asks_bfloat16(["eval", "--precision", "bfloat16"]), asks_bfloat16(["eval"])
        (True, False)
        >>> asks_bfloat16(["eval", "--precision=bfloat16"])
        True
    """
    pairs = zip(argv, [*argv[1:], None], strict=True)
    return "--precision=bfloat16" in argv or any(a == "--precision" and b == "bfloat16"
                                                 for a, b in pairs)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # Same numbers from the same command on every AVX2 CPU (before torch is imported); not
    # torch's pins for bfloat16 inference (no portable numbers there, and 14x slower pinned)
    portable.enable(torch_pins=not asks_bfloat16(argv))
    parser = argparse.ArgumentParser(prog="usplat", description="usplat-dr: UniqueSplat with a "
                                     "Dr.Jit Gaussian rasteriser")
    parser.add_argument("--version", action="version", version=f"usplat-dr {__version__}")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    parser.add_argument("--debug", action="store_true",
                        help="show the traceback of an error instead of its one-line message")
    sub = parser.add_subparsers(dest="command", required=True)
    parsers = {name: sub.add_parser(name, help=text, description=text,
                                    formatter_class=DefaultsHelpFormatter)
               for name, text in COMMANDS.items()}
    chosen = next((a for a in argv if not a.startswith("-")), None)
    if chosen in COMMANDS:
        job = importlib.import_module(f"usplat_dr.jobs.{job_module(chosen)}")
        job.add_arguments(parsers[chosen])
        parsers[chosen].set_defaults(run=job.run)
        for action in parsers[chosen]._actions:  # an option without help still shows its default
            if action.help is None and shows_default(action):
                action.help = "(default: %(default)s)"
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO,
                        format="%(message)s")
    try:
        if args.command not in NO_THREADS:
            use_free_cores()
        return args.run(args)
    except (*USER_ERRORS, OSError) as e:
        if args.debug or not is_user_error(e):
            raise
        print(f"usplat {args.command}: error: {e or type(e).__name__} (--debug shows "
              f"the traceback)", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
