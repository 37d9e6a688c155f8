"""Composable YAML configurations with dotted ``key=value`` overrides (the field's Hydra
habits without Hydra).

The shipped configurations are package data (``usplat_dr/configs/``, read with
``importlib.resources``, so a wheel install has them). A config is named by a path to a YAML
file (a user's own) or, when no such file exists, by its name among the packaged ones
(``synthetic_tiny.yaml``, ``model/tiny.yaml``). A file may list others under ``include:``
(paths relative to it, else packaged names); they are merged first, in order, then the file
itself, then the command line's overrides. Dictionaries merge key by key; anything else
replaces. Override values are parsed as YAML (``lr=1e-6``, ``steps=100``,
``model.variant=full``, ``dataset.roots=[a,b]``, ``x=null``).

    cfg = load_config(["synthetic_tiny.yaml"], ["optimizer.lr=1e-4"])
"""

import copy
import dataclasses
import os
import re
import types
import typing
from importlib.resources import files
from pathlib import Path, PurePosixPath

import yaml

try:  # Python >= 3.11
    from importlib.resources.abc import Traversable
except ImportError:  # Python 3.10
    from importlib.abc import Traversable


class _Loader(yaml.SafeLoader):
    """YAML 1.1 reads ``1e-6`` (no dot) as a string; here it is a float, as people mean it."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                  |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                  |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                  |[-+]?\.(?:inf|Inf|INF)
                  |\.(?:nan|NaN|NAN))$""", re.VERBOSE),
    list("-+0123456789."))


#: A config expands to at most this many YAML nodes (aliases counted each time they are
#: used): the shipped ones have ~300; nested aliases ("billion laughs") would otherwise
#: expand to ~10^9 objects before any check. And at most this many characters.
MAX_YAML_NODES = 100_000
MAX_YAML_CHARS = 1_000_000


def parse(text: str):
    """YAML ``text`` to Python data; ``yaml.YAMLError`` for text that does not parse or that
    would expand past ``MAX_YAML_NODES`` (aliases) or ``MAX_YAML_CHARS``."""
    if len(text) > MAX_YAML_CHARS:
        raise yaml.YAMLError(f"{len(text):,} characters, more than a config may hold "
                             f"({MAX_YAML_CHARS:,})")
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        size = _expanded_size(node, {}, set())
        if size > MAX_YAML_NODES:
            raise yaml.YAMLError(f"its aliases expand to {size:,} nodes, more than a config "
                                 f"may hold ({MAX_YAML_NODES:,}): write the values out")
        return loader.construct_document(node)
    finally:
        loader.dispose()


def _expanded_size(node: yaml.Node, memo: dict[int, int], open_: set[int]) -> int:
    """The nodes ``node`` stands for with every alias expanded (memoised, so a shared node is
    counted once per use without walking it again); a node that contains itself is refused.
    Stops adding at ``MAX_YAML_NODES`` + 1 (the sum can otherwise reach 10^100)."""
    if id(node) in memo:
        return memo[id(node)]
    if id(node) in open_:
        raise yaml.YAMLError("a recursive alias (a node that contains itself)")
    open_.add(id(node))
    size = 1
    if isinstance(node, yaml.SequenceNode):
        children = node.value
    elif isinstance(node, yaml.MappingNode):
        children = [n for pair in node.value for n in pair]
    else:
        children = []
    for child in children:
        size = min(size + _expanded_size(child, memo, open_), MAX_YAML_NODES + 1)
    open_.discard(id(node))
    memo[id(node)] = size
    return size


class ConfigError(ValueError):
    """A configuration file or override that cannot be used; the message says which."""


def merge(base: dict, update: dict) -> dict:
    """Deep merge of ``update`` into a copy of ``base``."""
    out = copy.deepcopy(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def packaged_configs() -> Traversable:
    """The folder of the shipped configurations (``usplat_dr/configs/``, package data)."""
    return files("usplat_dr") / "configs"


def packaged_names() -> list[str]:
    """The packaged configurations' names, e.g. ``synthetic_tiny.yaml``, ``model/tiny.yaml``."""
    def walk(node: Traversable, prefix: str) -> list[str]:
        names = []
        for child in node.iterdir():
            if child.is_dir():
                names += walk(child, f"{prefix}{child.name}/")
            elif child.name.endswith(".yaml"):
                names.append(prefix + child.name)
        return names
    return sorted(walk(packaged_configs(), ""))


def find_config(ref: str | os.PathLike, relative_to: Path | Traversable | None = None
                ) -> Path | Traversable:
    """The config file ``ref`` names: a path to an existing file (a user's own YAML; relative
    to ``relative_to``, the including file's folder, when given), else a packaged config's
    name (``synthetic_tiny.yaml``, ``model/tiny.yaml``)."""
    path = Path(ref)
    if relative_to is not None and not path.is_absolute():
        local = relative_to / str(ref)
        if local.is_file():
            return local
    elif path.is_file():
        return path
    if not path.is_absolute():
        packaged = packaged_configs().joinpath(*PurePosixPath(str(ref)).parts)
        if packaged.is_file():
            return packaged
    raise ConfigError(f"config file {str(ref)!r} does not exist and is not a packaged config; "
                      f"pass the path of a YAML file or one of {packaged_names()}")


class Config(dict):
    """A loaded configuration: a plain dict, plus ``origins``, the file (or command-line
    override) that set each dotted key, so that errors can name where a value came from."""

    def __init__(self, data=(), origins: dict[str, str] | None = None):
        super().__init__(data)
        self.origins = dict(origins or {})


def _record(origins: dict[str, str], data, where: str, prefix: str = "") -> None:
    """Note ``where`` as the origin of every key in ``data`` (nested keys dotted)."""
    if not isinstance(data, dict):
        return
    for key, value in data.items():
        origins[prefix + str(key)] = where
        _record(origins, value, where, f"{prefix}{key}.")


def read_file(path: str | os.PathLike | Traversable, _seen: tuple = (),
              origins: dict[str, str] | None = None) -> dict:
    """One config file (a path, a packaged name or a packaged resource) merged over its
    includes; ``origins`` (when given) receives the file that set each dotted key."""
    source = find_config(path) if isinstance(path, (str, os.PathLike)) else path
    key = str(source.resolve()) if isinstance(source, Path) else str(source)
    if key in _seen:
        raise ConfigError(f"config {key} includes itself (through {list(_seen)})")
    try:
        data = parse(source.read_text(encoding="utf-8")) or {}
    except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as e:
        raise ConfigError(f"config file {key} is not valid YAML: {e}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config file {key} must hold a mapping, got {type(data).__name__}")
    includes = data.pop("include", []) or []
    if isinstance(includes, str):
        includes = [includes]
    if not isinstance(includes, list) or not all(isinstance(i, str) for i in includes):
        raise ConfigError(f"config file {key}: 'include' must be a file name or a list of "
                          f"them, got {includes!r}")
    out = {}
    for inc in includes:
        try:
            found = find_config(inc, source.parent)
        except ConfigError as e:
            raise ConfigError(f"config file {key} includes {inc!r}: {e}") from None
        out = merge(out, read_file(found, _seen + (key,), origins))
    if origins is not None:
        _record(origins, data, key)
    return merge(out, data)


def apply_override(cfg: dict, override: str, origins: dict[str, str] | None = None) -> dict:
    if "=" not in override:
        raise ConfigError(f"override {override!r} must look like key.sub=value")
    key, raw = override.split("=", 1)
    try:
        value = parse(raw) if raw != "" else ""
    except (yaml.YAMLError, RecursionError) as e:
        raise ConfigError(f"override {override!r}: value is not valid YAML ({e})") from e
    parts = key.strip().split(".")
    node = cfg
    for i, part in enumerate(parts[:-1]):
        if not isinstance(node.get(part, {}), dict):
            raise ConfigError(f"override {override!r}: {'.'.join(parts[:i + 1])} is not a "
                              f"section")
        node = node.setdefault(part, {})
    node[parts[-1]] = value
    if origins is not None:
        _record(origins, {key.strip(): value}, f"the command line ({override})")
    return cfg


def load_config(paths, overrides=()) -> Config:
    """Merge the files (each with its includes) and apply the overrides. ``paths``: paths of
    YAML files or names of packaged configs (``synthetic_tiny.yaml``)."""
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    cfg, origins = {}, {}
    for p in paths:
        cfg = merge(cfg, read_file(p, origins=origins))
    for o in overrides:
        cfg = apply_override(cfg, o, origins)
    return Config(cfg, origins)


# ---- typed configs ---------------------------------------------------------------------

def where_set(origins: dict[str, str], key: str) -> str:
    """Where ``key`` (dotted) was set, for messages: its file or override, else the key's
    nearest section that has an origin."""
    parts = key.split(".")
    for i in range(len(parts), 0, -1):
        if ".".join(parts[:i]) in origins:
            return origins[".".join(parts[:i])]
    return "the configuration"


def typed_value(tp, value, key: str, origins: dict[str, str] | None = None):
    """``value`` checked against the annotation ``tp`` (int, float, bool, str, None, dict,
    a tuple of them, a dataclass, a union of them, or a union of named dataclasses:
    ``load_named``): ints are accepted for floats, YAML lists for tuples; anything else is a
    ``ConfigError`` naming the key, the expected type and the value's origin.

    Examples:
        >>> typed_value(tuple[int, int], [32, 48], "dataset.image_shape")
        (32, 48)
    """
    origins = origins or {}
    if dataclasses.is_dataclass(tp):
        return load_typed(tp, value, key, origins)
    options = typing.get_args(tp) if isinstance(tp, types.UnionType) else (tp,)
    if len(options) > 1 and all(dataclasses.is_dataclass(o) for o in options):
        return load_named(options, value, key, origins)
    for option in options:
        if option is type(None) and value is None:
            return None
        if option is bool and isinstance(value, bool):
            return value
        if option is int and isinstance(value, int) and not isinstance(value, bool):
            return value
        if option is float and isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if option in (str, dict) and isinstance(value, option):
            return value
        if option is dict and value is None:  # a section with nothing under it
            return {}
        if typing.get_origin(option) is dict and isinstance(value, dict):
            return value
        if typing.get_origin(option) is tuple and isinstance(value, (list, tuple)):
            args = typing.get_args(option)
            items = args[:1] * len(value) if args[-1:] == (Ellipsis,) else args
            try:
                if len(items) == len(value):
                    return tuple(typed_value(t, v, key, origins) for t, v in zip(items, value))
            except ConfigError:
                pass  # reported below, as the whole value
    expected = " or ".join("null" if o is type(None) else o.__name__ if isinstance(o, type)
                           else str(o) for o in options)
    raise ConfigError(f"{key}={value!r}: expected {expected}, got {type(value).__name__} "
                      f"(set in {where_set(origins, key)})")


def load_named(options: tuple, data, section: str, origins: dict[str, str] | None = None):
    """One of the dataclasses ``options``, each with a ``name`` field whose default names it
    (pixelSplat's encoder and view-sampler configs), chosen by the mapping ``data``'s
    ``name`` (default: the first option's) and loaded from its other keys (``load_typed``).

    Examples:
        >>> @dataclasses.dataclass(frozen=True)
        ... class Bounded:
        ...     name: str = "bounded"
        ...     views: int = 2
        >>> @dataclasses.dataclass(frozen=True)
        ... class All:
        ...     name: str = "all"
        >>> load_named((Bounded, All), {"views": 3}, "sampler")
        Bounded(name='bounded', views=3)
        >>> load_named((Bounded, All), {"name": "some"}, "sampler")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        usplat_dr.config.ConfigError: sampler.name='some' must be one of ['all', 'bounded'] ...
    """
    origins = origins or {}
    by_name = {next(f.default for f in dataclasses.fields(o) if f.name == "name"): o
               for o in options}
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ConfigError(f"{section}={data!r} must be a mapping (set in "
                          f"{where_set(origins, section)})")
    data = dict(data)
    name = data.pop("name", next(iter(by_name)))
    if name not in by_name:
        raise ConfigError(f"{section}.name={name!r} must be one of {sorted(by_name)} (set in "
                          f"{where_set(origins, f'{section}.name')})")
    return load_typed(by_name[name], data, section, origins)


def load_typed(cls, data, section: str = "", origins: dict[str, str] | None = None):
    """The dataclass ``cls`` from the mapping ``data`` (a config section): missing keys keep
    the dataclass's defaults, unknown keys and values of the wrong type are a ``ConfigError``
    naming the key and the file or override that set it. A dataclass with a ``checked(section,
    origins)`` method gets it called on the result: its checks across fields and of ranges
    (a ``ConfigError`` naming the key and where it was set), and its normal form.

    Examples:
        >>> @dataclasses.dataclass(frozen=True)
        ... class Train:
        ...     steps: int = 10
        >>> load_typed(Train, {"steps": 3}, "train")
        Train(steps=3)
        >>> load_typed(Train, {"steps": "abc"}, "train")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        usplat_dr.config.ConfigError: train.steps='abc': expected int, got str (set in ...)
    """
    origins = getattr(data, "origins", None) if origins is None else origins
    origins = origins or {}
    prefix = f"{section}." if section else ""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{section or 'the configuration'} must be a mapping of keys to "
                          f"values, got {data!r} (set in {where_set(origins, section)})")
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - known, key=str)  # YAML keys may be ints too
    if unknown:
        key = prefix + str(unknown[0])
        raise ConfigError(f"unknown key {key!r} (set in {where_set(origins, key)}); "
                          f"{section or 'the top level'} knows {sorted(known)}")
    missing = [f.name for f in dataclasses.fields(cls) if f.name not in data
               and f.default is dataclasses.MISSING
               and f.default_factory is dataclasses.MISSING]
    if missing:
        raise ConfigError(f"{section or 'the configuration'} needs {missing} (set in "
                          f"{where_set(origins, section)})")
    loaded = cls(**{k: typed_value(hints[k], v, prefix + k, origins) for k, v in data.items()})
    checked = getattr(loaded, "checked", None)
    return checked(section, origins) if checked is not None else loaded


def check_keys(section: dict, known: set[str], where: str,
               origins: dict[str, str] | None = None) -> None:
    """A ``ConfigError`` naming the unknown keys of the mapping ``section`` (at dotted
    ``where``) and, given ``origins``, the file or override that set the first."""
    unknown = sorted(set(section) - known, key=str)
    if unknown:
        at = f" (set in {where_set(origins, f'{where}.{unknown[0]}')})" if origins else ""
        raise ConfigError(f"unknown key(s) {unknown} in {where}{at}; known: {sorted(known)}")
