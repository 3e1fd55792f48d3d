"""humimic: human motion to humanoid robots.

Conventions: quaternions are ``wxyz`` everywhere inside humimic; the world frame is z-up, x
forward, metres and radians. Suffixes ``_w`` (world frame) and ``_b`` (body frame).
"""

from humimic.errors import HumimicError, InputError

__version__ = "0.1.0"

__all__ = ["HumimicError", "InputError", "__version__"]
