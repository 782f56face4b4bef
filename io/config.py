"""pipeline.yaml: one section per stage, loaded into the option dataclasses of `fullview.sfm.options`.

Defaults, types, bounds and meanings all come from those classes; this module only reads YAML and `--set`
overrides and checks every value against them: unknown sections and keys, wrong types, NaN or infinity, values out
of bounds and broken cross-key rules are errors naming the key.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

from fullview.io import limits
from fullview.io.errors import FullviewError
from fullview.io.yamlio import YamlError, load_yaml
from fullview.sfm.options import OPTIONS_BY_SECTION, option_fields

Config = dict[str, Any]  # section name -> its options dataclass instance


class ConfigError(FullviewError, ValueError):
    """pipeline.yaml or a --set override is invalid."""


def default_config() -> Config:
    return {section: cls() for section, cls in OPTIONS_BY_SECTION.items()}


def params_of(options) -> dict[str, Any]:
    """The settings of one section as a plain dict (manifests, fingerprints)."""
    return dataclasses.asdict(options)


def load_config(path: Path | None, overrides: list[str] = ()) -> Config:
    """Defaults, updated by the YAML file at `path` (optional) and by `stage.key=value` overrides."""
    values: dict[str, dict[str, Any]] = {s: {} for s in OPTIONS_BY_SECTION}
    where: dict[tuple[str, str], str] = {}
    if path is not None:
        for section, items in _read_file(Path(path)).items():
            _collect(values, where, section, items, str(path))
    for item in overrides:
        key, sep, raw = item.partition("=")
        section, dot, name = key.partition(".")
        if not sep or not dot:
            raise ConfigError(f"--set {item!r}: expected stage.key=value")
        source = f"--set {item}" if item.isprintable() else f"--set {item!r}"  # a newline would split the message
        try:
            value = load_yaml(raw, source)
        except YamlError as e:
            raise ConfigError(str(e)) from None
        _collect(values, where, section, {name: value}, source)
    config = {section: _build(OPTIONS_BY_SECTION[section], items, section, where)
              for section, items in values.items()}
    _check_memory(config, where)
    return config


def _check_memory(config: Config, where: dict) -> None:
    """Settings whose memory does not follow the images' size (which the dataset's pixel budget bounds) checked
    against this machine's memory: the cube faces' side."""
    face_size, limit = config["features"].face_size, limits.max_face_size()
    if face_size > limit:
        need = limits.FEATURES_IMAGES_AT_ONCE * limits.FACE_BYTES_PER_SIDE2 * face_size**2 / 2**30
        raise ConfigError(f"{where.get(('features', 'face_size'), 'defaults')}: features.face_size={face_size} "
                          f"needs about {need:.0f} GiB for its cube faces; at most {limit} fits "
                          f"({limits.memory_text()})")


def _read_file(path: Path) -> dict:
    if not path.exists():
        raise ConfigError(f"config file not found: {path}")
    if not path.is_file():
        raise ConfigError(f"{path}: not a file")
    try:
        data = load_yaml(path, str(path))
    except YamlError as e:
        raise ConfigError(str(e)) from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(f"{path}: cannot read ({getattr(e, 'strerror', None) or e})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of stage sections, got {type(data).__name__}")
    return data


def _collect(values: dict, where: dict, section: Any, items: Any, source: str) -> None:
    if section not in OPTIONS_BY_SECTION:
        raise ConfigError(f"{source}: unknown section {section!r} (known: {', '.join(OPTIONS_BY_SECTION)})")
    if items is None:
        return
    if not isinstance(items, dict):
        raise ConfigError(f"{source}: section {section!r} must be a mapping, got {type(items).__name__}")
    known = {f.name: f for f in option_fields(OPTIONS_BY_SECTION[section])}
    for key, value in items.items():
        if key not in known:
            raise ConfigError(f"{source}: unknown key {section}.{key} (known: {', '.join(known)})")
        values[section][key] = checked_value(known[key], value, f"{source}: {section}.{key}")
        where[section, key] = source


def checked_value(f: dataclasses.Field, value: Any, name: str) -> Any:
    """`value` converted to the field's type and checked against its bounds; ConfigError naming `name` if not."""
    meta = f.metadata
    if meta["choices"] is not None and isinstance(value, bool):  # name the choices rather than the type
        raise ConfigError(f"{name} must be one of {list(meta['choices'])}, got {value!r}")
    value = _typed(f, value, name)
    if meta["choices"] is not None:
        if value not in meta["choices"]:
            raise ConfigError(f"{name} must be one of {list(meta['choices'])}, got {value!r}")
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return value
    if meta["zero_means"] is not None and value == 0:
        return value
    for key, ok, text in (("ge", lambda v, b: v >= b, ">="), ("gt", lambda v, b: v > b, ">"),
                          ("le", lambda v, b: v <= b, "<="), ("lt", lambda v, b: v < b, "<")):
        bound = meta[key]
        if bound is not None and not ok(value, bound):
            zero = f" or 0 ({meta['zero_means']})" if meta["zero_means"] else ""
            raise ConfigError(f"{name} must be {text} {bound}{zero}, got {value!r}")
    if meta["odd"] and value % 2 == 0:
        raise ConfigError(f"{name} must be odd, got {value!r}")
    return value


def _typed(f: dataclasses.Field, value: Any, name: str) -> Any:
    expected = type(f.default)
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if type(value) is not expected:
        raise ConfigError(f"{name} must be {expected.__name__}, got {value!r} ({type(value).__name__})")
    if expected is float and not math.isfinite(value):
        raise ConfigError(f"{name} must be a finite number, got {value!r}")
    return value


def _build(cls: type, items: dict, section: str, where: dict) -> Any:
    options = cls(**items)
    for rule, holds in cls.RULES:
        if not holds(options):
            named = _rule_keys(cls, rule)
            # The sources of the keys the rule names (else of every key given for the section, else the defaults).
            keys = sorted({where[section, k] for k in named if (section, k) in where}
                          or {where.get((section, k), "defaults") for k in items} or {"defaults"})
            raise ConfigError(f"{', '.join(keys)}: {section}: {rule} must hold "
                              f"({', '.join(f'{section}.{k}={getattr(options, k)!r}' for k in named)})")
    return options


def _rule_keys(cls: type, rule: str) -> list[str]:
    """The settings a rule's text names, in order (its other words, such as 'when' or 'is', are prose)."""
    known = {f.name for f in option_fields(cls)}
    words = rule.replace("<", " ").replace(">", " ").replace("=", " ").replace(",", " ").split()
    return list(dict.fromkeys(word for word in words if word in known))


def key_table_markdown() -> str:
    """The README's table of every pipeline.yaml key, generated from the option classes."""
    lines = ["| key | default | allowed | meaning |", "|---|---|---|---|"]
    for section, cls in OPTIONS_BY_SECTION.items():
        for f in option_fields(cls):
            lines.append(f"| `{section}.{f.name}` | `{f.default!r}` | {_allowed(f)} | {f.metadata['doc']} |")
    return "\n".join(lines) + "\n"


def _allowed(f: dataclasses.Field) -> str:
    meta = f.metadata
    if meta["choices"]:
        return " \\| ".join(meta["choices"])
    if isinstance(f.default, bool):
        return "true \\| false"
    parts = [f"{op} {meta[k]}" for k, op in (("ge", "≥"), ("gt", ">"), ("le", "≤"), ("lt", "<")) if meta[k] is not None]
    if meta["odd"]:
        parts.append("odd")
    if meta["zero_means"]:
        parts.append(f"or 0 = {meta['zero_means']}")
    return ", ".join(parts) or "any"


# ------------------------------------------------------------------------------------------- layered settings
def parse_override(item: str) -> tuple[str, str, Any]:
    """A `--set stage.key=value` item as (section, key, value), the value read as YAML."""
    key, sep, raw = item.partition("=")
    section, dot, name = key.partition(".")
    if not sep or not dot:
        raise ConfigError(f"--set {item!r}: expected stage.key=value")
    try:
        return section, name, load_yaml(raw, f"--set {item}")
    except YamlError as e:
        raise ConfigError(str(e)) from None


def read_config_file(path: Path) -> dict:
    """A pipeline.yaml file's mapping of sections (not yet checked against the options)."""
    return _read_file(Path(path))


def layered_config(layers: list[tuple[str, dict]]) -> tuple[Config, dict[str, str]]:
    """The defaults updated by each layer in order, a (source, {section: {key: value}}) pair, every value checked as
    `load_config` checks it; also the source of every key a layer set ("section.key" -> source). io/settings.py
    layers a workspace's recorded settings, a pipeline.yaml and --set this way."""
    values: dict[str, dict[str, Any]] = {s: {} for s in OPTIONS_BY_SECTION}
    where: dict[tuple[str, str], str] = {}
    for source, data in layers:
        for section, items in data.items():
            _collect(values, where, section, items, source)
    config = {section: _build(OPTIONS_BY_SECTION[section], items, section, where) for section, items in values.items()}
    return config, {f"{section}.{key}": source for (section, key), source in where.items()}
