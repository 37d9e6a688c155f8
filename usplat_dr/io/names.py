"""File names made from data: a scene key (any string a chunk holds) becomes a name that stays
inside the folder it is written to.

The field's keys (RealEstate10K's 16 hex digits, DTU's ``scan1_...``) pass unchanged; a key
with a path separator, ``..``, a NUL byte, a leading dot, other characters outside
``[A-Za-z0-9_.-]`` or more than ``MAX_STEM`` characters becomes its safe characters (the rest
as ``_``, cut to length) plus a short hash of the whole key, so two keys never share a name.
Writers keep the key itself inside the file (PNG text, JSON field)."""

import hashlib
import re

#: Longest stem kept as is; a suffix and a prefix ("fit_", ".png") keep whole names far below
#: the 255 bytes most file systems allow.
MAX_STEM = 96
_SAFE = re.compile(r"[A-Za-z0-9_.\-]+")


def safe_stem(key: str) -> str:
    """A file-name stem for ``key`` that names no other folder.

    Examples:
        >>> safe_stem("5aca87f95a9412c6")
        '5aca87f95a9412c6'
        >>> safe_stem("../../escaped")
        '_.._escaped-ea03bc47f8'
        >>> safe_stem("a" * 300) == "a" * 85 + "-" + safe_stem("a" * 300)[-10:]
        True
    """
    if not isinstance(key, str):
        raise TypeError(f"a scene key must be a str, got {type(key).__name__}")
    if _SAFE.fullmatch(key) and not key.startswith(".") and len(key) <= MAX_STEM:
        return key
    digest = hashlib.sha256(key.encode("utf-8", "surrogatepass")).hexdigest()[:10]
    body = re.sub(r"[^A-Za-z0-9_.\-]", "_", key).lstrip(".")[:MAX_STEM - 11]
    return f"{body}-{digest}"
