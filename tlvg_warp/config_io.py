"""One config scheme for every command: dataclass configs with nested sections, and ONE loader.

A config is a dataclass; a field whose type is itself a dataclass is a *section* (``lr``, ``density``,
``loss``, ...). In YAML a section is a nested mapping; on the command line a dotted key
(``--set loss.w_align=0.1``). Loading (``load``): the class defaults (or a base config, e.g. a checkpoint's),
then the YAML file after its ``base: other.yaml`` chain (relative to the file, base first), then the
``key=value`` overrides (values parsed as YAML). Every error is one InputError line naming the file (or
``--set``) and the key: unknown keys with the closest known ones, values coerced strictly to the annotated
type, range rules (a class's ``RULES``) and its own ``check()``. A class's ``RENAMED`` maps old flat names to
their dotted place; they still load, with one deprecation line on stderr once the config is valid.

``config_yaml`` writes the resolved config back, one ``key: value  # comment`` line per field (the comment
is the field's trailing comment in the class source), sections indented; it loads back unchanged.
"""
from __future__ import annotations

import copy
import dataclasses
import difflib
import functools
import inspect
import math
import re
import sys
import typing
from pathlib import Path

import yaml

from .errors import InputError


class ConfigError(InputError):
    """A config value out of its rules; ``key`` is its dotted name (so the loader can name its file)."""

    def __init__(self, key: str, message: str):
        self.key = key
        super().__init__(f"config {key} {message}")


def read_yaml_mapping(path, what: str = "config file") -> dict:
    """A YAML file holding a mapping, as a dict; one-line InputErrors naming the file (missing, not YAML,
    not a mapping). Every YAML the project reads (configs, studies, run folders) goes through here."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{what} does not exist" + _presets_hint(p, what), p)
    try:
        d = yaml.safe_load(p.read_text()) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise InputError(f"not valid YAML ({str(e).splitlines()[0]})", p) from None
    if not isinstance(d, dict):
        raise InputError("expected a YAML mapping of key: value", p)
    return d


# --- the schema: fields, sections, comments ---------------------------------------------------------------------
@functools.cache
def _types(cls) -> dict:
    """{field: resolved type} of a dataclass (annotations are strings under ``from __future__``)."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def _is_section(t) -> bool:
    return isinstance(t, type) and dataclasses.is_dataclass(t)


def field_comments(cls) -> dict:
    """{field: its trailing # comment} of a dataclass, from its source."""
    src = inspect.getsource(cls)
    return {m.group(1): m.group(2).strip() for m in re.finditer(r"^    (\w+): [^#\n]*#(.*)$", src, re.M)}


def keys(cls, prefix: str = "") -> list[str]:
    """Every setting of a config class as a dotted name, in declaration order."""
    out = []
    for name, t in _types(cls).items():
        out += keys(t, f"{prefix}{name}.") if _is_section(t) else [prefix + name]
    return out


def flatten(cfg, prefix: str = "") -> dict:
    """{dotted name: value} of a config instance."""
    out = {}
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        out.update(flatten(v, f"{prefix}{f.name}.") if dataclasses.is_dataclass(v) else {prefix + f.name: v})
    return out


def canonical(cls, key: str) -> str:
    """The dotted name of ``key`` (an old flat name becomes its new place; others are returned unchanged)."""
    new = getattr(cls, "RENAMED", {}).get(key)
    return (new[0] if isinstance(new, tuple) else new) if new else key


# --- coercion ---------------------------------------------------------------------------------------------------
def coerce(name: str, value, typ):
    """``value`` as ``typ`` (bool, int, float, str, list[...] and their ``| None``), strictly: no float for an
    int, no number for a bool; an InputError naming the key otherwise."""
    args = typing.get_args(typ)
    optional = type(None) in args
    if optional:
        typ = next(a for a in args if a is not type(None))
    try:
        if value is None:
            if optional:
                return None
            raise TypeError
        if typ is bool:
            if isinstance(value, str):
                low = value.lower()
                if low in ("true", "yes", "1", "on"):
                    return True
                if low in ("false", "no", "0", "off"):
                    return False
                raise ValueError
            if not isinstance(value, (bool, int)):
                raise TypeError
            return bool(value)
        if typ is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError
            return int(value)
        if typ is float:
            if isinstance(value, bool):
                raise TypeError
            return float(value)
        if typ is str:
            if isinstance(value, (list, dict)):
                raise TypeError
            return str(value)
        if typing.get_origin(typ) is list or typ is list:
            if not isinstance(value, (list, tuple)):
                raise TypeError
            (item,) = typing.get_args(typ) or (float,)
            return [coerce(name, v, item) for v in value]
    except (TypeError, ValueError):
        shown = getattr(typ, "__name__", str(typ)) + (" or null" if optional else "")
        raise InputError(f"config {name}: cannot use {value!r} as {shown}") from None
    return value


# --- applying mappings ------------------------------------------------------------------------------------------
def _unknown(cls, key: str, where) -> InputError:
    """'unknown config key' with the closest dotted names (matched on the whole key and on its last part)."""
    known = keys(cls)
    last = key.rsplit(".", 1)[-1]
    score = {k: max(difflib.SequenceMatcher(None, key, k).ratio(),
                    difflib.SequenceMatcher(None, last, k.rsplit(".", 1)[-1]).ratio()) for k in known}
    close = [k for k, s in sorted(score.items(), key=lambda kv: -kv[1]) if s >= 0.6][:3]
    hint = f"; did you mean {', '.join(close)}?" if close else f" (known keys: {', '.join(known)})"
    return InputError(f"unknown config key {key!r}{hint}", where)


def _set(cfg, key: str, value, where, origin: dict, notes: list, root=None) -> None:
    """Set dotted ``key`` of ``cfg`` (in place); a mapping value on a section sets its keys."""
    root = cfg if root is None else root
    head, _, rest = key.partition(".")
    types = _types(type(cfg))
    if head not in types:
        renamed = getattr(type(root), "RENAMED", {})
        if cfg is root and key in renamed:  # an old flat name: set its new place
            new = renamed[key]
            new_key, merge = new if isinstance(new, tuple) else (new, None)
            if merge is not None:
                value = merge(flatten(root)[new_key], value)
            notes.append(f"{key} -> {new_key}")
            _set(root, new_key, value, where, origin, notes, root)
            return
        raise _unknown(type(root), _path(cfg, root) + key, where)
    t = types[head]
    if _is_section(t):
        sub = getattr(cfg, head)
        if rest:
            _set(sub, rest, value, where, origin, notes, root)
            return
        if not isinstance(value, dict):
            raise InputError(f"config {_path(cfg, root)}{head} is a section: expected a mapping of its keys, "
                             f"got {value!r}", where)
        for k, v in value.items():
            _set(sub, str(k), v, where, origin, notes, root)
        return
    if rest:
        raise _unknown(type(root), _path(cfg, root) + key, where)
    full = _path(cfg, root) + head
    setattr(cfg, head, coerce(full, value, t))
    origin[full] = where


def _path(cfg, root) -> str:
    """The dotted prefix of section ``cfg`` inside ``root`` ('' for the root)."""
    if cfg is root:
        return ""
    for f in dataclasses.fields(root):
        v = getattr(root, f.name)
        if v is cfg:
            return f.name + "."
        if dataclasses.is_dataclass(v):
            p = _path(cfg, v)
            if p:
                return f"{f.name}.{p}"
    return ""


def from_dict(cls, d: dict, base=None, *, where=None, origin=None, notes=None):
    """A config of ``cls``: ``base`` (default: the class defaults) with the (nested or dotted) mapping ``d``."""
    cfg = copy.deepcopy(base) if base is not None else cls()
    origin = {} if origin is None else origin
    notes = [] if notes is None else notes
    for k, v in (d or {}).items():
        _set(cfg, str(k), v, where, origin, notes)
    return cfg


def yaml_chain(path, _seen=None) -> list[tuple[Path, dict]]:
    """[(file, mapping)] of ``path`` and its ``base:`` ancestors, the farthest base first."""
    p = Path(path)
    seen = set() if _seen is None else _seen
    d = read_yaml_mapping(p)
    if p.resolve() in seen:
        raise InputError("config base: chain loops back to this file", p)
    seen.add(p.resolve())
    base = d.pop("base", None)
    return ([] if base is None else yaml_chain(p.parent / str(base), seen)) + [(p, d)]


def parse_override(ov: str) -> tuple[str, object]:
    """``key=value`` -> (key, value parsed as YAML)."""
    if "=" not in ov:
        raise InputError(f"--set expects key=value, got {ov!r}")
    k, v = ov.split("=", 1)
    try:
        val = yaml.safe_load(v)
    except yaml.YAMLError:
        val = v
    return k.strip(), val


def load(cls, path=None, overrides=(), base=None, *, quiet: bool = False):
    """Defaults (or ``base``), then the YAML file with its ``base:`` chain, then ``key=value`` overrides;
    validated. Old flat names print one note line each on stderr (after everything loaded: a config that
    fails says only why it fails)."""
    cfg = copy.deepcopy(base) if base is not None else cls()
    origin, notes = {}, []
    if path is not None:
        for file, d in yaml_chain(path):
            cfg = from_dict(cls, d, cfg, where=file, origin=origin, notes=notes)
    for ov in overrides:
        k, v = parse_override(ov)
        cfg = from_dict(cls, {k: v}, cfg, where="--set", origin=origin, notes=notes)
    try:
        validate(cfg)
    except ConfigError as e:
        where = origin.get(e.key)
        if isinstance(where, Path):
            raise InputError(str(e), where) from None
        raise
    if notes and not quiet:
        print(f"note: old config keys (they still load; rename them): {', '.join(dict.fromkeys(notes))}",
              file=sys.stderr)
    return cfg


# --- validation -------------------------------------------------------------------------------------------------
def validate(cfg, prefix: str = ""):
    """Apply each class's ``RULES`` {field: rule} and ``check()`` to ``cfg`` and its sections; returns cfg.
    Rules: (">=", x) / (">", x) a finite number, ("in", lo, hi) a closed range, ("of", a, b, ...) a choice."""
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            validate(v, f"{prefix}{f.name}.")
    for name, rule in getattr(type(cfg), "RULES", {}).items():
        v, key = getattr(cfg, name), prefix + name
        op, *arg = rule
        if op == "of":
            if v not in arg:
                raise ConfigError(key, f"must be one of {', '.join(map(str, arg))}, got {v!r}")
            continue
        number = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        if op == ">=" and not (number and v >= arg[0]):
            raise ConfigError(key, f"must be {'a finite number ' if arg[0] == 0 else ''}>= {arg[0]}, got {v}")
        if op == ">" and not (number and v > arg[0]):
            raise ConfigError(key, f"must be a number > {arg[0]}, got {v}")
        if op == "in" and not (number and arg[0] <= v <= arg[1]):
            raise ConfigError(key, f"must be in [{arg[0]}, {arg[1]}], got {v}")
    check = getattr(cfg, "check", None)
    if check is not None:
        check(prefix)
    return cfg


def check_run_settings(cfg, prefix: str = "") -> None:
    """The settings every command shares: ``device``, ``background`` and ``render_headroom``."""
    if cfg.device not in ("auto", "cpu", "cuda") and not str(cfg.device).startswith("cuda:"):
        raise ConfigError(prefix + "device", f"must be auto, cpu or cuda, got {cfg.device!r}")
    if cfg.background is not None and len(cfg.background) != 3:
        raise ConfigError(prefix + "background", f"must be 3 numbers, got {cfg.background!r}")
    h = getattr(cfg, "render_headroom", 0)
    if not (isinstance(h, (int, float)) and (h == 0 or 1 < h <= 16)):
        raise ConfigError(prefix + "render_headroom", f"must be 0 (exact counts) or in (1, 16], got {h!r}")


# --- writing ----------------------------------------------------------------------------------------------------
def config_yaml(cfg, header: str) -> str:
    """A resolved config as YAML, one ``key: value  # comment`` line per field, sections indented."""
    return "\n".join([f"# {header}", *_yaml_lines(cfg, "")]) + "\n"


def _yaml_lines(cfg, indent: str) -> list[str]:
    comments = field_comments(type(cfg))
    lines = []
    for f in dataclasses.fields(cfg):
        v, c = getattr(cfg, f.name), comments.get(f.name)
        tail = f"  # {c}" if c else ""
        if dataclasses.is_dataclass(v):
            lines += [f"{indent}{f.name}:{tail}", *_yaml_lines(v, indent + "  ")]
            continue
        s = yaml.safe_dump({f.name: v}, default_flow_style=True, width=1000).strip()
        lines.append(indent + (s[1:-1] if s.startswith("{") else s) + tail)
    return lines


# --- the configs that ship with the tool ------------------------------------------------------------------
CONFIG_DIRS = (Path(__file__).resolve().parents[1] / "configs",  # a source tree (or an editable install)
               Path(__file__).resolve().parent / "configs")  # where a wheel puts configs/ (package data)


def shipped_config(name: str = "tlvg.yaml") -> Path | None:
    """A config that ships with the tool: the source tree's configs/NAME, else the copy a wheel installed (a user
    who ran `pip install` gets the tuned method, not the bare defaults); None when neither exists."""
    for folder in CONFIG_DIRS:
        if (folder / name).is_file():
            return folder / name
    return None


def _named_bare(path: Path) -> bool:
    """A config given as a preset's name (``abcgs``, ``abcgs.yaml``, ``configs/abcgs.yaml``), not a path elsewhere."""
    return path.parent in (Path("."), Path("configs"))


def _presets_hint(path: Path, what: str) -> str:
    """For a config named bare (``tlvg_textur``, ``configs/x.yaml``) that is neither a file nor a shipped preset:
    the presets that do ship, so a mistyped or retired name is one look away from the right one."""
    if what != "config file" or not _named_bare(path):
        return ""
    names = sorted({f.stem for d in CONFIG_DIRS if d.is_dir() for f in d.glob("*.yaml") if not f.stem.startswith("study_")})
    return f" (the shipped presets: {', '.join(names)})" if names else ""


def resolve_config(config, default: str | None = "tlvg.yaml") -> Path | None:
    """--config as given: a file that exists; else a shipped preset named as the README names it (configs/abcgs.yaml,
    abcgs.yaml or abcgs), so the presets work from any folder after `pip install`; else the path itself, which the
    loader reports as missing. No --config: the shipped ``default`` (None: the class defaults)."""
    if config is None:
        return shipped_config(default) if default else None
    path = Path(config)
    if path.is_file() or not _named_bare(path):
        return path
    return shipped_config(path.name if path.suffix else path.name + ".yaml") or path


__all__ = ["ConfigError", "read_yaml_mapping", "field_comments", "keys", "flatten", "canonical", "coerce",
           "from_dict", "yaml_chain", "parse_override", "load", "validate", "check_run_settings", "config_yaml",
           "CONFIG_DIRS", "shipped_config", "resolve_config"]
