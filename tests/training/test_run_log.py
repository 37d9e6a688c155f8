"""The run log (``RunLog``): ``metrics.csv`` kept across a resume by an atomic rewrite, rows at
the logging cadence, the files closed on leaving however the block ends, a full disk named;
and the readers of the same file (``read_metrics``, ``curve``)."""

import errno

import pytest

from usplat_dr.training import run_log as run_log_module
from usplat_dr.training.run_log import DiskFull, RunLog, curve, read_metrics

FIELDS = ["step", "loss", "psnr", "lpips", "skipped", "steps_per_s", "time_s", "cpu_s"]


def stats(step: int) -> dict:
    return {"loss": 1.0 / step, "psnr": 10.0 + step}


def run(folder, start: int, steps: int, log_every: int = 1) -> None:
    with RunLog(folder, FIELDS, start, steps, log_every, progress=False) as log:
        for step in range(start + 1, steps + 1):
            log.log(step, stats(step), skipped=0)


def test_rows_at_the_cadence_and_at_the_last_step(tmp_path):
    run(tmp_path, 0, 7, log_every=3)
    rows = read_metrics(tmp_path)
    assert [r["step"] for r in rows] == ["3", "6", "7"]
    assert curve(rows, "loss") == ([3, 6, 7], [1 / 3, 1 / 6, 1 / 7])
    assert curve(rows, "lpips") == ([], [])  # a column no row has a value in
    with RunLog(tmp_path / "b", FIELDS, 0, 2, progress=False) as log:
        log.log(1, {}, skipped=1)  # no good step yet: nothing to write
        log.log(2, stats(2), skipped=1)
    assert [(r["step"], r["skipped"]) for r in read_metrics(tmp_path / "b")] == [("2", "1")]


def test_rows_carry_wall_and_process_cpu_time(tmp_path):
    with RunLog(tmp_path, FIELDS, 0, 2, progress=False) as log:
        sum(range(2_000_000))  # some CPU work before each row
        log.log(1, stats(1), skipped=0)
        sum(range(2_000_000))
        log.log(2, stats(2), skipped=0)
    rows = read_metrics(tmp_path)
    cpu = [float(r["cpu_s"]) for r in rows]
    # process_time counts this process's CPU time since the log opened: it grows by the loop's
    # CPU time (tens of ms; the counter's resolution is far finer)
    assert 0 < cpu[0] < cpu[1]
    # resumed from step 1: counting goes on from the kept row's cpu_s, not from 0 again
    with RunLog(tmp_path, FIELDS, 1, 2, progress=False) as log:
        log.log(2, stats(2), skipped=0)
    rows = read_metrics(tmp_path)
    assert [r["step"] for r in rows] == ["1", "2"]
    assert float(rows[1]["cpu_s"]) >= cpu[0]  # from 0 it would be microseconds, below cpu[0]


def test_a_resumed_run_keeps_the_rows_up_to_its_step(tmp_path):
    run(tmp_path, 0, 5)
    run(tmp_path, 3, 6)  # resumed from the step-3 checkpoint: steps 4.. are redone
    rows = read_metrics(tmp_path)
    assert [r["step"] for r in rows] == ["1", "2", "3", "4", "5", "6"]
    assert all(float(r["loss"]) == 1 / int(r["step"]) for r in rows)
    assert not list(tmp_path.glob(".*.tmp"))  # the rewrite left no temporary file


def test_a_row_cut_short_is_dropped(tmp_path):
    run(tmp_path, 0, 4)
    with open(tmp_path / "metrics.csv", "a") as f:
        f.write("5,0.2")  # a power cut mid-append, after the step-5 checkpoint
    run(tmp_path, 5, 6)
    assert [r["step"] for r in read_metrics(tmp_path)] == ["1", "2", "3", "4", "6"]


def test_leaving_closes_the_files_however_the_block_ends(tmp_path):
    with pytest.raises(RuntimeError), \
            RunLog(tmp_path, FIELDS, 0, 2, progress=True) as log:
        log.log(1, stats(1), skipped=0)
        raise RuntimeError("a step failed")
    assert log.metrics.file.closed
    assert log.bar.disable  # tqdm's close() disables the bar


def test_a_full_disk_names_metrics_csv(tmp_path, monkeypatch):
    def disk_full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(run_log_module, "atomic_open", disk_full)
    with pytest.raises(DiskFull, match=r"disk full .*metrics\.csv.*--resume"):
        RunLog(tmp_path, FIELDS, 0, 2, progress=False).__enter__()
