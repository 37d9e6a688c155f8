"""The clone stays light: no tracked file over 1 MiB but a shipped checkpoint (one named in
checkpoints/manifest.json) and the MVSplat fixture, and no blob over 1 MiB added by the
commits after the base named in docs/reproducibility.md ("What a clone costs")."""

import json
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MIB = 1 << 20
#: The commit from which the rule holds; the history before it keeps old study states.
BASE = "ff87623d7adf"
#: Files allowed over 1 MiB besides the shipped checkpoints, with the reason.
ALLOWED = {"tests/fixtures/mvsplat_fixture_dev.pt":
           "the official MVSplat layer outputs the loader is checked against"}


def allowed() -> set[str]:
    manifest = json.loads((ROOT / "checkpoints" / "manifest.json").read_text())
    names = {f"checkpoints/{Path(e['file']).name}" for e in manifest if "file" in e}
    assert names, "checkpoints/manifest.json names no checkpoint file: the test reads it wrong"
    return names | set(ALLOWED)


def git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout


@pytest.fixture(scope="module")
def repo():
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.fail("the clone-size tests read the git repository: run them in a clone")
    return ROOT


def test_no_large_file_in_the_tree(repo):
    ok = allowed()
    big = {p: (ROOT / p).stat().st_size for p in git("ls-files").splitlines()
           if (ROOT / p).is_file() and (ROOT / p).stat().st_size > MIB and p not in ok}
    assert not big, (f"tracked files over 1 MiB: {big}; keep training states under outputs/ "
                     "and commit the commands and small results that reproduce them")


def test_no_large_blob_since_the_base(repo):
    ok = allowed()
    have_base = subprocess.run(["git", "cat-file", "-e", f"{BASE}^{{commit}}"], check=False,
                               cwd=ROOT,
                               capture_output=True).returncode == 0
    # a shallow clone without the base checks the commits it has (at least HEAD's tree)
    rev = ["HEAD", "--not", BASE] if have_base else ["HEAD"]
    objects = git("rev-list", "--objects", *rev)
    check = subprocess.run(["git", "cat-file", "--batch-check=%(objecttype) %(objectsize) %(rest)"],
                           cwd=ROOT, input=objects, capture_output=True, text=True, check=True)
    big = []
    for line in check.stdout.splitlines():
        kind, size, *path = line.split(" ", 2)
        if kind == "blob" and int(size) > MIB and (path[0] if path else "") not in ok:
            big.append((path[0] if path else "?", int(size)))
    assert not big, f"blobs over 1 MiB added after {BASE}: {big} (docs/reproducibility.md)"
