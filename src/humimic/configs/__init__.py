"""Configuration dataclasses and their named variants (factory functions)."""

from humimic.configs.retarget import RetargetConfig, retarget_default, retarget_fast

__all__ = ["RetargetConfig", "retarget_default", "retarget_fast"]
