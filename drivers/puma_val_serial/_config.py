"""Reading the driver's configuration files: YAML mappings whose keys are a dataclass's fields."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import yaml

from selfview.errors import ConfigError


def read_yaml(path, what: str) -> dict:
    """The mapping in a YAML file (empty file: {}); ``ConfigError`` naming the file otherwise."""
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text())
    except OSError as exc:
        raise ConfigError(f"{what} file {str(p)!r}: cannot read ({exc.strerror or exc})") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"{what} file {str(p)!r}: not valid YAML ({exc})") from exc
    if data is not None and not isinstance(data, dict):
        raise ConfigError(f"{what} file {str(p)!r}: expected a mapping, got {type(data).__name__}")
    return data or {}


def check_keys(data, cls, what: str) -> dict:
    """``data`` if it is a mapping whose keys are all fields of dataclass ``cls``, else ``ConfigError``."""
    if not isinstance(data, dict):
        raise ConfigError(f"{what}: expected a mapping, got {type(data).__name__} {data!r}")
    names = {f.name for f in fields(cls)}
    unknown = set(data) - names
    if unknown:
        raise ConfigError(
            f"{what}: unknown key(s) {', '.join(sorted(map(str, unknown)))}; expected some of {', '.join(sorted(names))}"
        )
    return data
