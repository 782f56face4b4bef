"""Settings recorded with a workspace: `<workspace>/settings.yaml`, what every command on that workspace uses.

The first `fullview run` records the settings it ran with, every key with its value and where the value came from
(``default``, the path of a pipeline.yaml given with -c, ``--set``); every later command reads them, so a plain
`status`, `eval`, `export`, `view`, `report` or `run` (no -c, no --set) sees the results that exist, from any folder.

How a command's settings are made, later layers winning:

1. the recorded settings when the workspace has them (and neither -c nor `run --reset-settings` is given), else the
   code's defaults (`fullview.sfm.options`; the repo's pipeline.yaml is a copy of them, a template);
2. with ``-c FILE``: the defaults updated by FILE (the recorded settings are replaced, not merged);
3. every ``--set stage.key=value``.

`run` records the result (under the run lock, before its stages run: an interrupted run resumes with the same
settings); the other commands only read. A recorded key this fullview no longer has, or a value its bounds now
refuse, is an error naming the key and what to do; never a silent reset. A key recorded as ``default`` whose default
has changed since keeps its recorded value (the results on disk were made with it), and `status` says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from fullview.io.artifacts import save_text
from fullview.io.config import (Config, ConfigError, default_config, layered_config, params_of, parse_override,
                                read_config_file)
from fullview.io.yamlio import YamlError, load_yaml
from fullview.sfm.options import OPTIONS_BY_SECTION, option_fields

FORMAT = 1  # the `fullview_settings` version of settings.yaml
DEFAULT = "default"
SET = "--set"
EARLIER_DEFAULT = "default when recorded"  # a recorded default that the code's default no longer equals
_RESET = "or run `fullview run DATASET --reset-settings` (back to the defaults)"

_HEADER = """\
# The settings of this workspace, recorded by `fullview run`: every fullview command on this workspace uses them.
# Change them with `fullview run DATASET --set stage.key=value` (or -c FILE); `--reset-settings` goes back to the
# defaults. Each key: its value, and where it came from (default, a pipeline.yaml given with -c, --set).
"""


@dataclass(kw_only=True)
class Settings:
    config: Config  # section -> its options instance: what the command uses
    sources: dict[str, str]  # "section.key" -> where its value comes from, for every key
    recorded: Config | None  # the workspace's recorded settings (None: none recorded)
    path: Path  # the workspace's settings.yaml
    earlier_defaults: dict[str, Any] = field(default_factory=dict)  # "section.key" -> today's default it differs from

    def values(self) -> dict[str, Any]:
        """Every "section.key" -> value."""
        return flat_values(self.config)

    def non_default(self) -> list[tuple[str, Any, str]]:
        """(key, value, source) of every key whose value differs from the code's default."""
        defaults = flat_values(default_config())
        return [(k, v, self.sources[k]) for k, v in self.values().items() if not _same(v, defaults[k])]


def flat_values(config: Config) -> dict[str, Any]:
    return {f"{section}.{k}": v for section, options in config.items() for k, v in params_of(options).items()}


def changes(before: Config, after: Config) -> list[tuple[str, Any, Any]]:
    """(key, old, new) of every key whose value differs between two configs."""
    old = flat_values(before)
    return [(k, old[k], v) for k, v in flat_values(after).items() if not _same(old[k], v)]


def effective_settings(ws, config_path: Path | None, overrides: list[str] = (), *, reset: bool = False) -> Settings:
    """The settings a command on `ws` uses (see the module's docstring for the layers)."""
    path = ws.path("settings")
    use_record = config_path is None and not reset
    recorded, recorded_config = None, None
    if path.exists():
        try:
            recorded = _read_recorded(path)
            recorded_config = layered_config([(str(path), recorded[0])])[0]
        except ConfigError as e:
            if use_record:  # -c and --reset-settings replace the record: a broken one is no obstacle
                raise ConfigError(f"{e}; edit {path} {_RESET}" if _RESET not in str(e) else str(e)) from None
            recorded, recorded_config = None, None
    layers: list[tuple[str, dict]] = []
    sources: dict[str, str] = {}
    if recorded is not None and use_record:
        layers.append((str(path), recorded[0]))
        sources.update(recorded[1])
    if config_path is not None:
        layers.append((str(config_path), read_config_file(Path(config_path))))
    for item in overrides:
        section, key, value = parse_override(item)
        layers.append((f"--set {item}", {section: {key: value}}))
    config, where = layered_config(layers)
    file_source = str(Path(config_path).resolve()) if config_path is not None else None
    for key, source in where.items():
        if source.startswith("--set "):
            sources[key] = SET
        elif source != str(path):
            sources[key] = file_source
    values, defaults = flat_values(config), flat_values(default_config())
    full = {k: sources.get(k, DEFAULT) for k in values}
    earlier = {k: defaults[k] for k, v in values.items()
               if full[k] in (DEFAULT, EARLIER_DEFAULT) and not _same(v, defaults[k])}
    for k in earlier:
        full[k] = EARLIER_DEFAULT
    return Settings(config=config, sources=full, recorded=recorded_config, path=path, earlier_defaults=earlier)


def record_settings(ws, settings: Settings) -> Path:
    """Write `settings` as the workspace's settings.yaml (atomically; the caller holds the run lock)."""
    if not ws.is_locked:
        raise RuntimeError(f"{ws.root}: recording settings needs the workspace lock")
    doc: dict[str, Any] = {"fullview_settings": FORMAT}
    for section, options in settings.config.items():
        doc[section] = {k: {"value": v, "from": settings.sources[f"{section}.{k}"]}
                        for k, v in params_of(options).items()}
    text = _HEADER + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, allow_unicode=True, width=120)
    return save_text(settings.path, text)


def _read_recorded(path: Path) -> tuple[dict[str, dict[str, Any]], dict[str, str]]:
    """The recorded values ({section: {key: value}}) and sources ("section.key" -> source) of a settings.yaml."""
    try:
        data = load_yaml(path, str(path))
    except YamlError as e:
        raise ConfigError(f"{e}; fix it {_RESET}") from None
    if not isinstance(data, dict) or data.get("fullview_settings") != FORMAT:
        raise ConfigError(f"{path}: not a fullview settings file (format {FORMAT}); delete it {_RESET}")
    values: dict[str, dict[str, Any]] = {}
    sources: dict[str, str] = {}
    for section, items in data.items():
        if section == "fullview_settings":
            continue
        if section not in OPTIONS_BY_SECTION:
            raise ConfigError(f"{path}: {section!r} is not a settings section of this fullview; remove it from "
                              f"{path} {_RESET}")
        if not isinstance(items, dict):
            raise ConfigError(f"{path}: section {section!r} must be a mapping of keys; fix it {_RESET}")
        known = {f.name for f in option_fields(OPTIONS_BY_SECTION[section])}
        for key, entry in items.items():
            if key not in known:
                raise ConfigError(f"{path}: {section}.{key} is no longer a setting of fullview; remove it from "
                                  f"{path} {_RESET}")
            if not isinstance(entry, dict) or set(entry) != {"value", "from"} or not isinstance(entry["from"], str):
                raise ConfigError(f"{path}: {section}.{key} must be {{value: ..., from: ...}}, got {entry!r}; fix it "
                                  f"{_RESET}")
            values.setdefault(section, {})[key] = entry["value"]
            sources[f"{section}.{key}"] = entry["from"]
    return values, sources


def _same(a: Any, b: Any) -> bool:
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))
