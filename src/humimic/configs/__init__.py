"""Configuration dataclasses and their named variants (factory functions)."""

from humimic.configs.retarget import (
    InteractionConfig,
    RetargetConfig,
    retarget_default,
    retarget_fast,
)

__all__ = ["InteractionConfig", "RetargetConfig", "retarget_default", "retarget_fast"]
