"""Provenance and portable numerics: the dataset hash follows the bytes, the environment
record, and Dr.Jit's LLVM target pinned (or not) by USPLAT_PORTABLE in a fresh process."""

import json
import os
import subprocess
import sys

import pytest

from usplat_dr import portable
from usplat_dr.evaluation.provenance import dataset_hash, environment, provenance


def test_dataset_hash_follows_the_bytes(tmp_path):
    (tmp_path / "train").mkdir()
    (tmp_path / "train" / "index.json").write_text('{"a": "000000.torch"}')
    (tmp_path / "train" / "000000.torch").write_bytes(b"\x00" * 100)
    (tmp_path / "unrelated.txt").write_text("not data")
    first = dataset_hash(tmp_path)
    (tmp_path / "unrelated.txt").write_text("changed")  # not part of the data
    assert dataset_hash(tmp_path) == first
    (tmp_path / "train" / "000000.torch").write_bytes(b"\x00" * 99 + b"\x01")
    assert dataset_hash(tmp_path) != first
    with pytest.raises(FileNotFoundError, match="no dataset files"):
        dataset_hash(tmp_path / "train" / "none")
    assert provenance([tmp_path, tmp_path / "missing"])["data"] == {
        str(tmp_path): dataset_hash(tmp_path)}


def test_environment_names_versions_cpu_and_threads():
    info = environment()
    assert info["torch"] and info["drjit"] and info["mitsuba"] and info["cpu"]
    assert info["torch_threads"] >= 1 and "portable" in info["numerics"]
    json.dumps(info)  # plain data: goes into checkpoints and JSON reports


SCRIPT = """
import json, usplat_dr
from usplat_dr import portable
from usplat_dr.backend import require_llvm
require_llvm()
print(json.dumps({"target": portable.drjit_target(), "env": portable.describe()}))
"""


def _target(value: str) -> dict:
    env = {k: v for k, v in os.environ.items()
           if k not in portable.TORCH_ENV and k != portable.ENV_VAR}
    env[portable.ENV_VAR] = value
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True,
                         text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


@pytest.mark.skipif(not portable._host_has_avx2_fma(),
                    reason="portable numerics pin the AVX2 code path; this CPU has no AVX2")
def test_usplat_portable_pins_the_drjit_target():
    pinned = _target("1")
    cpu, features, lanes = portable.DRJIT_TARGET
    assert pinned["target"] == [cpu, features, lanes]
    assert pinned["env"]["drjit_target"] == [cpu, features, lanes]
    host = _target("0")  # the host's own target, not pinned
    assert host["target"][0] != "" and host["env"]["drjit_target"] is None


UNPIN = """
import json, usplat_dr
from usplat_dr import portable
from usplat_dr.backend import require_llvm
host = portable.drjit_target()
require_llvm()  # pins
pinned = portable.drjit_target()
portable.unpin_drjit()
print(json.dumps({"host": host, "pinned": pinned, "after": portable.drjit_target(),
                  "env": portable.describe()}))
"""


@pytest.mark.skipif(not portable._host_has_avx2_fma(),
                    reason="portable numerics pin the AVX2 code path; this CPU has no AVX2")
def test_unpin_gives_the_host_target_back():
    env = {**os.environ, portable.ENV_VAR: "1"}
    out = subprocess.run([sys.executable, "-c", UNPIN], env=env, capture_output=True,
                         text=True, check=True).stdout
    r = json.loads(out.strip().splitlines()[-1])
    assert r["pinned"] == list(portable.DRJIT_TARGET)
    assert r["after"] == r["host"] and r["env"]["drjit_target"] is None


def test_enable_sets_the_torch_environment(monkeypatch):
    for key in (portable.ENV_VAR, *portable.TORCH_ENV):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("MKL_CBWR", "COMPATIBLE")  # a user's own choice wins
    portable.enable()
    assert os.environ[portable.ENV_VAR] == "1"
    assert os.environ["ATEN_CPU_CAPABILITY"] == "avx2"
    assert os.environ["MKL_CBWR"] == "COMPATIBLE"
