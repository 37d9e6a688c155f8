"""The attack suite: inputs written to make the project write outside its folder, hand data
to an interpreter, take unbounded memory or time, or stop a run that should skip a record.
It grows from the fuzz suite (``tests/test_fuzz.py``: its guards and fakes) and counts its
outcomes per class; the last test prints them (``pytest tests/test_attacks.py -q -s``) and
docs/reliability.md records them. Process faults (SIGKILL, two runs on one
folder, a full disk) are in ``tests/training/test_run_safety.py``.

Each input must end in a documented way: an error naming the file or value (``ValueError``
and its subclasses), or the record skipped with a warning and the pass going on. A crash
(any other exception), a hang (no result in ``HANG_S``), a file written outside the output
folder, or a special file replaced fails the test and is counted."""

import collections
import io
import json
import os
import subprocess
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from tests.data.fakes import write_plain_dataset
from tests.test_fuzz import deadline, iterate, png_claiming, scene, warnings_of
from usplat_dr.config import ConfigError, load_config, parse
from usplat_dr.data.chunks import BadChunkError, decode_image, read_chunk, read_index
from usplat_dr.data.view_sampler import read_evaluation_index
from usplat_dr.io import torch_save, write_json
from usplat_dr.io.images import save_png
from usplat_dr.io.names import safe_stem
from usplat_dr.model.uniquesplat import UniqueSplatCfg

# Every input here ends in well under a second on an idle machine (the evaluation of 6
# scenes with the tiny model takes ~3 s, and has 6x longer); 20 s means it did not end.
HANG_S = 20
COUNTS = collections.Counter()  # (class, outcome) -> inputs; printed by test_zz_the_counts
PATHS, DECODING, BOUNDS, SKIPS = ("writes outside the folder", "data reaching an interpreter",
                                  "unbounded memory or time", "one bad record stops a run")


def hostile_keys(rng: np.random.Generator, count: int) -> list[str]:
    """Scene keys that name other folders, are too long for a file name, or hold bytes a
    file name cannot: fixed classics, then random mixtures of the dangerous parts."""
    fixed = ["../../../../../escaped", "/tmp/absolute", "..", ".", "", "a/../../b", "~root",
             "x" * 300, "nul\x00byte", "new\nline", "back\\slash", ".hidden", "-rf", "é" * 200,
             "\u202ereversed", "con", "a" * 96, "a" * 97, "..\\..\\win", "/", "//", "a:b*c?"]
    parts = ["..", "/", "\\", "\x00", "\n", ".", "é", "€", " ", "x", "0", "-", "_", "~",
             "\x7f", "\U0001f600", "a" * 50]
    keys = list(fixed)
    while len(keys) < count:
        n = int(rng.integers(1, 12))
        keys.append("".join(parts[int(i)] for i in rng.integers(0, len(parts), n)))
    return keys


def files_under(root: Path) -> set[Path]:
    return {p for p in root.rglob("*")}


# ---- 1. paths ------------------------------------------------------------------------------

def test_every_hostile_key_names_a_file_inside_its_folder(tmp_path):
    keys = hostile_keys(np.random.default_rng(0), 400)
    stems = {}
    for key in keys:
        stem = safe_stem(key)
        target = (tmp_path / f"fit_{stem}.png")
        # inside the folder, a file name of <= 255 bytes, no NUL: the writer can open it
        assert target.resolve().parent == tmp_path.resolve(), (key, stem)
        assert len(target.name.encode()) <= 255 and "\x00" not in stem and stem not in (
            "", ".", ".."), (key, stem)
        assert stems.setdefault(stem, key) == key, f"{key!r} and {stems[stem]!r} share {stem}"
        COUNTS[(PATHS, "inside")] += 1
    # the field's keys are kept as they are (RealEstate10K: 16 hex digits)
    assert safe_stem("5aca87f95a9412c6") == "5aca87f95a9412c6"


def test_evaluation_writes_hostile_keys_inside_its_folder(tmp_path):
    from usplat_dr.evaluation import evaluate
    from usplat_dr.model import UniqueSplat

    keys = ["../../../../escaped", str(tmp_path / "absolute"), "k" * 300, "nul\x00byte",
            "a/b", "plain"]
    data, out = tmp_path / "data", tmp_path / "run" / "eval"
    write_plain_dataset(data, "test", [[scene(k) for k in keys]])
    index = tmp_path / "index.json"
    index.write_text(json.dumps({k: {"context": [0, 4], "target": [2]} for k in keys}))
    before = files_under(tmp_path)
    torch.manual_seed(0)
    model = UniqueSplat.from_preset("tiny", variant="baseline")
    with deadline(6 * HANG_S):  # a model's forward passes: slower on a loaded 2-core machine
        summary = evaluate(model, {"name": "re10k", "roots": [str(data)], "image_shape": [32, 32],
                                   "overrides": {"original_image_shape": [32, 48]}},
                           {"standard": str(index)}, out, progress=False, images_per_split=10)
    assert summary["splits"]["standard"]["scenes"] == len(keys)
    new = files_under(tmp_path) - before
    outside = [p for p in new if not p.is_relative_to(out) and p not in out.parents]
    assert not outside, outside
    renders = sorted((out / "renders" / "standard").iterdir())
    assert len(renders) == len(keys)
    # the key itself is kept inside each file
    found = {json.loads(Image.open(p).text["scene"]) for p in renders}
    assert found == set(keys)
    COUNTS[(PATHS, "inside")] += len(keys)


def special_files(tmp_path: Path) -> list[tuple[str, Path]]:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    (tmp_path / "folder").mkdir()
    return [("character device", Path("/dev/null")), ("FIFO", fifo),
            ("folder", tmp_path / "folder")]


@pytest.mark.parametrize("writer", ["json", "png", "torch"])
def test_special_files_are_never_renamed_over(writer, tmp_path):
    write = {"json": lambda p: write_json(p, {"a": 1}),
             "png": lambda p: save_png(p, np.zeros((4, 4, 3))),
             "torch": lambda p: torch_save({"a": torch.zeros(1)}, p)}[writer]
    for kind, path in special_files(tmp_path):
        mode = os.stat(path).st_mode
        with deadline(HANG_S), pytest.raises(ValueError, match="not a regular file"):
            write(path)
        assert os.stat(path).st_mode == mode, f"{kind} {path} was replaced"
        COUNTS[(PATHS, "refused")] += 1
    assert not list(tmp_path.glob(".*.tmp"))  # no temporary file left behind


def test_chunks_that_link_outside_the_root_or_are_not_files_are_skipped(tmp_path, caplog):
    root = tmp_path / "data"
    stage = write_plain_dataset(root, "test", [[scene("s0")]])
    outside = tmp_path / "elsewhere.torch"
    torch.save([scene("s1")], outside)
    (stage / "000001.torch").symlink_to(outside)
    os.mkfifo(stage / "000002.torch")
    (stage / "index.json").write_text(json.dumps(
        {"s0": "000000.torch", "s1": "000001.torch", "s2": "000002.torch"}))
    examples = iterate(root, caplog)
    assert [e["scene"] for e in examples] == ["s0"]
    warnings = " ".join(warnings_of(caplog))
    assert "outside the dataset root" in warnings and "not a regular file" in warnings
    COUNTS[(PATHS, "skipped with a warning")] += 2


# ---- 2. decoding ---------------------------------------------------------------------------

def encoded(fmt: str, **kwargs) -> torch.Tensor:
    buf = io.BytesIO()
    Image.fromarray(np.full((8, 8, 3), 200, np.uint8)).save(buf, format=fmt, **kwargs)
    return torch.frombuffer(bytearray(buf.getvalue()), dtype=torch.uint8)


def raw(data: bytes) -> torch.Tensor:
    return torch.frombuffer(bytearray(data), dtype=torch.uint8)


def other_formats() -> list[tuple[str, torch.Tensor]]:
    """Images Pillow could decode, none of them PNG or JPEG, and bytes meant for external
    programs (Ghostscript for EPS/PS/PDF)."""
    eps = (b"%!PS-Adobe-3.0 EPSF-3.0\n%%BoundingBox: 0 0 8 8\n"
           b"(%pipe%touch /tmp/usplat_pwned) (w) file\nshowpage\n%%EOF\n")
    cases = [(f, encoded(f)) for f in ("GIF", "BMP", "TIFF", "PPM", "ICO", "TGA", "PCX", "SGI",
                                       "DDS", "QOI") if _can_write(f)]
    cases += [("EPS", raw(eps)), ("PS", raw(b"%!PS\n" + eps[24:])),
              ("PDF", raw(b"%PDF-1.4\n1 0 obj<<>>endobj\ntrailer<<>>\n%%EOF")),
              ("XBM", raw(b"#define a_width 8\n#define a_height 8\nstatic char a_bits[] = "
                          b"{0,0,0,0,0,0,0,0};\n")),
              ("SVG", raw(b"<svg xmlns='http://www.w3.org/2000/svg'/>"))]
    return cases


def _can_write(fmt: str) -> bool:
    try:
        encoded(fmt)
    except (KeyError, OSError, ValueError):
        return False
    return True


def test_only_png_and_jpeg_are_decoded_and_no_program_runs(monkeypatch):
    ran = []

    def refuse(*args, **kwargs):
        ran.append(args)
        raise AssertionError(f"a program was started on data: {args}")

    monkeypatch.setattr(subprocess, "Popen", refuse)
    for fmt, data in other_formats():
        with deadline(HANG_S), pytest.raises(ValueError, match="cannot be decoded"):
            decode_image(data)
        COUNTS[(DECODING, "refused")] += 1
    assert not ran and not Path("/tmp/usplat_pwned").exists()
    for fmt in ("PNG", "JPEG"):
        assert decode_image(encoded(fmt)).shape == (3, 8, 8)


def png_16bit(values: np.ndarray) -> bytes:
    """A 16-bit PNG written from the specification (grey: colour type 0; RGB: 2), big-endian
    samples, filter 0 on every row: Pillow cannot write 16-bit RGB."""
    h, w = values.shape[:2]
    colour = 2 if values.ndim == 3 else 0

    def chunk(tag: bytes, data: bytes) -> bytes:
        return (len(data).to_bytes(4, "big") + tag + data
                + zlib.crc32(tag + data).to_bytes(4, "big"))

    rows = b"".join(b"\x00" + values[y].astype(">u2").tobytes() for y in range(h))
    ihdr = w.to_bytes(4, "big") + h.to_bytes(4, "big") + bytes([16, colour, 0, 0, 0])
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(rows))
            + chunk(b"IEND", b""))


def test_16_bit_pngs_decode_to_the_right_values():
    rng = np.random.default_rng(1)
    for i in range(40):
        shape = (int(rng.integers(1, 9)), int(rng.integers(1, 9))) + ((3,) if i % 2 else ())
        values = rng.integers(0, 65536, shape).astype(np.uint16)
        values.flat[0], values.flat[-1] = 0, 65535
        got = decode_image(raw(png_16bit(values))).permute(1, 2, 0).numpy().astype(int)
        want = np.rint(values.astype(np.float64) * 255 / 65535).astype(int)
        if values.ndim == 2:
            want = np.repeat(want[..., None], 3, axis=-1)
        # grey: scaled and rounded exactly; RGB: Pillow keeps each sample's high byte
        # (v >> 8), within 1 of the rounded value
        tol = 1 if values.ndim == 3 else 0
        assert np.abs(got - want).max() <= tol, (values, got)
        COUNTS[(DECODING, "16-bit decoded right")] += 1


# ---- 3. bounds -----------------------------------------------------------------------------

def yaml_bomb(levels: int, width: int) -> str:
    lines = [f"a0: &a0 [{', '.join(['x'] * width)}]"]
    for i in range(1, levels):
        lines.append(f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * width)}]")
    return "\n".join(lines) + "\n"


def yaml_attacks() -> list[tuple[str, str]]:
    # width^levels nodes: from 5x10^5 (5 x the bound) to 40^12
    cases = [(f"aliases {lv}x{w}", yaml_bomb(lv, w))
             for lv in (6, 9, 12) for w in (9, 10, 20, 40)] + [("aliases 4x18", yaml_bomb(4, 18))]
    cases += [("recursive alias", "a: &a [*a]\n"),
              ("recursive mapping", "a: &a {b: *a}\n"),
              ("nested 100k lists", "a: " + "[" * 100_000 + "]" * 100_000 + "\n"),
              ("nested 100k maps", "a: " + "{b: " * 50_000 + "1" + "}" * 50_000 + "\n"),
              ("10 MB of text", "a: " + "x" * 10_000_000 + "\n")]
    return cases


def test_yaml_configs_are_bounded_before_expansion(tmp_path):
    for i, (kind, text) in enumerate(yaml_attacks()):
        path = tmp_path / f"bomb{i}.yaml"
        path.write_text(text)
        with deadline(HANG_S), pytest.raises(ConfigError) as e:
            load_config([str(path)])
        assert path.name in str(e.value), (kind, e.value)
        COUNTS[(BOUNDS, "refused")] += 1
        with deadline(HANG_S), pytest.raises(ConfigError):  # the same text as an override
            load_config(["synthetic_tiny.yaml"], [f"train.x={text[3:]}"]
                        if kind.startswith("nested") else [f"train.x={text}"])
        COUNTS[(BOUNDS, "refused")] += 1
    # what the shipped configs hold still parses: anchors used a few times
    assert parse("a: &x {b: 1}\nc: *x\n") == {"a": {"b": 1}, "c": {"b": 1}}


def model_config_attacks() -> list[tuple[str, dict]]:
    cases = [("layers", {"primary": {"num_transformer_layers": 10 ** 6}}),
             ("depth candidates", {"primary": {"num_depth_candidates": 10 ** 7}}),
             ("features", {"primary": {"d_feature": 10 ** 6}}),
             ("U-Net levels", {"primary": {"depth_unet_channel_mult": [1] * 100_000}}),
             ("channel mult", {"primary": {"costvolume_unet_channel_mult": [1, 10 ** 6]}}),
             ("phi channels", {"phi_channels": [64] * 100_000}),
             ("phi width", {"phi_channels": [10 ** 7]}),
             ("embedding", {"embed_dim": 10 ** 8}),
             ("rank", {"delta_rank": 10 ** 6}),
             ("samples", {"proj_samples": 10 ** 6}),
             ("a string", {"embed_dim": "512"}),
             ("a float", {"hyper_hidden": 1e9}),
             ("negative", {"feature_dim": -5}),
             ("gaussians per pixel", {"primary": {"gaussians_per_pixel": 10 ** 5}})]
    return cases


def test_model_configs_are_bounded_before_building(tmp_path):
    from usplat_dr.training.checkpoints import load_model

    good = UniqueSplatCfg.from_dict({}).to_dict()
    for i, (kind, change) in enumerate(model_config_attacks()):
        with deadline(HANG_S), pytest.raises(ValueError):
            UniqueSplatCfg.from_dict({**change})
        # the same inside a checkpoint: refused before a module is built
        cfg = {**good, **change}
        if "primary" in change:
            cfg["primary"] = {**good["primary"], **change["primary"]}
        path = torch_save({"model_config": cfg, "state_dict": {}, "step": 0},
                          tmp_path / f"ckpt{i}.pt")
        with deadline(HANG_S), pytest.raises(ValueError) as e:
            load_model(path)
        assert path.name in str(e.value), (kind, e.value)
        COUNTS[(BOUNDS, "refused")] += 2


def deflated(obj: object, path: Path) -> Path:
    """``obj`` saved by torch.save, then re-packed with every record deflated: a file that
    inflates ``ratio`` times."""
    plain = io.BytesIO()
    torch.save(obj, plain)
    with zipfile.ZipFile(plain) as zi, zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zo:
        for info in zi.infolist():
            zo.writestr(info.filename, zi.read(info.filename))
    return path


def test_compressed_archives_are_refused_before_inflating(tmp_path, caplog):
    from usplat_dr.training.checkpoints import load_model

    for i, mb in enumerate((1, 16, 64)):
        big = torch.zeros(mb * 2 ** 18)  # mb MiB of zeros: deflates ~1000x
        chunk = deflated([scene("s0", filler=big)], tmp_path / f"c{i}.torch")
        assert chunk.stat().st_size < mb * 2 ** 20 / 50
        with deadline(HANG_S), pytest.raises(BadChunkError, match="compressed records"):
            read_chunk(chunk)
        ckpt = deflated({"model_config": {}, "state_dict": {"w": big}}, tmp_path / f"m{i}.pt")
        with deadline(HANG_S), pytest.raises(ValueError, match="compressed records"):
            load_model(ckpt)
        COUNTS[(BOUNDS, "refused")] += 2
    root = tmp_path / "data"
    stage = write_plain_dataset(root, "test", [[scene("s0")]])
    deflated([scene("s0")], stage / "000000.torch")
    assert iterate(root, caplog) == []
    assert any("compressed records" in w for w in warnings_of(caplog))
    COUNTS[(BOUNDS, "skipped with a warning")] += 1


def test_deep_json_is_an_error_naming_the_file(tmp_path):
    for depth in (1_000, 10_000, 100_000, 1_000_000):
        for shape in ("[", '{"a":'):
            text = shape * depth + "1" + ("]" if shape == "[" else "}") * depth
            stage = tmp_path / f"d{depth}{len(shape)}"
            stage.mkdir()
            (stage / "index.json").write_text(text)
            with deadline(HANG_S), pytest.raises(ValueError) as e:
                read_index(stage)
            assert "index.json" in str(e.value)
            with deadline(HANG_S), pytest.raises(ValueError) as e:
                read_evaluation_index(stage / "index.json")
            assert "index.json" in str(e.value)
            COUNTS[(BOUNDS, "refused")] += 2


def test_images_are_bounded_after_resizing(tmp_path, caplog):
    # frames thin enough to pass the pixel cap, which the resize to cover 16x16 would blow up
    for i, (h, w) in enumerate([(1, 4_000_000), (4_000_000, 1), (2, 3_000_000)]):
        img = np.zeros((h, w, 3), np.uint8)
        buf = io.BytesIO()
        Image.fromarray(img).save(buf, format="PNG")
        data = raw(buf.getvalue())
        root = tmp_path / f"r{i}"
        write_plain_dataset(root, "test", [[scene("s0", images=[data] * 6)]])
        with deadline(HANG_S):
            examples = list(_pass(root, caplog))
        assert examples == [] and any("would be resized" in w for w in warnings_of(caplog))
        COUNTS[(BOUNDS, "skipped with a warning")] += 1
    # a header claiming a huge image is refused before decoding (the fuzz suite's case)
    with pytest.raises(ValueError, match="claims|cannot be decoded"):
        decode_image(png_claiming(100_000, 100_000))


def _pass(root: Path, caplog):
    from usplat_dr.data.dataset import dataset_from_section

    index = root / "index_default.json"
    index.write_text(json.dumps({"s0": {"context": [0, 4], "target": [2]}}))
    caplog.clear()
    # the shape check is off (as for DTU), so the odd frame reaches the resize
    return dataset_from_section({"name": "re10k", "roots": [str(root)], "image_shape": [16, 16],
                                 "overrides": {"skip_bad_shape": False},
                                 "evaluation_index": str(index)}, "test")


# ---- 4. records a run skips ----------------------------------------------------------------

NEAR_FAR = [(1e-30, 1e30), (1e-30, 1.0), (1.0, 1e30), (1e-7, 10.0), (1.0, 2e6), (0.0, 1.0),
            (-1.0, 1.0), (5.0, 5.0), (6.0, 5.0), (float("nan"), 1.0), (1.0, float("inf")),
            (1e38, 3e38), (-1e30, -1e29)]


def test_absurd_near_far_and_cameras_are_skipped(tmp_path, caplog):
    good = scene("s0")
    cams = good["cameras"]
    cases = [("near_far", {"near_far": torch.tensor(nf, dtype=torch.float32)})
             for nf in NEAR_FAR]
    for rows, cols, value in [(slice(None), 0, 1e30), (0, 1, 1e20), (1, 2, -1e9),
                              (slice(None), 15, 1e30), (2, 9, -1e12), (3, 17, 1e7)]:
        c = cams.clone()
        c[rows, cols] = value
        cases.append(("camera", {"cameras": c}))
    for i, (kind, change) in enumerate(cases):
        root = tmp_path / f"s{i}"
        write_plain_dataset(root, "test", [[scene("s0", **change)]])
        examples = iterate(root, caplog, name="synth" if kind == "near_far" else "re10k")
        assert examples == [], (kind, change)
        assert any("s0" in w and "000000.torch" in w for w in warnings_of(caplog)), kind
        COUNTS[(SKIPS, "skipped with a warning")] += 1


def odd_tensors() -> list[tuple[str, dict]]:
    good = scene("s0")
    img0 = good["images"][0]
    return [("sparse cameras", {"cameras": good["cameras"].to_sparse()}),
            ("meta cameras", {"cameras": torch.empty(6, 18, device="meta")}),
            ("sparse timestamps", {"timestamps": good["timestamps"].to_sparse()}),
            ("meta timestamps", {"timestamps": torch.empty(6, dtype=torch.int64,
                                                           device="meta")}),
            ("sparse image", {"images": [img0.to_sparse()] + good["images"][1:]}),
            ("meta image", {"images": [torch.empty(10, dtype=torch.uint8, device="meta")] * 6}),
            ("sparse depths", {"depths": torch.ones(6, 32, 48).to_sparse()}),
            ("meta depths", {"depths": torch.empty(6, 32, 48, device="meta")}),
            ("quantised cameras", {"cameras": torch.quantize_per_tensor(
                good["cameras"], 0.1, 0, torch.qint8)}),
            ("sparse near_far", {"near_far": torch.tensor([1.0, 100.0]).to_sparse()})]


@pytest.mark.filterwarnings("ignore::UserWarning")  # quantised tensors are deprecated
def test_sparse_meta_and_quantised_tensors_are_skipped(tmp_path, caplog):
    for i, (kind, change) in enumerate(odd_tensors()):
        root = tmp_path / f"t{i}"
        write_plain_dataset(root, "test", [[scene("s0", **change)]])
        examples = iterate(root, caplog)
        assert examples == [], kind
        assert any("s0" in w for w in warnings_of(caplog)), (kind, warnings_of(caplog))
        COUNTS[(SKIPS, "skipped with a warning")] += 1


def test_duplicate_keys_are_read_once(tmp_path, caplog):
    cases = {"two chunks": [[scene("s0")], [scene("s0")]],
             "one chunk": [[scene("s0"), scene("s0")]],
             "three copies": [[scene("s0")], [scene("s0"), scene("s0")]]}
    for i, (kind, chunks) in enumerate(cases.items()):
        root = tmp_path / f"d{i}"
        write_plain_dataset(root, "test", chunks)
        examples = iterate(root, caplog)
        assert [e["scene"] for e in examples] == ["s0"], kind
        assert any("duplicate key" in w for w in warnings_of(caplog)), kind
        COUNTS[(SKIPS, "read once, copies skipped")] += 1
    # two roots holding the same scene: read once
    examples = iterate(tmp_path / "d0", caplog)
    assert len(examples) == 1


# ---- own data: the importers' and render --images' doors ------------------------------------

READS = "reads outside what the user named"


def own_colmap(folder: Path, image: bytes | None = None, name: str = "a.png",
               size: tuple[int, int] = (64, 48)) -> Path:
    """A one-camera COLMAP text model (``tests.data.test_importers``'s) of two images, the
    first named ``name`` and holding ``image`` (a valid PNG when None), the second a valid
    ``b.png``, calibrated at ``size`` (W, H)."""
    from tests.data.test_importers import write_one_camera_colmap

    write_one_camera_colmap(folder)
    w, h = size
    (folder / "cameras.txt").write_text(f"1 PINHOLE {w} {h} 50 50 {w / 2} {h / 2}\n")
    (folder / "images.txt").write_text(f"1 1 0 0 0 0 0 5 1 {name}\n\n"
                                       f"2 1 0 0 0 1 0 5 1 b.png\n\n")
    Image.new("RGB", (w, h)).save(folder / "images" / "b.png")
    if image is not None:
        (folder / "images" / "a.png").write_bytes(image)
    return folder


def run_import(args: list[str], out: Path, capsys, monkeypatch) -> str:
    """``usplat import ARGS --out OUT``: exit 2 with one line naming the problem, no program
    started, within ``HANG_S``; returns the line."""
    from usplat_dr.cli import main

    def refuse(*a, **k):
        raise AssertionError(f"a program was started on data: {a}")

    monkeypatch.setattr(subprocess, "Popen", refuse)
    with deadline(HANG_S):
        code = main(["-q", "import", *args, "--out", str(out), "--near", "1", "--far", "9"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("usplat import: error: "), (code, err)
    assert len(err.splitlines()) == 1, err
    return err


def test_imported_images_are_png_or_jpeg_of_bounded_size(tmp_path, capsys, monkeypatch):
    eps = (b"%!PS-Adobe-3.0 EPSF-3.0\n%%BoundingBox: 0 0 64 48\n"
           b"(%pipe%touch /tmp/usplat_pwned) (w) file\nshowpage\n%%EOF\n")
    cases = {"EPS named .png": eps, "text": b"these are not image bytes\n" * 10,
             "a 20000x20000 header": png_claiming(20000, 20000).numpy().tobytes(),
             "GIF": encoded("GIF").numpy().tobytes(), "empty": b""}
    for i, (kind, data) in enumerate(cases.items()):
        folder = own_colmap(tmp_path / f"m{i}", data)
        err = run_import(["--colmap", str(folder)], tmp_path / f"out{i}", capsys, monkeypatch)
        assert "cannot be decoded" in err or "claims" in err, (kind, err)
        assert not (tmp_path / f"out{i}" / "test").exists() or not list(
            (tmp_path / f"out{i}" / "test").glob("*.torch")), kind
        COUNTS[(DECODING, "error naming the file")] += 1
    assert not Path("/tmp/usplat_pwned").exists()


def test_imported_file_names_stay_inside_their_folder(tmp_path, capsys, monkeypatch):
    secret = tmp_path / "secret.png"
    Image.new("RGB", (64, 48), (255, 0, 0)).save(secret)
    hostile = ["../../secret.png", "../../../secret.png", str(secret), "images/../../../secret.png"]
    for i, name in enumerate(hostile):
        folder = own_colmap(tmp_path / f"c{i}" / "m", name=name)
        err = run_import(["--colmap", str(folder)], tmp_path / f"cout{i}", capsys, monkeypatch)
        assert "leaves" in err or "absolute" in err, (name, err)
        COUNTS[(READS, "error naming the file")] += 1
        folder = tmp_path / f"n{i}" / "scene"
        folder.mkdir(parents=True)
        (folder / "transforms.json").write_text(json.dumps({
            "fl_x": 50, "w": 64, "h": 48,
            "frames": [{"file_path": name, "transform_matrix": np.eye(4).tolist()}]}))
        err = run_import(["--nerfstudio", str(folder)], tmp_path / f"nout{i}", capsys,
                         monkeypatch)
        assert "leaves" in err or "absolute" in err, (name, err)
        COUNTS[(READS, "error naming the file")] += 1


def test_counts_and_sizes_in_camera_files_are_bounded(tmp_path, capsys, monkeypatch):
    import struct

    from usplat_dr.data.importers import MAX_JSON_BYTES
    from usplat_dr.io.user_files import MAX_DATA_BYTES

    def binary_model(folder: Path, cameras: bytes, images: bytes) -> Path:
        own_colmap(folder)
        for f in ("cameras.txt", "images.txt"):
            (folder / f).unlink()
        (folder / "cameras.bin").write_bytes(cameras)
        (folder / "images.bin").write_bytes(images)
        return folder

    one_camera = struct.pack("<QiiQQ4d", 1, 1, 1, 64, 48, 50, 50, 32, 24)
    image = struct.pack("<Qidddddddi", 1, 1, 1, 0, 0, 0, 0, 0, 5, 1) + b"a.png\0"
    # (one image: every case fails before the importer counts them)
    cases = {
        "2^62 2D points": (one_camera, image + struct.pack("<Q", 2**62)),
        "2^64 - 1 cameras": (struct.pack("<Q", 2**64 - 1), image + struct.pack("<Q", 0)),
        "2^64 - 1 images": (one_camera, struct.pack("<Q", 2**64 - 1)),
        "a name without its end": (one_camera, image[:-1]),
        "a name of bytes": (one_camera, image[:-6] + b"\xff\xfe\0" + struct.pack("<Q", 0)),
    }
    for i, (kind, (cams, imgs)) in enumerate(cases.items()):
        folder = binary_model(tmp_path / f"b{i}", cams, imgs)
        err = run_import(["--colmap", str(folder)], tmp_path / f"bout{i}", capsys, monkeypatch)
        # (a count past MAX_CAMERAS is refused by the count itself, before any record)
        assert ("ends early" in err or "UTF-8" in err or "NUL" in err
                or "more than the 100,000 a camera file may hold" in err), (kind, err)
        COUNTS[(BOUNDS, "error naming the file")] += 1
    # sparse files past the bounds: refused from their size, before a byte is read
    folder = binary_model(tmp_path / "sparse", one_camera, image + struct.pack("<Q", 0))
    with open(folder / "cameras.bin", "r+b") as f:
        f.truncate(MAX_DATA_BYTES + 1)
    err = run_import(["--colmap", str(folder)], tmp_path / "sout", capsys, monkeypatch)
    assert "bytes, more than" in err, err
    COUNTS[(BOUNDS, "error naming the file")] += 1
    folder = tmp_path / "json"
    folder.mkdir()
    with open(folder / "transforms.json", "wb") as f:
        f.truncate(MAX_JSON_BYTES + 1)
    err = run_import(["--nerfstudio", str(folder)], tmp_path / "jout", capsys, monkeypatch)
    assert "bytes, more than" in err, err
    (folder / "transforms.json").write_text("[" * 100_000 + "]" * 100_000)
    err = run_import(["--nerfstudio", str(folder)], tmp_path / "jout2", capsys, monkeypatch)
    assert "too deeply" in err or "no 'frames'" in err, err
    COUNTS[(BOUNDS, "error naming the file")] += 2


def test_render_images_decodes_through_the_same_door(tmp_path, monkeypatch):
    from usplat_dr.data.user_views import context_views, read_cameras

    monkeypatch.setattr(subprocess, "Popen", lambda *a, **k: pytest.fail(f"program: {a}"))
    eps = b"%!PS-Adobe-3.0 EPSF-3.0\n%%BoundingBox: 0 0 64 48\nshowpage\n%%EOF\n"
    folder = own_colmap(tmp_path / "eps", eps)
    images = [folder / "images" / "a.png", folder / "images" / "b.png"]
    with deadline(HANG_S), pytest.raises(ValueError, match="cannot be decoded"):
        context_views(images, read_cameras(folder), (64, 64))
    COUNTS[(DECODING, "error naming the file")] += 1
    # a camera 4,000,000 pixels wide: refused where the camera file is read, naming it
    folder = own_colmap(tmp_path / "wide", eps, size=(4_000_000, 1))
    with deadline(HANG_S), pytest.raises(ValueError, match=r"cameras.txt:1: the image size "
                                                           r"must be whole pixels"):
        read_cameras(folder)
    COUNTS[(BOUNDS, "error naming the file")] += 1
    # a valid 1 x 65,536 PNG (a few KB), the widest camera allowed: covering 64x64 would ask
    # for 64 x 4M pixels
    buf = io.BytesIO()
    Image.new("RGB", (65_536, 1)).save(buf, format="PNG")
    folder = own_colmap(tmp_path / "long", buf.getvalue(), size=(65_536, 1))
    Image.new("RGB", (65_536, 1)).save(folder / "images" / "b.png")
    images = [folder / "images" / "a.png", folder / "images" / "b.png"]
    with deadline(HANG_S), pytest.raises(ValueError, match="resized"):
        context_views(images, read_cameras(folder), (64, 64))
    COUNTS[(BOUNDS, "error naming the file")] += 1


def test_ply_files_are_regular_and_bounded(tmp_path):
    from usplat_dr.model.ply import read_ply

    fifo = tmp_path / "fifo.ply"
    os.mkfifo(fifo)
    huge = tmp_path / "huge.ply"
    props = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
             "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    huge.write_bytes(("ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\n"
                      + "".join(f"property float {p}\n" for p in props)
                      + "end_header\n").encode() + b"\0" * 64)
    for path, needle in ((fifo, "not a regular file"), (Path("/dev/zero"), "not a regular file"),
                         (tmp_path, "not a regular file"), (huge, "truncated")):
        with deadline(HANG_S), pytest.raises(ValueError, match=needle):
            read_ply(path)
        COUNTS[(BOUNDS, "error naming the file")] += 1


def test_an_add_on_base_is_hashed_only_when_regular_and_bounded(tmp_path):
    from usplat_dr.training.checkpoints import MAX_CHECKPOINT_BYTES, read_usplat_checkpoint

    addon = tmp_path / "addon.pt"
    torch_save({"base": {"file": "base.pt", "sha256": "0" * 64}, "model": {}}, addon)
    with open(tmp_path / "base.pt", "wb") as f:  # sparse: no disk used, a terabyte to hash
        f.truncate(MAX_CHECKPOINT_BYTES + 1)
    with deadline(HANG_S), pytest.raises(ValueError, match="bytes, more than"):
        read_usplat_checkpoint(addon)
    (tmp_path / "base.pt").unlink()
    os.mkfifo(tmp_path / "base.pt")
    with deadline(HANG_S), pytest.raises((ValueError, FileNotFoundError)):
        read_usplat_checkpoint(addon)  # a FIFO is no file: never opened
    COUNTS[(BOUNDS, "error naming the file")] += 2
    for name in ("../base.pt", "/etc/base.pt", "sub/base.pt"):
        torch_save({"base": {"file": name, "sha256": "0" * 64}, "model": {}}, addon)
        with pytest.raises(ValueError, match="not a .pt file name"):
            read_usplat_checkpoint(addon)
        COUNTS[(READS, "error naming the file")] += 1


def nerfstudio_scene(folder: Path, top: dict | None = None, frame: dict | None = None) -> Path:
    """Two 64x48 images and a transforms.json; ``top`` and ``frame`` (the first frame's)
    entries override the valid ones."""
    folder.mkdir(parents=True)
    for name in ("a.png", "b.png"):
        Image.new("RGB", (64, 48)).save(folder / name)
    moved = np.eye(4)
    moved[0, 3] = 1.0
    meta = {"fl_x": 50, "w": 64, "h": 48,
            "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()},
                       {"file_path": "b.png", "transform_matrix": moved.tolist()}]}
    meta.update(top or {})
    meta["frames"][0].update(frame or {})
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


@pytest.mark.parametrize("case, top, frame, needle", [
    ("zero focal length", {"fl_x": 0}, None, "the focal lengths must be in (0, 1e+06]"),
    ("infinite focal length", {"fl_x": 1e400}, None, "the focal lengths must be in (0, 1e+06]"),
    ("focal length of 1e300 pixels", {"fl_x": 1e300}, None, "the focal lengths must be in"),
    ("a size of 1e300 pixels", {"w": 1e300, "h": 1e300}, None,
     "the image size must be whole pixels in 1..65,536"),
    ("NaN centre", {"cx": float("nan")}, None, "must be finite"),
    ("width of text", {"w": "abc"}, None, "invalid literal"),
    ("NaN pose", None, {"transform_matrix": [[float("nan")] * 4] * 4}, "not finite"),
    ("singular pose", None, {"transform_matrix": [[0] * 4] * 4}, "not a rigid transform"),
    ("scaled pose", None, {"transform_matrix": np.diag([3.0, 3, 3, 1]).tolist()},
     "not a rotation"),
    ("mirrored pose", None, {"transform_matrix": np.diag([-1.0, 1, 1, 1]).tolist()},
     "not a rotation"),
    ("pose of text", None, {"transform_matrix": "abc"}, "could not convert"),
    ("3x3 pose", None, {"transform_matrix": np.eye(3).tolist()}, "must be 4x4"),
    ("file_path a number", None, {"file_path": 5}, "is not a file name"),
])
def test_absurd_cameras_end_in_one_line_naming_the_frame(tmp_path, capsys, monkeypatch, case,
                                                         top, frame, needle):
    folder = nerfstudio_scene(tmp_path / "s", top, frame)
    err = run_import(["--nerfstudio", str(folder)], tmp_path / "out", capsys, monkeypatch)
    assert needle in err and "transforms.json frame" in err, (case, err)
    COUNTS[(SKIPS, "error naming the file")] += 1


def test_one_image_named_by_two_frames_or_a_million_frames_are_refused(tmp_path, capsys,
                                                                        monkeypatch):
    folder = nerfstudio_scene(tmp_path / "twice", frame={"file_path": "./b.png"})
    err = run_import(["--nerfstudio", str(folder)], tmp_path / "out", capsys, monkeypatch)
    assert "frames name the image" in err and "b.png twice" in err, err
    COUNTS[(SKIPS, "error naming the file")] += 1
    folder = nerfstudio_scene(tmp_path / "million")
    meta = json.loads((folder / "transforms.json").read_text())
    meta["frames"] = [{"file_path": "a.png"}] * 1_000_000  # one image, a million times
    (folder / "transforms.json").write_text(json.dumps(meta))
    err = run_import(["--nerfstudio", str(folder)], tmp_path / "out2", capsys, monkeypatch)
    assert "declares 1,000,000 frames, more than the 100,000" in err, err
    COUNTS[(BOUNDS, "error naming the file")] += 1


def test_a_shipped_name_is_never_a_file_of_that_name_here(tmp_path, monkeypatch, caplog):
    # garbage named like a shipped model in the current folder: the name still means the
    # shipped file (said); the file is reached only as a path
    from usplat_dr.training.registry import resolve_checkpoint, shipped_models

    monkeypatch.chdir(tmp_path)
    for name in ("full-64", "baseline-64", "tiny_baseline_128"):
        (tmp_path / name).write_bytes(b"not a checkpoint")
        expected = next(m.file for m in shipped_models().values()
                        if name == m.name or name in m.old_names)
        assert resolve_checkpoint(name) == expected
        assert resolve_checkpoint(f"./{name}").resolve() == tmp_path / name
        COUNTS[(READS, "error naming the file")] += 1


@pytest.mark.parametrize("qvec", ["0 0 0 0", "nan 0 0 0", "1 inf 0 0"])
def test_colmap_quaternions_that_are_no_rotation_end_in_one_line(tmp_path, capsys, monkeypatch,
                                                                 qvec):
    folder = own_colmap(tmp_path / "m")
    (folder / "images.txt").write_text(f"1 {qvec} 0 0 5 1 a.png\n\n2 1 0 0 0 1 0 5 1 b.png\n\n")
    err = run_import(["--colmap", str(folder)], tmp_path / "out", capsys, monkeypatch)
    assert "image 'a.png'" in err and "quaternion" in err, err
    COUNTS[(SKIPS, "error naming the file")] += 1


@pytest.mark.parametrize("variable, value", [
    ("USPLAT_THREADS", "0"), ("USPLAT_THREADS", "abc"), ("USPLAT_THREADS", "99999"),
    ("USPLAT_THREADS", "-3"), ("USPLAT_OMP_SPIN", "abc"), ("USPLAT_OMP_SPIN", "-1"),
    ("USPLAT_PORTABLE", "maybe")])
def test_environment_variables_set_wrong(tmp_path, variable, value):
    import sys

    env = {**os.environ, variable: value}
    env.pop("GOMP_SPINCOUNT", None)
    env.pop("OMP_WAIT_POLICY", None)
    # importing the library never fails on a tuning variable: a warning names it
    imported = subprocess.run([sys.executable, "-c", "import usplat_dr"], env=env, check=False,
                              capture_output=True, text=True, timeout=120)
    assert imported.returncode == 0, imported.stderr
    if variable == "USPLAT_OMP_SPIN":
        assert "USPLAT_OMP_SPIN" in imported.stderr
    # a command: one line naming the variable and exit 2, or runs with libgomp's default
    cmd = subprocess.run([sys.executable, "-m", "usplat_dr.cli", "-q", "synth", "--out",
                          str(tmp_path / "out"), "--scenes", "1", "--frames", "3",
                          "--image-shape", "8", "8", "--spp", "1"], env=env, check=False,
                         capture_output=True, text=True, timeout=300)
    if variable == "USPLAT_THREADS":
        lines = [x for x in cmd.stderr.splitlines() if x.strip()]
        assert cmd.returncode == 2 and len(lines) == 1 and variable in lines[0], cmd.stderr
    else:
        assert cmd.returncode == 0, cmd.stderr
    if variable == "USPLAT_PORTABLE":  # said, with the values it takes
        assert "USPLAT_PORTABLE='maybe' is not one of 1/true/yes/on" in cmd.stderr, cmd.stderr
    COUNTS[(SKIPS, "error naming the variable" if cmd.returncode else "warning")] += 1


def test_weight_files_that_are_not_torch_files_name_themselves(tmp_path):
    from usplat_dr.evaluation.lpips import LPIPS
    from usplat_dr.model.hypernet.resnet import ResNet18

    files = {"text": b"not weights", "empty": b"", "a zip of nothing": b"PK\x05\x06" + bytes(18)}
    list_file = tmp_path / "list.pth"
    torch_save([torch.zeros(2)], list_file)
    for i, data in enumerate(files.values()):
        path = tmp_path / f"w{i}.pth"
        path.write_bytes(data)
        for load in (lambda p: LPIPS.from_files(p, p), lambda p: ResNet18().load_torchvision(p)):
            with deadline(HANG_S), pytest.raises(ValueError, match=str(path.name)):
                load(path)
            COUNTS[(SKIPS, "error naming the file")] += 1
    for load in (lambda p: LPIPS.from_files(p, p), lambda p: ResNet18().load_torchvision(p)):
        with pytest.raises(ValueError, match="not a state dict"):
            load(list_file)
        COUNTS[(SKIPS, "error naming the file")] += 1


@pytest.mark.parametrize("argv, needle", [
    (["train", "train.steps=1000000000000000000000000000000"], "must be >= 1 and <= 1,000,000"),
    (["train", "train.steps=10**30"], "expected int"),
    (["train", "output_dir="], "must name a folder"),
    (["train", "dataset.image_shape=[[[[1]]]]"], "expected tuple[int, int]"),
    (["eval", "--checkpoint", "tiny_full", "--data", ".", "--index", "standard"],
     "--index takes SPLIT=PATH"),
    (["eval", "--checkpoint", "tiny_full", "--data", ".", "--index", "=x"],
     "--index takes SPLIT=PATH"),
])
def test_settings_out_of_range_end_in_one_line(tmp_path, capsys, monkeypatch, argv, needle):
    from usplat_dr.cli import main

    monkeypatch.chdir(tmp_path)
    with deadline(HANG_S):
        code = main(["-q", *argv])
    err = [x for x in capsys.readouterr().err.splitlines() if "error:" in x]
    assert code == 2 and len(err) == 1 and needle in err[0], (code, err)
    COUNTS[(BOUNDS, "error naming the setting")] += 1


@pytest.mark.parametrize("kind", ["float8", "sparse", "meta", "quantised"])
def test_weights_of_the_right_shape_but_no_usable_tensor_name_themselves(tmp_path, kind):
    from usplat_dr.training.checkpoints import CHECKPOINTS
    from usplat_dr.training.loader import load

    state = torch.load(CHECKPOINTS / "tiny_baseline.pt", weights_only=True)
    name = next(k for k, v in state["model"].items() if v.is_floating_point())
    v = state["model"][name].float()
    state["model"][name] = {"float8": lambda: v.to(torch.float8_e4m3fn),
                            "sparse": v.to_sparse, "meta": lambda: v.to("meta"),
                            "quantised": lambda: torch.quantize_per_tensor(
                                v, 0.1, 0, torch.qint8)}[kind]()
    path = tmp_path / f"{kind}.pt"
    torch.save(state, path)
    with deadline(HANG_S), pytest.raises(ValueError, match=name.replace(".", r"\.")):
        load(path)
    COUNTS[(SKIPS, "error naming the file")] += 1


def test_zz_the_counts(capsys):
    """Prints the outcomes per class (run with ``-s`` to see them)."""
    assert not any(outcome in ("crash", "hang") for _, outcome in COUNTS)
    by_class = collections.defaultdict(dict)
    for (cls, outcome), n in sorted(COUNTS.items()):
        by_class[cls][outcome] = n
    with capsys.disabled():
        print(f"\nattack suite: {sum(COUNTS.values())} inputs")
        for cls, outcomes in by_class.items():
            print(f"  {cls}: " + ", ".join(f"{n} {o}" for o, n in outcomes.items()))
