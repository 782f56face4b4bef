"""One source of settings: every key has a default, bounds and a meaning in sfm/options.py; the loader enforces every
bound with an error naming the key; every key is read by the code it configures; docs/configuration.md's table is
generated."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import fullview.stages.runner as runner
from fullview.io.config import ConfigError, checked_value, default_config, key_table_markdown, load_config
from fullview.io.dataset import Dataset
from fullview.io.workspace import Workspace
from fullview.sfm.options import OPTIONS_BY_SECTION, option_fields
from fullview.stages import PIPELINE
from fullview.stages.protocol import StageContext

CONFIGURATION_DOC = Path(__file__).resolve().parents[1] / "docs" / "configuration.md"
ALL_KEYS = [(s, f) for s, cls in OPTIONS_BY_SECTION.items() for f in option_fields(cls)]


def _ids(item):
    return f"{item[0]}.{item[1].name}"


def test_sections_are_the_pipeline_stages():
    assert list(OPTIONS_BY_SECTION) == list(PIPELINE)


@pytest.mark.parametrize("item", ALL_KEYS, ids=[_ids(k) for k in ALL_KEYS])
def test_every_key_has_meaning_and_its_default_passes_its_own_bounds(item):
    section, f = item
    assert f.metadata["doc"], f"{section}.{f.name} has no meaning"
    assert checked_value(f, f.default, f.name) == f.default


def _outside(f) -> list:
    """Values just outside each bound of a numeric field (0 excluded where it means 'automatic')."""
    meta, values = f.metadata, []
    step = 1 if isinstance(f.default, int) else 1e-6
    for key, delta in (("ge", -step), ("gt", 0), ("le", step), ("lt", 0)):
        if meta[key] is not None:
            v = type(f.default)(meta[key] + delta) if isinstance(f.default, int) else meta[key] + delta
            if not (meta["zero_means"] and v == 0):
                values.append(v)
    if meta["odd"]:
        values.append(f.default + 1)
    return values


BOUNDED = [(s, f) for s, f in ALL_KEYS if not isinstance(f.default, (bool, str)) and _outside(f)]


@pytest.mark.parametrize("item", BOUNDED, ids=[_ids(k) for k in BOUNDED])
def test_every_bound_is_enforced_with_an_error_naming_the_key(item):
    section, f = item
    for value in _outside(f):
        with pytest.raises(ConfigError, match=rf"{section}\.{f.name}"):
            load_config(None, [f"{section}.{f.name}={value!r}"])


FLOATS = [(s, f) for s, f in ALL_KEYS if isinstance(f.default, float)]


@pytest.mark.parametrize("item", FLOATS, ids=[_ids(k) for k in FLOATS])
@pytest.mark.parametrize("text", [".nan", ".inf", "-.inf"])
def test_non_finite_numbers_are_rejected_everywhere(item, text):
    section, f = item
    with pytest.raises(ConfigError, match=rf"{section}\.{f.name} must be a finite number"):
        load_config(None, [f"{section}.{f.name}={text}"])


@pytest.mark.parametrize("override, message", [
    ("matches.ratio=.nan", "finite"), ("densify.block_size=4", "odd"), ("densify.block_size=0", ">= 1"),
    ("densify.rect_height=0", ">= 16"), ("features.working_width=7", "or 0"), ("filter.threshold_deg=0", "> 0"),
    ("densify.neighbours=-1", ">= 1"), ("matches.pairs=random", "one of"), ("filter.seed=true", "must be int"),
    ("features.denoise_min_noise=-1", ">= 0"),
])
def test_the_reported_bad_values_are_refused(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override])


@pytest.mark.parametrize("overrides, rule", [
    (["features.min_latitude_deg=30", "features.max_latitude_deg=10"], "min_latitude_deg < max_latitude_deg"),
    (["densify.min_triangulation_angle_deg=50", "densify.max_triangulation_angle_deg=40"],
     "min_triangulation_angle_deg < max_triangulation_angle_deg"),
])
def test_cross_key_rules(overrides, rule):
    with pytest.raises(ConfigError, match=rule):
        load_config(None, overrides)


@pytest.mark.parametrize("text, message", [
    ("features:\n  working_width: 1024\n  working_width: 512\n", "duplicate key"),
    ("- 1\n- 2\n", "expected a mapping"), ("features: [1, 2]\n", "must be a mapping"),
    ("nosuch:\n  a: 1\n", "unknown section"), ("features:\n  nosuch: 1\n", "unknown key features.nosuch"),
    ("features: {working_width: [1,\n", "not valid YAML"),
])
def test_bad_files(tmp_path, text, message):
    path = tmp_path / "pipeline.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_config(path)


def test_a_folder_as_config_and_bad_set_syntax(tmp_path):
    with pytest.raises(ConfigError, match="not a file"):
        load_config(tmp_path)
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(None, ["features.working_width=[1,"])
    with pytest.raises(ConfigError, match="expected stage.key=value"):
        load_config(None, ["working_width=3"])


def test_the_documented_key_table_is_the_generated_one():
    assert key_table_markdown() in CONFIGURATION_DOC.read_text(), \
        "docs/configuration.md's key table is stale: run python docs/generate.py"


# ------------------------------------------------------------------------------------------------ hypothesis
_scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=True),
                     st.text(max_size=8))
_key_names = st.sampled_from([f.name for _, f in ALL_KEYS] + ["bogus"])
_sections = st.dictionaries(st.sampled_from(list(OPTIONS_BY_SECTION) + ["bogus"]),
                            st.one_of(_scalars, st.dictionaries(_key_names, _scalars, max_size=4)), max_size=4)


def _valid(config) -> bool:
    for section, options in config.items():
        for f in option_fields(type(options)):
            value = getattr(options, f.name)
            if isinstance(value, float) and not math.isfinite(value):
                return False
            checked_value(f, value, f.name)  # raises if out of bounds
    return True


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=_sections)
def test_loader_never_crashes_nor_accepts_bad_values(tmp_path, data):
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(data))
    try:
        config = load_config(path)
    except ConfigError as e:
        assert "\n" not in str(e)
        return
    assert _valid(config)


@settings(max_examples=150, deadline=None)
@given(key=st.sampled_from([_ids(k) for k in ALL_KEYS]), raw=st.text(max_size=12))
def test_set_overrides_never_crash(key, raw):
    try:
        config = load_config(None, [f"{key}={raw}"])
    except ConfigError:
        return
    assert _valid(config)


# ------------------------------------------------------------------------------------------------ keys are used
class _Recorder:
    """Forwards attribute reads to the options object and remembers their names."""

    def __init__(self, options, seen: set):
        object.__setattr__(self, "_options", options)
        object.__setattr__(self, "_seen", seen)

    def __getattr__(self, name):
        self._seen.add(name)
        return getattr(self._options, name)


def test_every_key_is_read_by_the_stage_it_configures(tiny_dataset, tmp_path, monkeypatch, tiny_set_args):
    seen: dict[str, set] = {s: set() for s in OPTIONS_BY_SECTION}
    original = StageContext

    def recording_context(*, options, **kw):
        section = next(s for s, cls in OPTIONS_BY_SECTION.items() if isinstance(options, cls))
        return original(options=_Recorder(options, seen[section]), **kw)

    monkeypatch.setattr(runner, "StageContext", recording_context)
    dataset = Dataset(tiny_dataset)
    config = load_config(None, [a for a in tiny_set_args if a != "--set"] + ["densify.working_width=512", "densify.rect_height=256",
                                                 "densify.min_pair_inliers=30"])
    runner.Pipeline(dataset, Workspace(tmp_path / "ws", dataset.name), config).run()
    unread = [f"{s}.{f.name}" for s, f in ALL_KEYS if f.name not in seen[s]]
    assert not unread, f"settings no code reads: {unread}"


def test_defaults_are_the_option_classes():
    assert load_config(None) == default_config()
