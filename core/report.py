"""Compatibility name: the evaluation's arithmetic lives in ``core.decide.evaluate``."""

from .decide.evaluate import *  # noqa: F401,F403
from .decide.evaluate import __all__  # noqa: F401
from .decide.evaluate import _fit_median  # noqa: F401
