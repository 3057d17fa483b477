"""One TOML file that can set any setting of any service (``KMVIPE_CONFIG=path/to/kmvipe.toml``).

Every settings class derives from :class:`KmVipeSettings`. Its environment prefix names its table in the file —
``KMVIPE_FEATURES_`` reads ``[features]``, ``KMVIPE_BUS_`` reads ``[bus]``, ``KMVIPE_ROS2_ZENOH_`` reads
``[ros2_zenoh]`` — and each key of a table is a field name, in lower case, with a TOML value (arrays and numbers
natively, not the JSON strings of the environment)::

    [bus]
    mode = "client"
    connect = ["tls/router:7447"]

    [features]
    backbone = "dinov2-vitb14-reg"

Precedence, highest first: arguments given in code > environment > ``.env`` > secrets dir > this file >
defaults; so a deployment keeps its common settings in one file and a single ``KMVIPE_*`` variable still
overrides one of them. A table key that is not a setting, a table that belongs to no settings class, a key outside
any table and a file that is not TOML are errors (:class:`ConfigError` naming the file and the table, the line, or
the settings known): a typo must never be a setting silently not applied.

Only ``KMVIPE_CONFIG`` names the file (read from the process environment, not from ``.env``); there is no default
file looked up in the working directory, since every command works from any directory and a file found there by
accident would change a run's settings unseen. Relative paths inside the file are relative to the working
directory, as they are in the environment.
"""
from __future__ import annotations

import difflib
import os
import tomllib
from pathlib import Path
from typing import Any

from pydantic_settings import BaseSettings, InitSettingsSource, PydanticBaseSettingsSource

from .errors import ConfigError

CONFIG_ENV = "KMVIPE_CONFIG"
"""The environment variable that names the settings file (unset or empty: no file)."""
ENV_ROOT = "KMVIPE_"

TABLES = ("bus", "log", "metrics", "malloc", "streams", "shard", "ingest", "features", "ba", "mapstore", "query", "ros2",
          "ros2_zenoh")
"""Every table a file may hold: one per settings prefix (``KMVIPE_<TABLE>_``). Listed here, not collected from the
classes, because one process imports only its own service's classes, yet must still refuse a misspelt table meant
for another (tests/test_config_file.py checks this list against every settings class)."""

_FIELDS: dict[str, set[str]] = {}
"""Field names of the classes defined so far, per table: a subclass sharing its parent's prefix (ba's
``BaSettings`` over ``BASettings``) adds its fields to the same table."""


def table_of(settings_cls: type[BaseSettings]) -> str:
    """The table of a settings class: its ``env_prefix`` without ``KMVIPE_`` and the final ``_``, lower case."""
    prefix = settings_cls.model_config.get("env_prefix", "")
    if not prefix.startswith(ENV_ROOT) or not prefix.endswith("_"):
        raise TypeError(f"{settings_cls.__name__}: env_prefix must look like KMVIPE_<TABLE>_, got {prefix!r}")
    return prefix[len(ENV_ROOT):-1].lower()


def config_path(environ: dict[str, str] | None = None) -> Path | None:
    """The file ``KMVIPE_CONFIG`` names, or None when it is unset or empty."""
    value = (os.environ if environ is None else environ).get(CONFIG_ENV, "").strip()
    return Path(value) if value else None


def read_config(path: Path) -> dict[str, dict[str, Any]]:
    """The tables of a settings file, checked for shape: only known tables at the top, each a table."""
    try:
        with path.open("rb") as file:
            data = tomllib.load(file)
    except FileNotFoundError:
        raise ConfigError(f"{CONFIG_ENV} names {path}, which does not exist") from None
    except OSError as exc:
        raise ConfigError(f"{CONFIG_ENV} names {path}, which cannot be read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:  # its message ends with "(at line L, column C)"
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    for name, value in data.items():
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: {name!r} is outside any table; settings go in their service's table, e.g. "
                              f"[log] level = \"DEBUG\" (tables: {', '.join(TABLES)})")
        if name not in TABLES:
            raise ConfigError(f"{path}: [{name}] is not a settings table{_suggest(name, TABLES)}; "
                              f"tables: {', '.join(TABLES)}")
    return data


def table_values(path: Path, table: str) -> dict[str, Any]:
    """The keys of ``[table]`` in the file at ``path``, each checked to be a setting of that table."""
    values = read_config(path).get(table, {})
    known = _FIELDS.get(table, set())
    for key in values:
        if key not in known:
            raise ConfigError(f"{path}: [{table}] has no setting {key!r}{_suggest(key, known)}; "
                              f"settings of [{table}]: {', '.join(sorted(known))}")
    return values


def _suggest(word: str, choices) -> str:
    close = difflib.get_close_matches(word.lower(), sorted(choices), n=1)
    return f" (did you mean {close[0]!r}?)" if close else ""


class ConfigFileSource(InitSettingsSource):
    """The settings file's table of one class, as a pydantic-settings source (aliases handled as for init
    arguments)."""

    def __init__(self, settings_cls: type[BaseSettings]):
        path = config_path()
        super().__init__(settings_cls, table_values(path, table_of(settings_cls)) if path else {})

    def __repr__(self) -> str:
        return f"ConfigFileSource({CONFIG_ENV}={config_path()})"


class KmVipeSettings(BaseSettings):
    """Base of every KM-ViPE settings class: the environment, ``.env``, then the ``KMVIPE_CONFIG`` file."""

    @classmethod
    def __pydantic_init_subclass__(cls, **kwargs: Any) -> None:
        super().__pydantic_init_subclass__(**kwargs)
        if cls.model_config.get("env_prefix"):  # not an intermediate base without a table
            _FIELDS.setdefault(table_of(cls), set()).update(cls.model_fields)

    @classmethod
    def settings_customise_sources(
        cls, settings_cls: type[BaseSettings], init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource, dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # earlier sources win: the file only fills what nothing more specific set
        return init_settings, env_settings, dotenv_settings, file_secret_settings, ConfigFileSource(settings_cls)
