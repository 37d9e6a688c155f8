"""What the jobs share: argument types (a bad value is a usage error from argparse), the
arguments that name a model, a dataset example or a user's own views, and the helpers that
turn them into a model, an example and views (``usplat render``, ``eval``, ``export-ply`` and
``view`` take them from here; a job module imports no other job module but this one and
``report``)."""

import argparse
import logging
from pathlib import Path

from usplat_dr.data.chunks import stored_image_shape
from usplat_dr.data.user_views import UserViews, context_views, crop_advice, read_cameras
from usplat_dr.evaluation import load_example, synthetic_indices
from usplat_dr.geometry.plane_sweep import near_far_from_sweep
from usplat_dr.model.auto_budget import make_budget
from usplat_dr.model.budget import RANKINGS
from usplat_dr.training.checkpoints import depth_range_warning, training_image_shape
from usplat_dr.training.loader import load
from usplat_dr.training.registry import default_checkpoint

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


def between(minimum: int, maximum: int):
    """An argparse ``type``: an int in ``minimum``..``maximum`` (a count that sizes work).

    Examples:
        >>> between(2, 2000)("60")
        60
        >>> between(2, 2000)("1000000")
        Traceback (most recent call last):
        ...
        argparse.ArgumentTypeError: must be an integer in 2..2,000, got '1000000'
    """
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or not minimum <= value <= maximum:
            raise argparse.ArgumentTypeError(f"must be an integer in {minimum:,}..{maximum:,}, "
                                             f"got {text!r}")
        return value

    parse.__name__ = f"integer in {minimum}..{maximum}"
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


def budget_from_args(args: argparse.Namespace):
    """The budget ``--gaussians``, ``--rank-by`` and ``--tolerance`` name, as
    ``UniqueSplat.forward`` and ``predict`` take it: ``None`` (every Gaussian), a
    ``GaussianBudget`` or an ``AutoBudget`` (``make_budget``); the one place ``eval``,
    ``render`` and ``export-ply`` build it. Their mistakes are usage errors here
    (``check_budget_arguments``)."""
    check_budget_arguments(args)
    return make_budget(args.gaussians, args.rank_by, args.tolerance)


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


# ---- A model, a dataset example, a user's own views ----------------------------------------

DATASETS = ["synth", "re10k", "acid", "dtu"]


def add_scene_arguments(p, data_required: bool = False) -> None:
    """``--data``, ``--dataset``, ``--index`` and ``--scene``: one evaluation example of a
    dataset (``p``: a parser or an argument group)."""
    p.add_argument("--data", required=data_required, help="dataset root (chunk format)")
    p.add_argument("--dataset", default="synth", choices=DATASETS, help=DATASET_HELP)
    p.add_argument("--index", help="evaluation index JSON (default: the synthetic set's "
                   "standard split)")
    p.add_argument("--scene", help="scene key (default: the first of the index)")


def add_example_arguments(p: argparse.ArgumentParser, data_required: bool = True) -> None:
    """The arguments naming a model and one evaluation example (``render``, ``export-ply``)."""
    p.add_argument("--checkpoint", help=CHECKPOINT_HELP)
    add_scene_arguments(p, data_required)
    add_image_shape_argument(p)
    add_trust_argument(p)
    add_budget_arguments(p)
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                   help=DEVICE_HELP)


def add_trust_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument("--trust-checkpoint", action="store_true",
                   help="unpickle the checkpoint fully if torch.load(weights_only=True) refuses "
                   "it (it can run code: only for files you trust)")


def add_image_shape_argument(p: argparse.ArgumentParser, fits: bool = True) -> None:
    """``--image-shape``; ``fits``: without --checkpoint the command's default model is the
    one for that size (``fit_checkpoint``), and its help says so."""
    fitted = ("; without --checkpoint, the shipped (c) trained nearest it, or nearest --data's "
              "stored size, or the largest for your own images" if fits else "")
    p.add_argument("--image-shape", type=positive_int, nargs=2, metavar=("H", "W"),
                   help="the size images are cropped and resized to (default: the size the "
                   f"checkpoint was trained at{fitted})")


def image_shape(args: argparse.Namespace) -> tuple[int, int]:
    """``--image-shape``, or the checkpoint's training image shape (the dataset preset's
    default, 256 x 256, for a checkpoint that records none)."""
    if args.image_shape:
        return tuple(args.image_shape)
    return training_image_shape(args.checkpoint, args.trust_checkpoint) or (256, 256)


def fit_checkpoint(args: argparse.Namespace) -> str:
    """``--checkpoint`` as given (a name never changes size: ``full-64`` is that model at any
    size); without one, the shipped (c) for the request, which ``args.checkpoint`` becomes
    (``default_checkpoint``): the one trained nearest ``--image-shape``, else nearest the size
    ``--data``'s images are stored at, else with your own ``--images`` the largest; said."""
    if args.checkpoint is not None:
        return args.checkpoint
    if args.image_shape is not None:
        shape = tuple(args.image_shape)
    elif getattr(args, "images", None) is not None:
        shape = None  # your own photographs: larger than any model's size
    else:
        data = getattr(args, "data", None)
        shape = stored_image_shape(data) if data is not None else None
        if shape is None and data is not None:
            log.info("--data %s: its images' stored size cannot be read; choosing for 64x64",
                     data)
            shape = (64, 64)
    args.checkpoint, line = default_checkpoint(shape)
    log.info("%s", line)
    return args.checkpoint


def one_example(args: argparse.Namespace) -> tuple:
    """The model and the example that ``add_example_arguments``' arguments name."""
    index = args.index or synthetic_indices(args.data, ["standard"])["standard"]
    model = load(args.checkpoint, args.device, args.trust_checkpoint)
    return model, load_example(dataset_section(args), index, args.scene)


def dataset_section(args: argparse.Namespace) -> dict:
    """The dataset section of ``--data``, ``--dataset``, the image shape and, where given,
    ``--near``/``--far`` (overriding each scene's recorded range)."""
    dataset = {"name": args.dataset, "roots": [args.data], "image_shape": image_shape(args)}
    if hasattr(args, "near"):
        check_near_far(args)
        if args.near is not None:
            dataset["overrides"] = {"near": args.near, "far": args.far}
    return dataset


def add_own_views_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments naming a user's own context views (``render``, ``view``)."""
    own = p.add_argument_group("your own context views (instead of --data)")
    own.add_argument("--images", nargs="+", metavar="IMAGE",
                     help="two (or more) context images, named as in --cameras (without "
                     "--cameras they are posed by COLMAP first: usplat pose)")
    own.add_argument("--cameras", help="their cameras: a COLMAP model folder (sparse/0) or a "
                     "nerfstudio transforms.json (default: pose the images with COLMAP)")
    add_near_far_arguments(own, "from the COLMAP model's sparse points, else estimated by a "
                           "plane sweep between the two context views")
    own.add_argument("--ignore-distortion", action="store_true",
                     help="drop lens distortion coefficients (else they are an error)")


def add_near_far_arguments(p, default: str) -> None:
    """``--near`` and ``--far`` (scene units), ``default`` saying where they come from
    otherwise."""
    p.add_argument("--near", type=positive_float, help=f"near depth, scene units (default: "
                   f"{default})")
    p.add_argument("--far", type=positive_float, help="far depth (as --near)")


def check_own_views(args: argparse.Namespace) -> None:
    """The mistakes in ``add_own_views_arguments``' arguments that need no file read."""
    check_near_far(args)


def check_near_far(args: argparse.Namespace) -> None:
    if (args.near is None) != (args.far is None):
        raise ValueError("give both --near and --far, or neither")
    if args.near is not None and not args.near < args.far:
        raise ValueError(f"--near must be below --far, got {args.near} and {args.far}")


def pose_own_images(args: argparse.Namespace, folder: Path) -> None:
    """``--images`` without ``--cameras``: the images posed by COLMAP into ``folder``
    (``usplat_dr.data.pose``; reused when it already holds these photos' poses), then
    ``args.cameras`` its model and ``args.images`` its undistorted copies."""
    from usplat_dr import _threads  # (with pycolmap, only where photos are posed)
    from usplat_dr.data.pose import PoseSettings, pose_photos, posed_before

    photos = [Path(p) for p in args.images]
    result = posed_before(photos, folder)
    if result is None:
        print(f"no --cameras: posing the {len(photos)} photos with COLMAP (pycolmap) into "
              f"{folder} (usplat pose does this alone)")
        result = pose_photos(photos, folder, PoseSettings(threads=_threads.choose().threads))
    else:
        print(f"no --cameras: using the poses of these photos in {folder}")
    print(result.line())
    missing = [p.name for p in photos if p.name not in result.registered]
    if missing:
        raise ValueError(f"COLMAP could not pose {', '.join(missing)} (pose.json in {folder} "
                         "says why): give --cameras, or more photos of the scene with "
                         "usplat pose")
    args.cameras = str(result.model)
    args.images = [str(result.images / p.name) for p in photos]


def own_views(args: argparse.Namespace, trained_range: list[float] | None = None,
              pose_folder: Path | None = None) -> tuple[UserViews, float, float]:
    """The context views ``--images`` and ``--cameras`` name (posed first into
    ``pose_folder`` without ``--cameras``: ``pose_own_images``), cropped to ``image_shape``,
    and near/far (``--near``/``--far``, else from the sparse points, else estimated by a
    plane sweep between the first two views), printed, with a warning when they lie far
    outside ``trained_range`` (the model's ``trained_depth_range``)."""
    check_own_views(args)
    if args.cameras is None:
        from usplat_dr.data.pose import default_pose_folder  # only where photos are posed

        pose_own_images(args, pose_folder or default_pose_folder(args.images))
        posed = True
    else:
        posed = False
    scene, shape = read_cameras(args.cameras, args.ignore_distortion), image_shape(args)
    views = context_views(args.images, scene, shape)
    shapes = {tuple(int(n) for n in s) for s in scene.image_shapes}
    for advice in sorted(filter(None, (crop_advice(s, shape) for s in shapes))):
        print(advice)
    if args.near is not None:
        near, far, where = args.near, args.far, "--near/--far"
    elif views.near is not None:
        near, far = views.near, views.far
        where = "from the sparse points; --near/--far to set it"
    else:
        near, far = near_far_from_sweep(
            [im.permute(1, 2, 0).numpy() for im in views.images[:2]],
            list(views.intrinsics[:2].double().numpy()),
            list(views.extrinsics[:2].double().numpy()))
        where = ("no sparse points: estimated by a plane sweep between the two context "
                 "views; --near/--far to set it")
    if posed:
        baseline = float((views.extrinsics[0, :3, 3] - views.extrinsics[1, :3, 3]).norm())
        where += (f"; COLMAP's scale is arbitrary: the context cameras are {baseline:.3g} "
                  "units apart")
    # the range matters (2-3 dB against the one a scene was trained with, docs/data.md): say it
    print(f"near/far {near:.4g} / {far:.4g} ({where})")
    # COLMAP's units are arbitrary: a range far from the trained one says nothing there
    warning = None if posed else depth_range_warning(near, far, trained_range)
    if warning:
        log.warning(warning)
    return views, near, far
