"""Typed, frozen configuration objects built from YAML plus dotted overrides.

A configuration is a tree of frozen dataclasses. Each field may carry metadata made by
:func:`param` (allowed range, allowed choices, a one-line help text with units). The
loader checks every key and value against the dataclass: unknown keys, wrong types and
out-of-range values raise :class:`~skygen.errors.ConfigError` naming the dotted key and
what is allowed. The same machinery is used by ``fusion`` for training configs.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from skygen.errors import ConfigError

_SCI = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")


def param(
    default: Any,
    *,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    hi_open: bool = False,
    choices: tuple | None = None,
    doc: str = "",
) -> Any:
    """A dataclass field with validation metadata (range, choices) and a help text."""
    meta = {"lo": lo, "hi": hi, "lo_open": lo_open, "hi_open": hi_open, "choices": choices, "doc": doc}
    if isinstance(default, (list, dict)):
        raise TypeError("use tuples for sequence defaults (configs are immutable)")
    return dataclasses.field(default=default, metadata=meta)


def section(cls: type) -> Any:
    """A nested configuration section with its default instance."""
    return dataclasses.field(default_factory=cls, metadata={"section": True})


def _describe_range(meta: Mapping) -> str:
    parts = []
    if meta.get("choices"):
        return "one of " + ", ".join(repr(c) for c in meta["choices"])
    if meta.get("lo") is not None:
        parts.append(f"{'>' if meta['lo_open'] else '>='} {meta['lo']}")
    if meta.get("hi") is not None:
        parts.append(f"{'<' if meta['hi_open'] else '<='} {meta['hi']}")
    return " and ".join(parts) if parts else "any value of the right type"


def _type_name(tp: Any) -> str:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):  # Optional[float] -> "float or null"
        return " or ".join("null" if a is type(None) else _type_name(a) for a in typing.get_args(tp))
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


class NonFiniteError(ConfigError):
    """A float key was given NaN or an infinity (as a number, or as text such as ``nan``)."""


_NONFINITE_WORDS = {"nan", "inf", "infinity"}
_BOOL_WORDS = {False: ("off", "false", "no", "n"), True: ("on", "true", "yes", "y")}  # YAML 1.1 booleans


def _nonfinite(value: Any, key: str, meta: Mapping | None) -> NonFiniteError:
    shown = value.strip() if isinstance(value, str) else repr(value)
    allowed = _describe_range(meta or {})
    allowed = "a finite number" if allowed == "any value of the right type" else f"a finite number {allowed}"
    return NonFiniteError(f"{key}: {shown} is not a finite number; give {allowed}")


def _coerce(value: Any, tp: Any, key: str, meta: Mapping | None = None) -> Any:
    """Check ``value`` against annotation ``tp``; return it converted (lists to tuples).

    ``meta`` (the field's :func:`param` metadata) only words the messages: NaN and
    infinities are refused as "not a finite number" with the key's allowed range."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, key, meta)
            except NonFiniteError:
                raise  # a number, just not a usable one: say so, not "expected Optional"
            except ConfigError:
                pass
        raise ConfigError(f"{key}: expected {_type_name(tp)}, got {value!r}")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], f"{key}[{i}]", meta) for i, v in enumerate(value))
        if len(args) != len(value):
            raise ConfigError(f"{key}: expected a list of {len(args)} values, got {value!r}")
        return tuple(_coerce(v, a, f"{key}[{i}]", meta) for i, (a, v) in enumerate(zip(args, value)))
    if tp is Any:
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, str) and _SCI.fullmatch(value.strip()):
            value = float(value)  # YAML 1.1 reads 1e-4 (no dot) as a string
        if isinstance(value, str) and value.strip().lower().lstrip("+-.") in _NONFINITE_WORDS:
            raise _nonfinite(value, key, meta)  # YAML reads `nan` and `inf` (no dot) as strings
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise _nonfinite(value, key, meta)
        return value
    if tp is str:
        if isinstance(value, bool):
            # YAML 1.1 reads off/on/no/yes as booleans: `train.amp=off` means the choice "off"
            words = [w for w in _BOOL_WORDS[value] if w in ((meta or {}).get("choices") or ())]
            if len(words) == 1:
                return words[0]
            raise ConfigError(
                f"{key}: expected a string, got {value!r} (YAML reads off/on/no/yes as "
                f'true/false: quote the value, e.g. {key.rsplit(".", 1)[-1]}: "off")'
            )
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    raise TypeError(f"unsupported config annotation {tp!r} for {key}")


def _check_range(value: Any, meta: Mapping, key: str) -> None:
    if value is None:
        return
    values = value if isinstance(value, tuple) else (value,)
    for v in values:
        if meta.get("choices") is not None and v not in meta["choices"]:
            raise ConfigError(f"{key}: {v!r} is not allowed; expected {_describe_range(meta)}")
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            lo, hi = meta.get("lo"), meta.get("hi")
            bad = (lo is not None and (v <= lo if meta["lo_open"] else v < lo)) or (
                hi is not None and (v >= hi if meta["hi_open"] else v > hi)
            )
            if bad:
                raise ConfigError(f"{key}: {v!r} is out of range; expected {_describe_range(meta)}")


def from_dict(cls: type, data: dict | None, prefix: str = "") -> Any:
    """Build dataclass ``cls`` from a (possibly partial) nested dict, validating it."""
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise ConfigError(f"{prefix or 'config'}: expected a mapping of keys, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    unknown = [k for k in data if k not in fields]
    if unknown:
        k = unknown[0]
        close = difflib.get_close_matches(str(k), fields, n=1)
        hint = f"; did you mean '{prefix}{close[0]}'?" if close else ""
        raise ConfigError(f"unknown config key '{prefix}{k}'{hint} (valid keys here: {', '.join(fields)})")
    kwargs = {}
    for name, f in fields.items():
        key = prefix + name
        if f.metadata.get("section"):
            kwargs[name] = from_dict(hints[name], data.get(name), key + ".")
        elif name in data:
            value = _coerce(data[name], hints[name], key, f.metadata)
            _check_range(value, f.metadata, key)
            kwargs[name] = value
    return cls(**kwargs)


def to_dict(obj: Any) -> dict:
    """A plain nested dict (tuples become lists) of a config dataclass."""

    def conv(v: Any) -> Any:
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, tuple):
            return [conv(x) for x in v]
        return v

    return conv(obj)


def flatten(d: dict, prefix: str = "") -> dict:
    """{"a": {"b": 1}} -> {"a.b": 1}: dotted keys of a nested config dict."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(flatten(v, prefix + k + "."))
        else:
            out[prefix + k] = v
    return out


def parse_override(text: str) -> tuple[list[str], Any]:
    """Split ``a.b.c=value`` into (["a","b","c"], parsed YAML value)."""
    if "=" not in text:
        raise ConfigError(f"override {text!r} must look like key=value, e.g. sensor.exposure_s=0.05")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key:
        raise ConfigError(f"override {text!r} has an empty key")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError as exc:
        raise ConfigError(f"override {text!r}: value is not valid YAML ({exc})") from None
    return key.split("."), value


def merge_overrides(data: dict, overrides: list[str] | tuple[str, ...]) -> dict:
    """Apply dotted ``key=value`` overrides to a nested dict (returns a new dict)."""
    import copy

    data = copy.deepcopy(data)
    for text in overrides or ():
        path, value = parse_override(text)
        node = data
        for part in path[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override {text!r}: '{part}' is not a section")
        node[path[-1]] = value
    return data


#: leading bytes of binary files a user may give by mistake (a frame, a shard, an archive)
_BINARY_MAGIC = {
    b"\x89PNG": "a PNG image",
    b"II*\x00": "a TIFF image",
    b"MM\x00*": "a TIFF image",
    b"\x89HDF": "an HDF5 file",
    b"\x93NUMPY": "a NumPy .npy file",
    b"PK\x03\x04": "a zip archive",
    b"\x1f\x8b": "a gzip file",
    b"\xff\xd8\xff": "a JPEG image",
    b"SIMPLE  =": "a FITS file",
    b"%PDF": "a PDF document",
}


def _decode_text(raw: bytes, path: Path) -> str:
    """``raw`` as UTF-8 text (a UTF-8 byte-order mark dropped), or :class:`ConfigError` saying what it is.

    A binary file (known leading bytes, or a NUL among the first 8 KiB, as ``file`` and git
    tell text from binary) is "not a YAML text file"; text in another encoding (Latin-1 "µm"
    in a comment) names the first byte that is not UTF-8 and where it is."""
    kind = next((name for magic, name in _BINARY_MAGIC.items() if raw.startswith(magic)), None)
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise ConfigError(f"config file {path}: a UTF-16 text file, not UTF-8: save it as UTF-8")
    if kind is None and b"\x00" in raw[:8192]:
        kind = "a binary file"
    if kind is not None:
        raise ConfigError(f"config file {path}: not a YAML text file ({kind}); give the YAML config file")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ConfigError(
            f"config file {path}: not a UTF-8 text file (byte 0x{raw[exc.start]:02x} at offset "
            f"{exc.start}, line {line}): save it as UTF-8"
        ) from None


def read_yaml(path: str | Path) -> dict:
    """Read a YAML mapping, with a clear error for a missing, binary, non-UTF-8 or malformed file."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror or exc}") from None
    text = _decode_text(raw, path)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path} is not valid YAML: {exc}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path} must hold a mapping of keys at the top level")
    return data


def build(cls: type, data: dict | None = None, check=None) -> Any:
    """Build and validate config ``cls`` from a nested dict; ``check(cfg)`` covers multi-key rules."""
    cfg = from_dict(cls, data or {})
    if check is not None:
        check(cfg)
    return cfg


def load(cls: type, path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = (), check=None) -> Any:
    """Defaults, then the YAML file (if any), then ``key=value`` overrides; validated."""
    data = read_yaml(path) if path else {}
    return build(cls, merge_overrides(data, list(overrides)), check)


def help_table(cls: type) -> str:
    """Every key of ``cls`` with its default, allowed values and help text, one per line."""
    rows = describe(cls)
    width = max(len(r[0]) for r in rows)
    return "\n".join(f"{k:<{width}}  {d!r:<14} {allowed:<28} {doc}" for k, d, allowed, doc in rows)


def describe(cls: type, prefix: str = "") -> list[tuple[str, Any, str, str]]:
    """(dotted key, default, allowed, help) rows for documentation and ``--help``."""
    rows = []
    for f in dataclasses.fields(cls):
        if f.metadata.get("section"):
            rows += describe(typing.get_type_hints(cls)[f.name], prefix + f.name + ".")
        else:
            rows.append((prefix + f.name, f.default, _describe_range(f.metadata), f.metadata.get("doc", "")))
    return rows
