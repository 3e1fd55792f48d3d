"""Configuration dataclasses and their named variants (factory functions)."""

from humimic.configs.retarget import (
    RETARGET_CONFIGS,
    DynamicsConfig,
    InteractionConfig,
    RetargetConfig,
    retarget_default,
    retarget_fast,
)

__all__ = [
    "RETARGET_CONFIGS",
    "DynamicsConfig",
    "InteractionConfig",
    "RetargetConfig",
    "retarget_default",
    "retarget_fast",
]
