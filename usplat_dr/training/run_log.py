"""The log of a training run, and the one place that reads and writes its format:
``metrics.csv`` (a row per logged step: ``step``, the loss terms, PSNR, gradient norms, the
learning rate, skipped steps, the rate and time), TensorBoard scalars (when TensorBoard is
installed) and the progress bar.

``RunLog`` writes them while ``Trainer.fit`` runs; ``read_metrics`` and ``curve`` read
``metrics.csv`` back, and ``stability`` (loss and gradient-norm statistics) and ``curves`` (the
chart) summarise it. Nothing is lost: ``metrics.csv`` is rewritten atomically when a run
(re)starts and appended a row at a time, flushed, and a write that finds the disk full is a
``DiskFull`` naming the file.
"""

import contextlib
import csv
import errno
import logging
import math
import os
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from usplat_dr.io import atomic_open
from usplat_dr.model.uniquesplat import VARIANTS

log = logging.getLogger(__name__)

#: The file of a run folder that ``RunLog`` writes and ``read_metrics`` reads.
METRICS_FILE = "metrics.csv"
#: The gradient-norm columns of the network's parts (before clipping), and their labels.
GRAD_LABELS = {"grad_primary": "primary network", "grad_agnostic": "view-agnostic (e_a, H_a)",
               "grad_specific": "view-specific H_s",
               "grad_view_features": "view-specific features (ResNet, Proj, phi)",
               "grad_importance": "importance head and budget adaptation"}

#: The errors of a write that found no room: a full disk, a full quota, a file-size limit
#: (``ulimit -f``, with SIGXFSZ ignored as batch schedulers do).
FULL_DISK = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


class DiskFull(OSError):
    """A write of the run failed for a full disk (``errno.ENOSPC``); the message names the file
    and the fix (the atomic writers leave the file's previous version intact)."""

    def __init__(self, path: str | os.PathLike):
        super().__init__(errno.ENOSPC, f"disk full (or a quota or file-size limit): cannot write "
                         f"{path} (its previous version "
                         f"is intact): free space on that disk or choose another output_dir, "
                         f"then rerun with --resume", str(path))

    def __str__(self) -> str:
        return self.strerror


@contextlib.contextmanager
def disk_full_names(path: str | os.PathLike) -> Iterator[None]:
    """Turn an ``OSError(ENOSPC)`` inside the block into a ``DiskFull`` naming ``path``."""
    try:
        yield
    except DiskFull:
        raise
    except OSError as e:
        if e.errno not in FULL_DISK:
            raise
        raise DiskFull(path) from e


# ---- writing ----------------------------------------------------------------------------------

class MetricsLog:
    """``metrics.csv``, a row per logged step. Opened for a run at ``step``, it keeps the rows
    of the steps up to ``step`` (a resumed run redoes the later ones) by an atomic rewrite, so a
    kill at any moment leaves every kept row in the file; new rows are appended and flushed one
    at a time. A full disk is a ``DiskFull`` naming the file."""

    def __init__(self, path: Path, fields: list[str], step: int):
        self.path = path
        rows = self.kept_rows(path, step)
        #: CPU seconds of the run up to its last kept row (``cpu_s``; 0 for a new run)
        self.cpu_before = next((float(r["cpu_s"]) for r in reversed(rows) if r.get("cpu_s")),
                               0.0)
        with disk_full_names(path):
            with atomic_open(path, "w") as f:
                writer = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
                writer.writeheader()
                writer.writerows(rows)
            self.file = open(path, "a", newline="")  # noqa: SIM115 (closed by close())
        self.writer = csv.DictWriter(self.file, fieldnames=fields, extrasaction="ignore")

    @staticmethod
    def kept_rows(path: Path, step: int) -> list[dict]:
        """The complete rows of ``path`` (none when it does not exist) at steps <= ``step``; a
        row cut short (a power cut mid-append) is dropped."""
        if not path.exists():
            return []
        try:
            rows = _read_rows(path)
        except (UnicodeDecodeError, csv.Error) as e:
            # not this project's text (a damaged disk, another program): kept aside, and the
            # run's log starts again rather than the run failing on its own log
            aside = path.with_name(path.name + ".damaged")
            os.replace(path, aside)
            log.warning("%s is damaged (%s): moved to %s; the log starts again from this step",
                        path, type(e).__name__, aside)
            return []
        return [r for r in rows if None not in r and None not in r.values()
                and (r.get("step") or "").isdigit() and int(r["step"]) <= step
                and _number(r.get("cpu_s", "0") or "0")]

    def write(self, row: dict) -> None:
        with disk_full_names(self.path):
            self.writer.writerow(row)
            self.file.flush()

    def close(self) -> None:
        with disk_full_names(self.path):
            self.file.close()


class RunLog:
    """The log of a run in ``folder`` from step ``step`` on (of ``steps``): ``metrics.csv``
    with the columns ``fields`` (``MetricsLog``: a resumed run's rows of later steps are
    dropped), TensorBoard's ``tensorboard/`` (when installed; purged after ``step`` likewise)
    and, with ``progress``, a progress bar. A context manager: entering opens them, leaving
    closes them (the bar, TensorBoard, then ``metrics.csv``); ``log()`` after every step.

    Examples:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as folder:
        ...     with RunLog(Path(folder), ["step", "loss"], 0, steps=2, progress=False) as run:
        ...         run.log(1, {"loss": 0.5}, skipped=0)
        ...         run.log(2, {"loss": 0.25}, skipped=0)
        ...     print([(r["step"], r["loss"]) for r in read_metrics(folder)])
        [('1', '0.5'), ('2', '0.25')]
    """

    def __init__(self, folder: Path, fields: Sequence[str], step: int, steps: int,
                 log_every: int = 1, progress: bool = True):
        self.folder, self.fields = Path(folder), list(fields)
        self.start, self.steps, self.log_every, self.progress = step, steps, log_every, progress
        self.metrics: MetricsLog | None = None
        self.board = None  # torch.utils.tensorboard.SummaryWriter, when installed
        self.bar: tqdm | None = None
        self._closes = contextlib.ExitStack()
        self._t0, self._c0 = time.perf_counter(), time.process_time()

    def __enter__(self) -> "RunLog":  # noqa: PYI034 (typing.Self needs Python 3.11)
        with contextlib.ExitStack() as opened:  # what opened before a failure is closed
            self.metrics = MetricsLog(self.folder / METRICS_FILE, self.fields, self.start)
            opened.callback(self.metrics.close)
            try:  # TensorBoard when it is installed (optional)
                from torch.utils.tensorboard import SummaryWriter

                self.board = SummaryWriter(str(self.folder / "tensorboard"),
                                           purge_step=self.start)
                opened.callback(self.board.close)
            except ImportError:
                pass
            if self.progress:
                self.bar = tqdm(total=self.steps, initial=self.start, desc="train",
                                dynamic_ncols=True)
                opened.callback(self.bar.close)
            self._closes = opened.pop_all()
        self._t0, self._c0 = time.perf_counter(), time.process_time()
        self._c0 -= self.metrics.cpu_before  # cpu_s counts on from the kept rows
        return self

    def __exit__(self, *exc) -> None:
        self._closes.close()

    def log(self, step: int, stats: dict, skipped: int) -> None:
        """After step ``step`` (counted from 1): every ``log_every`` steps and at the last, a
        row of ``metrics.csv`` and TensorBoard with ``stats`` (the last good step's; nothing
        before there is one), ``skipped``, the rate and wall time since entering, and the
        process CPU time of the run (all threads; a resumed run adds its kept rows' last
        ``cpu_s``, so the work of a killed process past its checkpoint is not counted); the
        bar."""
        elapsed = time.perf_counter() - self._t0
        rate = (step - self.start) / max(elapsed, 1e-9)
        if stats and (step % self.log_every == 0 or step == self.steps):
            self.metrics.write({"step": step, **stats, "skipped": skipped,
                                "steps_per_s": rate, "time_s": elapsed,
                                "cpu_s": time.process_time() - self._c0})
            if self.board is not None:
                for key, value in stats.items():
                    self.board.add_scalar(f"train/{key}", value, step)
        if self.bar is not None:
            self.bar.update(1)
            if stats:
                self.bar.set_postfix(loss=f"{stats['loss']:.4f}", psnr=f"{stats['psnr']:.2f}",
                                     skipped=skipped)


# ---- reading ----------------------------------------------------------------------------------

def _number(text: str) -> bool:
    """Whether ``text`` is a finite number (a kept row's ``cpu_s`` is added up)."""
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def _read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def read_metrics(run: str | os.PathLike) -> list[dict]:
    """The rows of the run folder ``run``'s ``metrics.csv``, ``{column: text}``: "" where a
    row has no value (a loss term not on yet, a part the model does not have)."""
    return _read_rows(Path(run) / METRICS_FILE)


def curve(rows: list[dict], key: str) -> tuple[list[int], list[float]]:
    """The steps and values of the column ``key`` over ``rows`` (``read_metrics``), the rows
    without a value left out.

    Examples:
        >>> curve([{"step": "10", "lpips": ""}, {"step": "20", "lpips": "0.3"}], "lpips")
        ([20], [0.3])
    """
    points = [(int(r["step"]), float(r[key])) for r in rows if r.get(key)]
    return [s for s, _ in points], [v for _, v in points]


# ---- summaries --------------------------------------------------------------------------------

def curves(runs: dict, path: Path) -> Path:
    """Training loss, PSNR and the gradient norms of the network's parts (before clipping) of
    the runs ``{variant: run folder}``, as a PNG at ``path``."""
    import matplotlib  # only for the chart (start-up time: the trainer imports this module)

    matplotlib.use("Agg")  # files only, no display
    import matplotlib.pyplot as plt  # after choosing the backend

    fig, axes = plt.subplots(1, 3, figsize=(14, 3.4))
    for variant, run in runs.items():
        rows = read_metrics(run)
        for ax, key in ((axes[0], "loss"), (axes[1], "psnr")):
            steps, values = curve(rows, key)
            line, = ax.plot(steps, values, alpha=0.25, linewidth=0.8)
            ax.plot(steps, smooth(values), color=line.get_color(),
                    label=VARIANTS.get(variant, variant))
        for key, label in GRAD_LABELS.items():
            steps, values = curve(rows, key)
            if values:
                axes[2].plot(steps, smooth(values), linewidth=1,
                             label=f"{VARIANTS.get(variant, variant)[:3]} {label}")
    axes[0].set(xlabel="step", ylabel="training loss (MSE)", yscale="log")
    axes[1].set(xlabel="step", ylabel="training PSNR (dB)")
    axes[2].set(xlabel="step", ylabel="gradient norm before clipping", yscale="log")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_open(path, "wb") as f:
        fig.savefig(f, format="png", dpi=110)
    plt.close(fig)
    return path


def smooth(values: list[float]) -> list[float]:
    """Moving average over ~1/15 of the run."""
    w = max(1, len(values) // 15)
    return [sum(values[max(0, i - w + 1):i + 1]) / len(values[max(0, i - w + 1):i + 1])
            for i in range(len(values))]


def stability(run: Path) -> dict:
    """Loss and gradient-norm statistics of a training run's ``metrics.csv``: per part the
    median and maximum gradient norm (before clipping) and the last quarter's median against
    the first quarter's (bounded: the ratio stays near or below 1), and the skipped steps."""
    rows = read_metrics(run)
    q = max(1, len(rows) // 4)
    _, loss = curve(rows, "loss")
    out = {"steps": int(rows[-1]["step"]), "skipped": int(rows[-1]["skipped"]),
           "loss_first_quarter": float(np.median(loss[:q])),
           "loss_last_quarter": float(np.median(loss[-q:])), "parts": {}}
    for key in ("grad_norm", *GRAD_LABELS):
        _, values = curve(rows, key)
        if values:
            out["parts"][key] = {"median": float(np.median(values)), "max": max(values),
                                 "last_over_first_quarter": float(
                                     np.median(values[-q:]) / np.median(values[:q]))}
    return out
