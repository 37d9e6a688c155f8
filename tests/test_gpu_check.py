"""``bash scripts/run.sh gpu-check`` keeps working as the code changes: its benchmark commands,
read from the script itself, run here on the CPU (``--device cpu``) at a small size. Its CUDA
tests are the ``cuda`` variants of the suite, which skip here without a GPU."""

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]
#: Appended to each command: argparse keeps an option's last value, so the script's own flags
#: stay and only the size shrinks (a CPU runs the 256x256 and paper-preset settings in minutes).
SMALL = {"train/bench/rasterizer.py": ["--sizes", "16", "--dense-max", "16", "--runs", "1"],
         "train/bench/uniquesplat.py": ["--setting", "tiny64", "--repeats", "1"]}


def gpu_check_commands() -> list[list[str]]:
    """The ``"$PYTHON" train/bench/...`` commands of run.sh's ``gpu_check`` function, as
    argument lists (continuation lines joined, the output filters dropped)."""
    script = (ROOT / "scripts" / "run.sh").read_text()
    body = script[script.index("gpu_check() {"):]
    body = body[:body.index("\n}\n")].replace("\\\n", " ")
    commands = []
    for line in body.splitlines():
        match = re.search(r'"\$PYTHON" (train/bench/\S+\.py[^|]*)', line)
        if match:
            commands.append(shlex.split(match.group(1).replace("2>&1", "")))
    return commands


def test_run_sh_names_the_benchmarks_checked_here():
    assert sorted(c[0] for c in gpu_check_commands()) == sorted(SMALL)
    assert all(c[c.index("--device") + 1] == "cuda" for c in gpu_check_commands())


@pytest.mark.slow
@pytest.mark.parametrize("command", gpu_check_commands(), ids=lambda c: Path(c[0]).stem)
def test_gpu_check_benchmark_runs_on_the_cpu(command):
    args = [a if a != "cuda" else "cpu" for a in command] + SMALL[command[0]] + ["--threads", "1"]
    done = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=600, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    # each prints its table: the rasteriser's 16x16 row, UniqueSplat's (c)/(a) line
    expected = "| 16x16 |" if "rasterizer" in command[0] else "(c) full"
    assert expected in done.stdout, done.stdout[-3000:]


def test_the_gpu_commands_put_no_shared_folder_on_the_import_path(tmp_path):
    # a torch.py planted in the fixed /tmp/usplat-gpu-site (the folder the GPU commands once
    # put first on PYTHONPATH, writable by anyone on the machine) must not run; gpu-check then
    # stops at its own check (no CUDA here)
    planted = Path("/tmp/usplat-gpu-site")
    made = not planted.exists()
    if not made and not (planted / "torch.py").exists():
        pytest.skip("/tmp/usplat-gpu-site exists already (not ours to write into)")
    marker = tmp_path / "planted_module_ran"
    try:
        planted.mkdir(exist_ok=True)
        (planted / "torch.py").write_text(f"open({str(marker)!r}, 'w').write('ran')\n"
                                          "raise SystemExit(0)\n")
        done = subprocess.run(["bash", str(ROOT / "scripts" / "run.sh"), "gpu-check",
                               str(tmp_path / "out")], cwd=tmp_path, capture_output=True,
                              text=True, timeout=120, check=False,
                              env={"PATH": "/usr/bin:/bin", "PYTHON": sys.executable,
                                   "HOME": str(tmp_path)})
    finally:
        if made:
            (planted / "torch.py").unlink(missing_ok=True)
            planted.rmdir()
    assert not marker.exists(), "a module planted in /tmp/usplat-gpu-site ran"
    assert done.returncode == 1 and "torch sees no CUDA GPU here" in done.stderr + done.stdout
