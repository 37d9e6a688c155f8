"""SIGKILL at every commit of ``usplat import``, ``usplat eval`` and ``usplat render --images``:
what a killed command leaves is complete files only (each one parses), and a rerun after the
kill writes what a run that was never killed writes.

A commit is a rename (``os.replace``/``os.rename``: every atomic write and folder swap ends in
one). The command runs in a child process that counts them and sends itself SIGKILL just
before the N-th, for every N of a clean run's count; so each state between two commits is
met once, as a real kill would leave it (no cleanup code runs). The scene is the importers'
synthetic truth (6 views, 48x64); the model the shipped ``tiny_baseline``."""

import collections
import csv
import json
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from PIL import Image

from tests.training.processes import environment

pytestmark = pytest.mark.slow  # about 2 minutes: 30 processes of a few seconds each
COUNTS = collections.Counter()  # what the kills left; printed by the last test

#: The child: counts renames, SIGKILLs itself before the N-th (N = argv[1]; 0: never), and
#: reports how many it made.
CHILD = """
import os, signal, sys
kill_at, calls = int(sys.argv[1]), [0]
def counted(real):
    def commit(*args, **kwargs):
        calls[0] += 1
        if calls[0] == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)
        return real(*args, **kwargs)
    return commit
os.replace, os.rename = counted(os.replace), counted(os.rename)
from usplat_dr.cli import main
code = main(sys.argv[2:])
print(f"COMMITS {calls[0]}", file=sys.stderr)
sys.exit(code)
"""


def run(kill_at: int, argv: list[str]) -> tuple[int, int | None]:
    """(return code, commits made or None when killed) of ``usplat ARGV`` killed before the
    ``kill_at``-th commit."""
    # one thread, fixed: by default the commands start one per free core, and a rerun on a
    # machine that got busier in between would sum in another order and write other last digits
    proc = subprocess.run([sys.executable, "-c", CHILD, str(kill_at), "-q", *argv],
                          capture_output=True, text=True,
                          env={**environment(), "USPLAT_THREADS": "1"}, timeout=600,
                          check=False)
    commits = [line for line in proc.stderr.splitlines() if line.startswith("COMMITS ")]
    if proc.returncode not in (0, -signal.SIGKILL):
        raise AssertionError(f"usplat {' '.join(argv)}: status {proc.returncode}\n"
                             f"{proc.stderr[-3000:]}")
    return proc.returncode, int(commits[0].split()[1]) if commits else None


def visible_files(root: Path) -> dict[str, Path]:
    """{relative path: file} of the files under ``root`` a user or reader sees (no part of
    the path hidden: temporary files and partial folders start with a dot)."""
    if not root.exists():
        return {}
    return {str(p.relative_to(root)): p for p in sorted(root.rglob("*"))
            if p.is_file() and not any(part.startswith(".")
                                       for part in p.relative_to(root).parts)}


def check_complete(path: Path) -> None:
    """``path`` parses whole as what its suffix says (a truncated file does not)."""
    if path.suffix == ".json":
        json.loads(path.read_text())
    elif path.suffix == ".torch":
        assert isinstance(torch.load(path, weights_only=True), list)
    elif path.suffix == ".png":
        with Image.open(path) as im:
            im.load()
    elif path.suffix == ".csv":
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
        assert rows and all(len(r) == len(rows[0]) for r in rows), path
    elif path.suffix == ".ply":
        from plyfile import PlyData  # only the render writes one

        PlyData.read(str(path))
    elif path.suffix in (".mp4", ".gif"):
        assert path.stat().st_size > 0
    else:
        raise AssertionError(f"no check for {path}")


def kill_everywhere(argv, out: Path, commits: int, prepare=lambda: None,
                    whole_sets: dict | None = None, check=lambda left: None) -> list[dict]:
    """Kill ``usplat ARGV`` (writing ``out``) before each of its ``commits`` (a clean run's
    count), check what is left, rerun it unkilled; each rerun's files ({path: bytes}).
    ``prepare`` runs before each try; ``whole_sets``: {folder prefix: [its allowed contents
    ({path: bytes})]} for folders that must never hold a mixture; ``check``: more checks of
    what a kill left ({relative path: Path})."""
    reruns = []
    for n in range(1, commits + 1):
        prepare()
        code, _ = run(n, argv)
        assert code == -signal.SIGKILL, (n, code)
        left = visible_files(out)
        for path in left.values():
            check_complete(path)
        for folder, versions in (whole_sets or {}).items():
            # a folder written whole: one of these, or absent (between the swap's renames)
            now = {k: p.read_bytes() for k, p in left.items() if k.startswith(folder)}
            assert not now or now in versions, (n, folder, sorted(now))
        check(left)
        COUNTS["kills"] += 1
        COUNTS["files left, each complete"] += len(left)
        assert run(0, argv)[0] == 0, n
        reruns.append({k: p.read_bytes() for k, p in visible_files(out).items()})
    return reruns


def files_of(root: Path) -> dict[str, bytes]:
    return {k: p.read_bytes() for k, p in visible_files(root).items()}


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    from tests.data.test_importers import Truth  # a test module: only when a test asks

    t = Truth(tmp_path_factory.mktemp("scene"))
    t.write_colmap_binary(t.root / "sparse" / "0")
    return t


def import_argv(scene, out: Path) -> list[str]:
    return ["import", "--colmap", str(scene.root / "sparse" / "0"), "--out", str(out),
            "--image-shape", "64", "64"]


def test_a_killed_import_leaves_no_stage_or_all_of_it(scene, tmp_path):
    code, commits = run(0, import_argv(scene, tmp_path / "clean"))
    assert code == 0 and commits >= 3  # the chunk, its index, the evaluation index
    clean = files_of(tmp_path / "clean")
    assert {"test/000000.torch", "test/index.json", "evaluation_index_standard.json"} <= set(clean)
    stage = {k: v for k, v in clean.items() if k.startswith("test/")}
    out = tmp_path / "data"
    # each try into a fresh --out; the rerun goes into what the kill left (a user's rerun)
    reruns = kill_everywhere(import_argv(scene, out), out, commits,
                             lambda: shutil.rmtree(out, ignore_errors=True), {"test/": [stage]})
    assert all(files == clean for files in reruns)
    assert not list(out.glob(".*"))  # nothing hidden is left behind


def without_timings(files: dict[str, bytes]) -> dict:
    """An evaluation's files with ``summary.json``'s timing and memory fields left out (they
    differ from run to run; the scores may not)."""
    files = dict(files)
    summary = json.loads(files.pop("summary.json"))
    for key in ("time_per_scene_s", "peak_memory_gib"):
        summary.pop(key)
    return {**files, "summary.json": summary}


def test_a_killed_eval_leaves_complete_files_and_a_rerun_scores_the_same(scene, tmp_path):
    data = tmp_path / "data"
    assert run(0, import_argv(scene, data))[0] == 0
    argv = ["eval", "--checkpoint", "tiny_baseline", "--data", str(data)]
    code, commits = run(0, [*argv, "--out", str(tmp_path / "clean")])
    assert code == 0 and commits >= 3  # at least one commit per file
    clean = without_timings(files_of(tmp_path / "clean"))
    assert {"per_scene.csv", "summary.json"} <= set(clean)
    assert any(k.startswith("renders/standard/") for k in clean)
    # an earlier eval of another model in --out: a kill must never leave its summary.json
    # beside the new run's per_scene.csv or renders (a summary always describes the files
    # beside it), and a finished rerun holds nothing of it
    earlier_eval = tmp_path / "earlier"
    other = ["eval", "--checkpoint", "study/tiny_full", "--data", str(data)]
    assert run(0, [*other, "--out", str(earlier_eval)])[0] == 0
    earlier = files_of(earlier_eval)
    out = tmp_path / "eval"

    def over_the_earlier_eval():
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(earlier_eval, out)

    def one_run(left):
        if "summary.json" in left:  # then every result file beside it is the earlier run's
            assert all(p.read_bytes() == earlier[k] for k, p in left.items()), sorted(left)

    reruns = kill_everywhere([*argv, "--out", str(out)], out, commits, over_the_earlier_eval,
                             check=one_run)
    assert all(without_timings(files) == clean for files in reruns)


def test_a_killed_render_never_mixes_frames_and_a_rerun_renders_the_same(scene, tmp_path):
    images = [str(scene.root / "images" / scene.names[i]) for i in (1, 3)]
    argv = ["render", "--checkpoint", "tiny_baseline", "--images", *images, "--cameras",
            str(scene.root / "sparse" / "0"), "--frames", "2"]
    code, commits = run(0, [*argv, "--out", str(tmp_path / "clean")])
    assert code == 0 and commits >= 5  # the PLY, 2 frames, the swap, the video
    clean = files_of(tmp_path / "clean")
    assert {"frames/0000.png", "frames/0001.png", "gaussians_frame0000.ply"} <= set(clean)
    # an earlier render of 3 frames in --out: none of its frames may survive beside the 2 new
    earlier_render = tmp_path / "earlier"
    assert run(0, [*argv[:-1], "3", "--out", str(earlier_render)])[0] == 0
    earlier = {k: v for k, v in files_of(earlier_render).items() if k.startswith("frames/")}
    assert len(earlier) == 3
    out = tmp_path / "render"

    def over_the_earlier_render():
        shutil.rmtree(out, ignore_errors=True)
        shutil.copytree(earlier_render, out)

    new = {k: v for k, v in clean.items() if k.startswith("frames/")}
    reruns = kill_everywhere([*argv, "--out", str(out)], out, commits, over_the_earlier_render,
                             {"frames/": [earlier, new]})
    assert all(files == clean for files in reruns)


def test_zz_the_counts(capsys):
    with capsys.disabled():
        print("\nkills: " + ", ".join(f"{n} {k}" for k, n in sorted(COUNTS.items())))
