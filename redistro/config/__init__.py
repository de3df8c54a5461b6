"""Typed, validated configuration (YAML in, frozen dataclasses out)."""

from redistro.config.loader import DEFAULT_CONFIG_PATH, load_config, parse_override
from redistro.config.model import Config, NodeConfig, SchedulingConfig, SessionConfig

__all__ = [
    "DEFAULT_CONFIG_PATH",
    "Config",
    "NodeConfig",
    "SchedulingConfig",
    "SessionConfig",
    "load_config",
    "parse_override",
]
