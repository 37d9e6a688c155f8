"""Composable YAML configurations with dotted ``key=value`` overrides (the field's Hydra
habits without Hydra).

A file may list others under ``include:`` (paths relative to it); they are merged first, in
order, then the file itself, then the command line's overrides. Dictionaries merge key by key;
anything else replaces. Override values are parsed as YAML (``lr=1e-6``, ``steps=100``,
``model.variant=full``, ``dataset.roots=[a,b]``, ``x=null``).

    cfg = load_config(["train/configs/demo.yaml"], ["optimizer.lr=1e-4"])
"""

import copy
import os
import re
from pathlib import Path

import yaml


class _Loader(yaml.SafeLoader):
    """YAML 1.1 reads ``1e-6`` (no dot) as a string; here it is a float, as people mean it."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                  |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                  |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                  |[-+]?\.(?:inf|Inf|INF)
                  |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))


def parse(text: str):
    return yaml.load(text, Loader=_Loader)


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


def read_file(path: str | os.PathLike, _seen: tuple = ()) -> dict:
    path = Path(path).resolve()
    if path in _seen:
        raise ConfigError(f"config {path} includes itself (through {[str(p) for p in _seen]})")
    if not path.is_file():
        raise ConfigError(f"config file {str(path)!r} does not exist")
    with open(path) as f:
        try:
            data = parse(f.read()) or {}
        except yaml.YAMLError as e:
            raise ConfigError(f"config file {path} is not valid YAML: {e}") from e
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping, got {type(data).__name__}")
    includes = data.pop("include", []) or []
    if isinstance(includes, str):
        includes = [includes]
    out = {}
    for inc in includes:
        out = merge(out, read_file(path.parent / inc, _seen + (path,)))
    return merge(out, data)


def apply_override(cfg: dict, override: str) -> dict:
    if "=" not in override:
        raise ConfigError(f"override {override!r} must look like key.sub=value")
    key, raw = override.split("=", 1)
    try:
        value = parse(raw) if raw != "" else ""
    except yaml.YAMLError as e:
        raise ConfigError(f"override {override!r}: value is not valid YAML ({e})") from e
    parts = key.strip().split(".")
    node = cfg
    for i, part in enumerate(parts[:-1]):
        if not isinstance(node.get(part, {}), dict):
            raise ConfigError(f"override {override!r}: {'.'.join(parts[:i + 1])} is not a "
                              f"section")
        node = node.setdefault(part, {})
    node[parts[-1]] = value
    return cfg


def load_config(paths, overrides=()) -> dict:
    """Merge the files (each with its includes) and apply the overrides."""
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    cfg = {}
    for p in paths:
        cfg = merge(cfg, read_file(p))
    for o in overrides:
        cfg = apply_override(cfg, o)
    return cfg


def check_keys(section: dict, known: set[str], where: str) -> None:
    unknown = sorted(set(section) - known)
    if unknown:
        raise ConfigError(f"unknown key(s) {unknown} in {where}; known: {sorted(known)}")
