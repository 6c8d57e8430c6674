"""Config plumbing shared by every dataclass config: one-line field comments read from the class source
(they are dumped next to every run) and strict coercion of YAML / --set values to the field types."""
from __future__ import annotations

import dataclasses
import inspect
import re

from .errors import InputError


def read_yaml_mapping(path, what: str = "config file") -> dict:
    """A YAML file holding a mapping, as a dict; one-line InputErrors naming the file (missing, not YAML,
    not a mapping). Every YAML the project reads (configs, studies, run folders) goes through here."""
    from pathlib import Path

    import yaml

    p = Path(path)
    if not p.is_file():
        raise InputError(f"{what} does not exist", p)
    try:
        d = yaml.safe_load(p.read_text()) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise InputError(f"not valid YAML ({str(e).splitlines()[0]})", p) from None
    if not isinstance(d, dict):
        raise InputError("expected a YAML mapping of key: value", p)
    return d


def field_comments(cls) -> dict:
    """{field: its trailing # comment} of a dataclass, from its source."""
    src = inspect.getsource(cls)
    return {m.group(1): m.group(2).strip() for m in re.finditer(r"^    (\w+): [^#\n]*#(.*)$", src, re.M)}


def config_yaml(cfg, header: str) -> str:
    """A resolved dataclass config as YAML, one ``key: value  # comment`` line per field (loads back unchanged)."""
    import yaml

    comments = field_comments(type(cfg))
    lines = [f"# {header}"]
    for f in dataclasses.fields(cfg):
        v = yaml.safe_dump({f.name: getattr(cfg, f.name)}, default_flow_style=True, width=1000).strip()
        v = v[1:-1] if v.startswith("{") else v
        c = comments.get(f.name)
        lines.append(f"{v}  # {c}" if c else v)
    return "\n".join(lines) + "\n"


def coerce(name: str, value, typ):
    typ = str(typ)
    try:
        if value is None:
            if "None" in typ:
                return None
            raise TypeError
        if typ.startswith("bool"):
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
        if typ.startswith("int"):
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError
            return int(value)
        if typ.startswith("float"):
            if isinstance(value, bool):
                raise TypeError
            return float(value)
        if typ.startswith("str"):
            return str(value)
        if typ.startswith("list"):
            if not isinstance(value, (list, tuple)):
                raise TypeError
            return [float(v) for v in value]
    except (TypeError, ValueError):
        raise InputError(f"config {name}: cannot use {value!r} as {typ}") from None
    return value




def apply_overrides(cfg, overrides, from_dict):
    """Apply ``key=value`` strings (values parsed as YAML scalars) to ``cfg`` through ``from_dict(d, cfg)``."""
    import yaml

    for ov in overrides:
        if "=" not in ov:
            raise InputError(f"--set expects key=value, got {ov!r}")
        k, v = ov.split("=", 1)
        try:
            val = yaml.safe_load(v)
        except yaml.YAMLError:
            val = v
        cfg = from_dict({k.strip(): val}, cfg)
    return cfg
