"""Typed config loading: TOML, overrides, clear errors for unknown keys and bad values."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from papl_mapper.config import config_to_dict, dump_toml, load_config
from papl_mapper.errors import ConfigError


@dataclass
class Inner:
    tau: float = 2.0
    """a threshold"""
    mode: str = "soft"


@dataclass
class Outer:
    seed: int = 0
    verbose: bool = False
    inner: Inner = field(default_factory=Inner)
    sizes: tuple[int, ...] = (1, 2)


def test_defaults_file_and_overrides(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text("seed = 4\n[inner]\ntau = 3.5\n")
    c = load_config(Outer, f, ["inner.mode=hard", "verbose=true", "sizes=3,4"])
    assert (c.seed, c.inner.tau, c.inner.mode, c.verbose, c.sizes) == (4, 3.5, "hard", True, (3, 4))


def test_round_trip_through_toml(tmp_path):
    c = load_config(Outer, None, ["inner.tau=7.25", "seed=9"])
    f = tmp_path / "out.toml"
    f.write_text(dump_toml(config_to_dict(c)))
    assert load_config(Outer, f) == c


@pytest.mark.parametrize(
    "override, message",
    [
        ("nope=1", "unknown config key 'nope'"),
        ("inner.tau=abc", "expected float"),
        ("seed=1.5", "expected int"),
        ("verbose=maybe", "true or false"),
        ("seed", "key=value"),
    ],
)
def test_bad_overrides(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(Outer, None, [override])


def test_bad_file(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text("seed = [unclosed")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(Outer, f)
    with pytest.raises(ConfigError, match="not found"):
        load_config(Outer, tmp_path / "none.toml")


def test_run_config_has_one_source_for_the_windowed_ba_interval():
    """`mapping.refine_every` is the setting (run time rewrote it from `local_ba_every` before, so a
    --set of it was silently lost); the old key names the new one."""
    from papl_mapper.pipelines.config import RunConfig

    cfg = load_config(RunConfig, None, ["mapping.refine_every=5"])
    assert cfg.mapping.refine_every == 5 and not hasattr(cfg, "local_ba_every")
    with pytest.raises(ConfigError, match="'local_ba_every' is now 'mapping.refine_every'"):
        load_config(RunConfig, None, ["local_ba_every=5"])


def test_run_config_has_one_seed():
    """`seed` is the only seed (the pipeline passes it to every stage); the per-stage seeds of older
    config files name it."""
    import dataclasses

    from papl_mapper.pipelines.config import RunConfig

    def seeds(obj, prefix=""):
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            if dataclasses.is_dataclass(value):
                yield from seeds(value, f"{prefix}{f.name}.")
            elif f.name == "seed":
                yield prefix + f.name

    assert list(seeds(RunConfig())) == ["seed"]
    for key in ("mapping.pnp.seed", "frontend.vp.seed", "focal.seed"):
        with pytest.raises(ConfigError, match=f"'{key}' is now 'seed'"):
            load_config(RunConfig, None, [f"{key}=3"])


def test_every_axis_setting_is_in_the_axes_section():
    """Association, the update after BA and the support a new axis needs are `axes.*` (they were
    spread over `variant` and the top level); the presets set them there and old keys name them."""
    from papl_mapper.pipelines.config import PRESETS, RunConfig

    cfg = load_config(RunConfig, None, PRESETS["hard-association"] + PRESETS["no-axis-management"])
    assert (cfg.axes.association, cfg.axes.update, cfg.axes.min_support_fraction) == ("hard", False, 0.01)
    for old, new in (
        ("variant.association=hard", "axes.association"),
        ("variant.axis_management=false", "axes.update"),
        ("axis_min_support_fraction=0.1", "axes.min_support_fraction"),
    ):
        with pytest.raises(ConfigError, match=f"is now '{new}'"):
            load_config(RunConfig, None, [old])
