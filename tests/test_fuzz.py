"""A fuzz suite for every reader: chunks, the scene records and images inside them, index
files, evaluation indices, PLY files, checkpoints and YAML configs. Each of the generated
corrupt inputs (truncations, random and flipped bytes, wrong types, dtypes and shapes, NaN
cameras, absurd sizes) must end in one of these ways:

- an error of a documented kind (``ValueError`` and its subclasses ``ConfigError``,
  ``BadChunkError``, ...; ``FileNotFoundError``) whose message names the file;
- for data read through the dataset: the scene or chunk skipped with a warning naming the
  file (and the scene, when the record has a key), the pass completing;
- read: only where the corruption can leave a valid file (a flipped byte in a weight, a
  camera or a comment; a YAML file cut at a line end, or empty; a checkpoint whose damage is
  in a part the reader does not use). Each case says whether it may be read; every other
  case must end in an error or a skip.

An exception of any other kind (a crash) fails the test, and so does an input that takes
longer than ``HANG_S`` seconds (a hang). The outcomes are counted per reader and printed
by the last test (``pytest tests/test_fuzz.py -q``); docs/reliability.md records
them."""

import collections
import io
import json
import logging
import signal
import zlib
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.data.fakes import fake_scene, write_plain_dataset
from usplat_dr.config import load_config
from usplat_dr.data.dataset import dataset_from_section
from usplat_dr.data.view_sampler import read_evaluation_index
from usplat_dr.model import UniqueSplat
from usplat_dr.model.ply import read_ply, write_ply
from usplat_dr.model.types import Gaussians
from usplat_dr.training.checkpoints import (
    init_from_checkpoint,
    load_model,
    training_image_shape,
)
from usplat_dr.training.config import RootCfg

# Per input. Every input here is read in well under a second (the slowest, a checkpoint of
# the tiny model, in ~0.1 s), so 30 s is a hang, not a slow machine. SIGALRM interrupts
# Python code only: a hang inside one C call would still stop the suite, not just fail it.
HANG_S = 30
DOCUMENTED = (ValueError, FileNotFoundError)  # ConfigError, BadChunkError, ... are ValueErrors
OUTCOMES = collections.Counter()  # (reader, outcome) -> inputs; printed by test_zz_the_counts
READ, ERROR, SKIP = "read", "error naming the file", "skip with a warning"


class Hang(Exception):
    pass


@contextmanager
def deadline(seconds: int):
    def on_alarm(signum, frame):
        raise Hang(f"no result after {seconds} s")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def guarded(reader: str, read):
    """``read()`` within ``HANG_S``; a hang or an undocumented exception (a crash) is counted,
    then fails the test."""
    try:
        with deadline(HANG_S):
            return read()
    except Hang:
        OUTCOMES[(reader, "hang")] += 1
        raise
    except DOCUMENTED:
        raise
    except Exception:
        OUTCOMES[(reader, "crash")] += 1
        raise


def expect_error_or_read(reader: str, path: Path, read, may_read: bool) -> None:
    """``read()`` raises a documented error naming ``path``, or (``may_read``) succeeds."""
    try:
        guarded(reader, read)
    except DOCUMENTED as e:
        assert path.name in str(e), f"{reader}: the error does not name {path}: {e}"
        OUTCOMES[(reader, ERROR)] += 1
        return
    assert may_read, f"{reader}: {path.name} was read, but it is corrupt"
    OUTCOMES[(reader, READ)] += 1


def mutations(raw: bytes, rng: np.random.Generator, count: int) -> list[tuple[str, bytes]]:
    """``count`` corruptions of ``raw`` as ``(kind, bytes)``: an empty file, then truncations,
    1-15 flipped bytes and random bytes (up to 4 KiB) in turn."""
    out = [("empty", b""), ("random", bytes(rng.integers(0, 256, 64, dtype=np.uint8)))]
    while len(out) < count:
        kind = len(out) % 3
        if kind == 0:
            out.append(("truncated", raw[:int(rng.integers(1, len(raw)))]))
        elif kind == 1:
            b = bytearray(raw)
            for i in rng.integers(0, len(raw), int(rng.integers(1, 16))):
                b[i] ^= int(rng.integers(1, 256))
            out.append(("flipped", bytes(b)))
        else:
            n = int(rng.integers(1, 4096))
            out.append(("random", bytes(rng.integers(0, 256, n, dtype=np.uint8))))
    return out


def _saved(obj) -> bytes:
    buf = io.BytesIO()
    torch.save(obj, buf)
    return buf.getvalue()


# ---- data read through the dataset ---------------------------------------------------------

def iterate(root: Path, caplog, index: Path | None = None, name: str = "re10k",
            reader: str = "data") -> list:
    """One pass over the test stage (``guarded``, as ``reader``); views from ``index``
    (default: frames 0, 4 -> 2 of s0, which a good scene has)."""
    if index is None:
        index = root / "index_default.json"
        index.write_text(json.dumps({"s0": {"context": [0, 4], "target": [2]}}))
    section = {"name": name, "roots": [str(root)], "image_shape": [16, 16],
               "overrides": {"original_image_shape": [32, 48]},
               "evaluation_index": str(index)}
    caplog.clear()
    return guarded(reader, lambda: list(dataset_from_section(section, "test")))


def warnings_of(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


def expect_skip(reader: str, root: Path, names: list[str], caplog, may_read: bool = False,
                index: Path | None = None, name: str = "re10k") -> None:
    """A pass over ``root`` yields the good example (``may_read``) or nothing, with a warning
    naming every one of ``names`` (the file, and the scene when known)."""
    examples = iterate(root, caplog, index, name, reader)
    if examples:
        assert may_read, f"{reader}: read, but the input is corrupt"
        OUTCOMES[(reader, READ)] += 1
        return
    warnings = warnings_of(caplog)
    assert any(all(n in w for n in names) for w in warnings), (
        f"{reader}: nothing read and no warning naming {names}: {warnings}")
    OUTCOMES[(reader, SKIP)] += 1


def scene(key: str = "s0", **changes) -> dict:
    s = fake_scene(key, 6, shape=(32, 48), fmt="png", seed=1)
    s.update(changes)
    return s


def png_claiming(width: int, height: int) -> torch.Tensor:
    """A PNG signature and IHDR chunk (valid CRC) for a huge image, then nothing."""
    ihdr = b"IHDR" + width.to_bytes(4, "big") + height.to_bytes(4, "big") + bytes([8, 2, 0, 0, 0])
    raw = (b"\x89PNG\r\n\x1a\n" + (13).to_bytes(4, "big") + ihdr
           + zlib.crc32(ihdr).to_bytes(4, "big"))
    return torch.frombuffer(bytearray(raw), dtype=torch.uint8)


def bad_records() -> list[tuple[str, object]]:
    """Scene records with a broken structure, camera or depth (reader "scene records")."""
    good = scene()
    images, cams = good["images"], good["cameras"]

    def cams_with(rows, cols, value):
        c = cams.clone()
        c[rows, cols] = value
        return c

    return [
        ("not a dict", "a string"),
        ("a tensor", torch.zeros(3)),
        ("no key", {k: v for k, v in good.items() if k != "key"}),
        ("key not str", scene(key=5)),
        ("no images", {k: v for k, v in good.items() if k != "images"}),
        ("images a tensor", scene(images=torch.zeros(6, 10, dtype=torch.uint8))),
        ("no views", scene(images=[], cameras=cams[:0], timestamps=torch.zeros(0))),
        ("NaN camera", scene(cameras=cams_with(2, 7, float("nan")))),
        ("Inf camera", scene(cameras=cams_with(0, 0, float("inf")))),
        ("zero focal length", scene(cameras=cams_with(slice(None), 0, 0.0))),
        ("singular rotation", scene(cameras=cams_with(1, slice(6, 15), 0.0))),
        ("not a rotation", scene(cameras=cams_with(1, 6, 3.0))),
        ("absurd camera values", scene(cameras=cams_with(slice(None), slice(6, None), 1e30))),
        ("cameras [V, 17]", scene(cameras=cams[:, :17])),
        ("cameras [V]", scene(cameras=cams[:, 0])),
        ("cameras int64", scene(cameras=cams.long())),  # fx 0.5 -> 0: no focal length
        ("fewer images", scene(images=images[:4])),
        ("timestamps [V+1]", scene(timestamps=torch.zeros(7, dtype=torch.int64))),
        ("depths a list", scene(depths=[0.0] * 6)),
        ("depths of another shape", scene(depths=torch.ones(6, 8, 8))),
        ("depths [V-1]", scene(depths=torch.ones(5, 32, 48))),
        ("depths int", scene(depths=torch.ones(6, 32, 48, dtype=torch.int32))),
    ]


def bad_images() -> list[tuple[str, list]]:
    """The ``images`` of a scene record, damaged (reader "images inside chunks")."""
    images = scene()["images"]
    jpeg = fake_scene("j", 6, (32, 48), "jpeg")["images"]
    g = torch.Generator().manual_seed(0)
    other = fake_scene("o", 6, (40, 48), "png")["images"]
    return [
        ("truncated PNG", [im[:len(im) // 2] for im in images]),
        ("PNG cut after the header", [im[:40] for im in images]),
        ("random bytes", [torch.randint(0, 256, (300,), dtype=torch.uint8, generator=g)
                          for _ in range(6)]),
        ("empty", [torch.zeros(0, dtype=torch.uint8)] * 6),
        ("float", [im.float() for im in images]),
        ("2-D", [im[None] for im in images]),
        ("None", [None] * 6),
        ("a list of ints", [im.tolist() for im in images]),
        ("PNG claiming 100000 x 100000", [png_claiming(100_000, 100_000)] * 6),
        ("PNG claiming 9000 x 9000", [png_claiming(9000, 9000)] * 6),
        ("PNG claiming 0 x 0", [png_claiming(0, 0)] * 6),
        ("JPEG cut short", [im[:200] for im in jpeg]),
        ("one frame of another shape", images[:2] + other[2:3] + images[3:]),
        ("flipped PNG data", [_flip(im, 60) for im in images]),
    ]


def _flip(image: torch.Tensor, at: int) -> torch.Tensor:
    out = image.clone()
    out[at] ^= 0xFF
    return out


RECORD_CASES, IMAGE_CASES = bad_records(), bad_images()


def test_a_good_scene_is_read(tmp_path, caplog):
    # the baseline the corruptions below start from
    write_plain_dataset(tmp_path, "test", [[scene()]])
    assert len(iterate(tmp_path, caplog)) == 1
    write_plain_dataset(tmp_path, "test", [[scene(cameras=scene()["cameras"].double())]])
    assert len(iterate(tmp_path, caplog)) == 1  # float64 cameras are cameras
    assert len(iterate(tmp_path, caplog, name="synth")) == 0  # no near_far: skipped
    write_plain_dataset(tmp_path, "test", [[scene(near_far=torch.tensor([1.0, 9.0]))]])
    assert len(iterate(tmp_path, caplog, name="synth")) == 1


@pytest.mark.parametrize("case", range(len(RECORD_CASES)), ids=[c[0] for c in RECORD_CASES])
def test_bad_scene_records_are_skipped_with_a_warning(case, tmp_path, caplog):
    _, record = RECORD_CASES[case]
    key = record.get("key") if isinstance(record, dict) else None
    # the index names the good scene's key; a record without one is still in the chunk
    write_plain_dataset(tmp_path, "test", [[record]], index={"s0": "000000.torch"})
    names = ["000000.torch"] + ([key] if isinstance(key, str) else [])
    expect_skip("scene records", tmp_path, names, caplog)


@pytest.mark.parametrize("case", range(len(IMAGE_CASES)), ids=[c[0] for c in IMAGE_CASES])
def test_bad_images_are_skipped_with_a_warning(case, tmp_path, caplog):
    _, images = IMAGE_CASES[case]
    write_plain_dataset(tmp_path, "test", [[scene(images=images)]])
    expect_skip("images inside chunks", tmp_path, ["000000.torch", "s0"], caplog)


NEAR_FAR_CASES = [[float("nan"), 1.0], [1.0, float("inf")], [2.0, 1.0], [-1.0, 3.0], [0.0, 0.0],
                  "near", [1.0], [[1.0, 2.0]]]


@pytest.mark.parametrize("near_far", NEAR_FAR_CASES, ids=[str(c) for c in NEAR_FAR_CASES])
def test_bad_near_far_of_synthetic_scenes_is_skipped(near_far, tmp_path, caplog):
    record = scene(near_far=torch.tensor(near_far) if isinstance(near_far, list) else near_far)
    write_plain_dataset(tmp_path, "test", [[record]])
    expect_skip("scene records", tmp_path, ["000000.torch", "s0"], caplog, name="synth")


def test_corrupt_chunk_files_are_skipped_with_a_warning(tmp_path, caplog):
    rng = np.random.default_rng(1)
    stage = write_plain_dataset(tmp_path / "base", "test", [[scene()]])
    cases = mutations((stage / "000000.torch").read_bytes(), rng, 40)
    cases += [("wrong type", _saved(obj)) for obj in
              ({"not": "a list"}, [1, 2, 3], "text", None, torch.zeros(3))]
    for i, (kind, content) in enumerate(cases):
        root = tmp_path / f"c{i}"
        chunk = write_plain_dataset(root, "test", [[scene()]]) / "000000.torch"
        chunk.write_bytes(content)
        # a record of wrong type is one skipped scene, named by the file only
        expect_skip("chunk files", root, [chunk.name], caplog, may_read=kind == "flipped")


def test_corrupt_index_files_name_the_file(tmp_path, caplog):
    rng = np.random.default_rng(2)
    good = json.dumps({"s0": "000000.torch"}).encode()
    cases = mutations(good, rng, 14) + [
        ("wrong type", c) for c in (b"[1, 2]", b'{"s0": 5}', b'"text"', b"\xff\xfe\x00",
                                    b'{"s0": null}', b'{"s0": "../000000.torch"}',
                                    b'{"s0": "/etc/passwd"}', b'{"s0": ""}')]
    # an index naming a chunk that is not there: a warning; the scene is found in its chunk
    cases.append(("missing chunk", b'{"s0": "missing.torch"}'))
    for i, (kind, content) in enumerate(cases):
        root = tmp_path / f"i{i}"
        stage = write_plain_dataset(root, "test", [[scene()]])
        (stage / "index.json").write_bytes(content)
        try:
            examples = iterate(root, caplog, reader="index.json")
        except DOCUMENTED as e:
            assert "index.json" in str(e), e
            OUTCOMES[("index.json", ERROR)] += 1
            continue
        warnings = warnings_of(caplog)
        assert any("missing.torch" in w for w in warnings), warnings
        assert kind == "missing chunk" and len(examples) == 1
        OUTCOMES[("index.json", READ)] += 1


def test_corrupt_evaluation_indices_name_the_file(tmp_path, caplog):
    rng = np.random.default_rng(3)
    write_plain_dataset(tmp_path, "test", [[scene()]])
    good = json.dumps({"s0": {"context": [0, 4], "target": [2]}}).encode()
    entries = [[], {"context": [0, 4]}, {"context": [], "target": [1]},
               {"context": [0, -4], "target": [1]}, {"context": ["a"], "target": [1]},
               {"context": [0.5], "target": [1]}, {"context": "04", "target": [1]},
               {"context": 4, "target": 2}, {"context": {"0": 1}, "target": [1]},
               {"context": [True, 4], "target": [2]}, {"context": [0, None], "target": [2]},
               "s0", 7]
    cases = mutations(good, rng, 16) + [("wrong type", json.dumps({"s0": e}).encode())
                                        for e in entries]
    for i, (kind, content) in enumerate(cases):
        index = tmp_path / f"index{i}.json"
        index.write_bytes(content)
        # a flip can turn the key "s0" into another: valid JSON, with no entry for s0
        expect_error_or_read("evaluation indices", index,
                             lambda: read_evaluation_index(index), may_read=kind == "flipped")  # noqa: B023 (called in this iteration)
    # an entry naming frames the scene does not have: valid JSON, the scene skipped with a
    # warning naming the index, the chunk and the scene (and no overflow at 10**30)
    for frame in (6, 10**12, 10**30):
        index = tmp_path / f"frames{frame}.json"
        index.write_text(json.dumps({"s0": {"context": [0, frame], "target": [2]}}))
        expect_skip("evaluation indices", tmp_path, [index.name, "000000.torch", "s0"],
                    caplog, index=index)


# ---- PLY, checkpoints, configs -------------------------------------------------------------

def test_corrupt_ply_files_name_the_file(tmp_path):
    rng = np.random.default_rng(4)
    g = torch.Generator().manual_seed(0)
    a = torch.randn(1, 30, 3, 3, generator=g) * 0.1
    gaussians = Gaussians(means=torch.randn(1, 30, 3, generator=g),
                          covariances=a @ a.transpose(-1, -2) + 1e-3 * torch.eye(3),
                          harmonics=torch.randn(1, 30, 3, 16, generator=g),
                          opacities=torch.rand(1, 30, generator=g),
                          scales=torch.ones(1, 30, 3), rotations=torch.zeros(1, 30, 4))
    raw = write_ply(tmp_path / "good.ply", gaussians).read_bytes()
    read_ply(tmp_path / "good.ply")  # the baseline
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header, body = raw[:end], raw[end:]
    record = len(body) // 30
    names = [line.split()[-1] for line in header.decode().splitlines()
             if line.startswith("property")]

    def with_value(prop: str, value: float, vertex: int = 3) -> bytes:
        b = bytearray(body)
        at = vertex * record + 4 * names.index(prop)  # every property is a float32
        b[at:at + 4] = np.float32(value).tobytes()
        return header + bytes(b)

    cases = mutations(raw, rng, 30)
    cases += [("absurd size", raw.replace(b"element vertex 30", b"element vertex " + n))
              for n in (b"1000000000000", b"31", b"-5", b"3O")]
    cases += [("absurd size", raw.replace(b"element vertex 30",
                                          b"element face 1000000000000\n"
                                          b"property uchar x\nelement vertex 30"))]
    for _ in range(10):  # flipped bytes inside the header only
        b = bytearray(raw)
        for i in rng.integers(0, len(header), 3):
            b[i] ^= int(rng.integers(1, 256))
        cases.append(("header", bytes(b)))
    cases += [("wrong type", raw.replace(b"property float opacity", b"property uint24 opacity")),
              ("wrong type", raw.replace(b"property float f_rest_3", b"property float x")),
              ("wrong type", raw.replace(b"binary_little_endian", b"ascii")),
              ("wrong type", raw.replace(b"property float opacity", b"property")),
              ("NaN", with_value("x", float("nan"))), ("Inf", with_value("f_dc_1", float("inf"))),
              ("absurd size", with_value("scale_0", 1e4))]
    for i, (kind, content) in enumerate(cases):
        path = tmp_path / f"p{i}.ply"
        path.write_bytes(content)
        # a flip in the data is a changed Gaussian (unless it makes a NaN: an error);
        # in the header it can leave a valid one ("comment" -> "comMent" in a comment line)
        expect_error_or_read("PLY files", path, lambda: read_ply(path),  # noqa: B023 (called in this iteration)
                             may_read=kind in ("flipped", "header"))


def test_corrupt_checkpoints_name_the_file(tmp_path, caplog):
    caplog.set_level(logging.ERROR, logger="usplat_dr.model.hypernet.resnet")
    rng = np.random.default_rng(5)
    model = UniqueSplat.from_preset("tiny", variant="baseline")
    state = {"model": model.state_dict(), "model_config": model.cfg.to_dict(), "step": 3,
             "config": {"dataset": {"image_shape": [32, 32]}}}
    cfg = state["model_config"]
    first = next(iter(state["model"]))

    def with_weight(value) -> bytes:
        return _saved({**state, "model": {**state["model"], first: value}})

    def with_primary(**changes) -> bytes:
        return _saved({**state, "model_config": {**cfg, "primary": {**cfg["primary"],
                                                                     **changes}}})

    nan = state["model"][first].clone()
    nan.view(-1)[0] = float("nan")
    # (kind, bytes, the readers that may read it: the parts they use are intact)
    weights_only, config_only = {"image shape"}, {"load_model", "init_from"}
    cases = [(kind, c, {"load_model", "image shape", "init_from"} if kind == "flipped" else
              set()) for kind, c in mutations(_saved(state), rng, 30)]
    cases += [("wrong type", c, set()) for c in (_saved([1, 2]), _saved("text"))]
    cases += [("wrong type", c, weights_only) for c in (
        _saved({"model": {}}), _saved({**state, "model_config": "tiny"}),
        _saved({**state, "model_config": {"no_such_field": 1}}),
        _saved({**state, "model_config": {**cfg, "variant": "z"}}),
        _saved({**state, "model": {k: v for k, v in list(state["model"].items())[1:]}}),
        _saved({**state, "model": [1, 2]}), _saved({**state, "model": {5: torch.zeros(1)}}),
        with_weight(torch.zeros(1)), with_weight("not a tensor"), with_weight(nan),
        with_weight(state["model"][first].long()),
        with_weight(state["model"][first].to(torch.complex64)))]
    cases += [("absurd size", c, weights_only) for c in (
        with_primary(d_feature=10**6), with_primary(num_depth_candidates=10**9),
        with_primary(d_feature=-3),
        with_primary(depth_unet_feat_dim=10**7))]
    cases += [("wrong type", _saved({**state, "config": config}), config_only) for config in (
        {"dataset": {"image_shape": "ab"}}, {"dataset": {"image_shape": [10**6, 10**6]}},
        {"dataset": {"image_shape": [32, True]}}, {"dataset": [32, 32]}, [1])]
    baseline = UniqueSplat.from_preset("tiny", variant="baseline")
    readers = {"load_model": load_model, "image shape": training_image_shape,
               "init_from": lambda path: init_from_checkpoint(baseline, path)}
    for i, (kind, content, readable) in enumerate(cases):
        path = tmp_path / f"k{i}.ckpt"
        path.write_bytes(content)
        # eval/render/export-ply's model, the image shape they default to, model.init_from;
        # a flip in a weight's bytes is another weight (unless it makes a NaN: an error)
        for name, read in readers.items():
            expect_error_or_read(f"checkpoints ({name})", path, lambda: read(path),  # noqa: B023 (called in this iteration)
                                 may_read=name in readable)


def test_corrupt_yaml_configs_name_the_file(tmp_path):
    rng = np.random.default_rng(6)
    good = (b"include: [synthetic_tiny.yaml]\ntrain:\n  steps: 10\noptimizer:\n  lr: 1.0e-3\n"
            b"dataset:\n  image_shape: [32, 32]\n")
    RootCfg.load(load_config([_written(tmp_path / "good.yaml", good)]))  # the baseline
    cases = mutations(good, rng, 20) + [("wrong type", c) for c in (
        b"train: [1, 2]\n", b"train:\n  steps: abc\n", b"train:\n  stepz: 3\n", b"- a\n- b\n",
        b"include: [missing.yaml]\n", b"include: [self.yaml]\n", b"include: {a: 1}\n",
        b"train:\n\tsteps: 3\n", b"a: " + b"[" * 500 + b"]" * 500 + b"\n",
        b"train: {steps: 10\n", b"optimizer:\n  lr: .nan\n", b"threads: -3\n",
        b"train:\n  1: 3\n  x: 2\n", b"loss:\n  mse: -1\n",
        b"dataset:\n  name: imagenet\n", b"dataset:\n  roots: 5\n", b"dataset: [1]\n",
        b"dataset:\n  image_shape: ab\n", b"dataset:\n  image_shape: [32]\n",
        b"dataset:\n  image_shape: [1000000, 1000000]\n", b"dataset:\n  image_shape: [0, 32]\n",
        b"dataset:\n  overrides: {nearr: 1}\n", b"dataset:\n  overrides: {near: 5, far: 1}\n",
        b"dataset:\n  overrides: {skip_bad_shape: maybe}\n", b"dataset:\n  overrides: [1]\n",
        b"dataset:\n  view_sampler: {name: random}\n",
        b"dataset:\n  view_sampler: {num_target_views: four}\n",
        b"dataset:\n  view_sampler: {name: evaluation}\n")]
    for i, (kind, content) in enumerate(cases):
        path = tmp_path / ("self.yaml" if b"self.yaml" in content else f"y{i}.yaml")
        path.write_bytes(content)
        # YAML cut at a line end, or a flipped digit, can be a valid config; an empty file is
        # an empty mapping (the defaults)
        expect_error_or_read("YAML configs", path, lambda: RootCfg.load(load_config([path])),  # noqa: B023 (called in this iteration)
                             may_read=kind in ("flipped", "truncated", "empty"))


def _written(path: Path, content: bytes) -> Path:
    path.write_bytes(content)
    return path


def test_zz_the_counts(capsys):
    # runs last in this file (pytest keeps the file's order): the totals of the suite above
    by_reader = collections.defaultdict(dict)
    for (reader, outcome), n in sorted(OUTCOMES.items()):
        by_reader[reader][outcome] = n
    reads = sum(OUTCOMES.values())
    # each checkpoint file is read three ways (model, image shape, init_from): one input
    inputs = reads - sum(sum(by_reader.get(f"checkpoints ({r})", {}).values())
                         for r in ("image shape", "init_from"))
    crashes = sum(n for (_, outcome), n in OUTCOMES.items() if outcome == "crash")
    hangs = sum(n for (_, outcome), n in OUTCOMES.items() if outcome == "hang")
    with capsys.disabled():
        # the first crash or hang of a test stops it: a test that failed otherwise (a read
        # that should not have been, a message without the file) is reported by pytest
        print(f"\nfuzz: {inputs} corrupt inputs ({reads} reads), {crashes} crashes, {hangs} "
              f"hangs; each read an error naming the file, a skip with a warning naming file "
              f"and scene, or (where the damage leaves a valid file) read")
        for reader, outcomes in by_reader.items():
            print(f"  {reader}: {sum(outcomes.values())}: "
                  + ", ".join(f"{n} {o}" for o, n in outcomes.items()))
    assert crashes == 0 and hangs == 0, (crashes, hangs)
    if reads:  # the file was run as a whole (not one selected test)
        assert inputs >= 200, inputs
