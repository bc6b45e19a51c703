"""Compatibility names: the calibration's parts live in ``core.decide`` (``cost``: the
model and its fit; ``calfile``: the file and load policy; ``measurements``: the measuring)."""

from .decide.calfile import (CALIBRATION_FORMAT, DEFAULT_PATH, Calibration, CalibrationError, _builtin_fallback,  # noqa: F401
                             _first_difference, current_version, load, load_default, load_or_default,
                             machine_fingerprint, package_version)
from .decide.cost import (DEFAULT_MODEL, DEFAULT_SPREAD, MODELS, Estimate, KindFit, Measurement, SceneRecord,  # noqa: F401
                          _affine_lsq, _estimate_affine, _estimate_paper, _fit_affine, _fit_paper, _spread, break_even,
                          fit, log2n, nlog2n)
from .decide.measurements import (GRID_LARGE_RAYS, RAYS_PER_SCENE, SAMPLE_LADDER, BreakEven, _grid_samples,  # noqa: F401
                             _prepare, _size_hint, available_kinds, calibrate, measure, measure_break_even, time_trace,
                             warm_up)
