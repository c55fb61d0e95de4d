"""Reading the driver's configuration files: YAML mappings whose keys are a dataclass's fields."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

from selfview.errors import ConfigError
from selfview.files.io_safe import load_yaml_file


def read_yaml(path, what: str) -> dict:
    """The mapping in a YAML file of at most ``MAX_YAML_BYTES`` (empty file: {}); ``ConfigError`` naming
    the file otherwise (not a regular file, too large, not YAML, aliases, too deep)."""
    p = Path(path)
    data = load_yaml_file(p, what=f"{what} file", source=f"{what} file {str(p)!r}")
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
