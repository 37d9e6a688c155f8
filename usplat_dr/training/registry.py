"""The shipped models by name (``checkpoints/manifest.json``): the user names, at most one (a)
and one (c) per training size; the study models under ``study/``; the old names, which load
for one more release with a line naming the new one; and the default of the commands, the
shipped (c) for the size asked (``default_checkpoint``).

Each manifest entry records what choosing needs: its ``variant``, ``kind`` (``user`` or
``study``), ``training_shape``, ``recipe``, ``purpose``, ``default_for`` and, for an add-on
(a file holding only the weights it adds to another), its ``base``. ``usplat models`` prints
them, one line a model.
"""

import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

#: Where the shipped checkpoints are: package data in a wheel install (usplat_dr/checkpoints,
#: pyproject.toml maps the repository's checkpoints/ there), else the repository's
#: checkpoints/ folder (a source checkout or an editable install).
CHECKPOINTS = next((p for p in (Path(__file__).parents[1] / "checkpoints",
                                Path(__file__).parents[2] / "checkpoints") if p.is_dir()),
                   Path(__file__).parents[2] / "checkpoints")

#: A manifest entry's ``kind``: a model for users (``usplat models`` lists it), or one a study
#: made and reads (``usplat models --all``; its name starts with ``study/``).
KINDS = ("user", "study")
STUDY_PREFIX = "study/"
#: The paper's labels of the variants.
LABELS = {"baseline": "(a)", "agnostic": "(b)", "full": "(c)"}

_told: set[str] = set()  # old names already announced in this process


@dataclass(frozen=True)
class ShippedModel:
    """One manifest entry, as ``usplat models`` and the loader read it."""

    name: str
    file: Path
    variant: str
    kind: str
    size: int | None  # the shorter side of its training images
    recipe: str
    purpose: str
    default_for: str | None
    sha256: str
    base: str | None  # the file an add-on completes (its other weights)
    old_names: tuple[str, ...]

    def line(self) -> str:
        """``usplat models``' line: name, variant, size, purpose, default for, sha256 prefix.

        Examples:
            >>> ShippedModel("full-64", Path("a.pt"), "full", "user", 64, "r", "UniqueSplat",
            ...              "every request", "0123456789ab", None, ()).line()
            'full-64  (c)  64x64  UniqueSplat  [default for every request]  sha256 01234567'
        """
        size = f"{self.size}x{self.size}" if self.size else "?"
        default = f"  [default for {self.default_for}]" if self.default_for else ""
        return (f"{self.name}  {LABELS.get(self.variant, self.variant)}  {size}  "
                f"{self.purpose}{default}  sha256 {self.sha256[:8]}")


def manifest_entries(root: Path = CHECKPOINTS) -> list[dict]:
    """The manifest's entries (``[]`` where there is none)."""
    path = root / "manifest.json"
    if not path.is_file():
        return []
    entries = json.loads(path.read_text())
    if not isinstance(entries, list) or not all(isinstance(e, dict) and "name" in e
                                                and "file" in e for e in entries):
        raise ValueError(f"{path} must be a list of entries with 'name' and 'file'")
    return entries


def _model(root: Path, e: dict) -> ShippedModel:
    shape = e.get("training_shape")
    kind = e.get("kind", "study" if str(e["name"]).startswith(STUDY_PREFIX) else "user")
    if kind not in KINDS:
        raise ValueError(f"{root / 'manifest.json'}: {e['name']}'s kind must be one of {KINDS}, "
                         f"got {kind!r}")
    return ShippedModel(
        name=e["name"], file=root / e["file"], variant=e.get("variant", "?"), kind=kind,
        size=min(shape) if isinstance(shape, list) and shape else None,
        recipe=e.get("recipe", ""), purpose=e.get("purpose", ""),
        default_for=e.get("default_for"), sha256=e.get("sha256", ""),
        base=e.get("base"), old_names=tuple(e.get("old_names", ())))


def shipped_models(root: Path = CHECKPOINTS) -> dict[str, ShippedModel]:
    """``{name: ShippedModel}`` of the manifest, in its order (user models first)."""
    models = [_model(root, e) for e in manifest_entries(root)]
    models.sort(key=lambda m: KINDS.index(m.kind))
    names = [m.name for m in models] + [o for m in models for o in m.old_names]
    users = [(m.variant, m.size) for m in models if m.kind == "user"]
    if len(set(names)) != len(names) or len(set(users)) != len(users):
        raise ValueError(f"{root / 'manifest.json'}: a name (or old name) given twice, or two "
                         f"user models of one variant and size: each name must choose one "
                         f"model")
    return {m.name: m for m in models}


def shipped_checkpoints(root: Path = CHECKPOINTS) -> dict[str, Path]:
    """``{manifest name: file}`` of the shipped checkpoints."""
    if not (root / "manifest.json").is_file():
        raise FileNotFoundError(f"no {root / 'manifest.json'}: the demo starts from the shipped "
                                f"checkpoints (train them with train/ship_checkpoint.py; see "
                                f"README)")
    return {name: m.file for name, m in shipped_models(root).items()}


def canonical_name(name: str, root: Path = CHECKPOINTS) -> str | None:
    """The manifest name that ``name`` (with or without ``.pt``) is, or names under an old
    name, else ``None``. An old name is said once per process, with its new name.

    Examples:
        >>> canonical_name("full-64"), canonical_name("nothing")
        ('full-64', None)
    """
    stem = str(name).removesuffix(".pt")
    models = shipped_models(root)
    if stem in models:
        return stem
    for model in models.values():
        if stem in model.old_names:
            if stem not in _told:
                _told.add(stem)
                log.warning("%s is now %s (the same file); the old name loads for one more "
                            "release", stem, model.name)
            return model.name
    return None


def user_names(root: Path = CHECKPOINTS) -> list[str]:
    """The names ``usplat models`` lists without ``--all``."""
    return [n for n, m in shipped_models(root).items() if m.kind == "user"]


def resolve_checkpoint(checkpoint: str | os.PathLike, root: Path = CHECKPOINTS) -> Path:
    """The file ``checkpoint`` names: a shipped model's name (``full-64``, ``study/tiny_full``,
    an old name; with or without ``.pt``), else a path. A shipped name wins over a file of the
    same name in the current folder (said: ``./NAME`` names the file). Neither is a
    ``FileNotFoundError`` listing the user names."""
    text = str(checkpoint)
    name = canonical_name(text, root) if not text.startswith((".", "/")) else None
    if name is not None:
        if Path(text).is_file():
            log.warning("%s is the shipped model's name and also a file here: using the shipped "
                        "one (name the file ./%s to use it)", text, text)
        return shipped_models(root)[name].file
    path = Path(checkpoint)
    if path.is_file():
        return path
    names = ", ".join(user_names(root)) or "none installed"
    hint = f"shipped models (usplat models; --all for study/ ones): {names}"
    if len(path.parts) == 1:  # a bare name
        raise FileNotFoundError(f"checkpoint {text!r} is neither a file nor a shipped model's "
                                f"name ({hint})")
    raise FileNotFoundError(f"checkpoint {text!r} does not exist (usplat train writes "
                            f"OUTPUT_DIR/checkpoints/last.ckpt; MVSplat's files are re10k.ckpt / "
                            f"acid.ckpt from its release; {hint})")


def default_checkpoint(image_shape: tuple[int, int] | None, variant: str = "full",
                       root: Path = CHECKPOINTS) -> tuple[str, str]:
    """The default of the commands for a request of ``image_shape`` (``None``: your own
    photographs, larger than any model's size): the user model of ``variant`` trained
    nearest its shorter side (in octaves; the larger on a tie), or the largest; and the line
    that says so.

    Examples:
        >>> default_checkpoint((64, 64))[0]
        'full-64'
    """
    candidates = {m.size: n for n, m in shipped_models(root).items()
                  if m.kind == "user" and m.variant == variant and m.size}
    if not candidates:
        raise FileNotFoundError(f"no shipped {LABELS.get(variant, variant)} model in {root} "
                                f"(checkpoints/manifest.json): give --checkpoint")
    if image_shape is None:
        size = max(candidates)
    else:
        target = min(image_shape)
        size = min(candidates, key=lambda s: (abs(math.log2(s / target)), -s))
    name = candidates[size]
    why = ("your own images" if image_shape is None
           else f"{image_shape[0]}x{image_shape[1]}")
    return name, (f"no --checkpoint: using {name}, the shipped {LABELS.get(variant, variant)} "
                  f"trained at {size}x{size}, for {why} (usplat models lists the others)")
