"""Configuration dataclasses and their named variants (factory functions)."""

from humimic.configs.retarget import (
    DynamicsConfig,
    InteractionConfig,
    RetargetConfig,
    retarget_default,
    retarget_fast,
)

__all__ = [
    "DynamicsConfig",
    "InteractionConfig",
    "RetargetConfig",
    "retarget_default",
    "retarget_fast",
]
