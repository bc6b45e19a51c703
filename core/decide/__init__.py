"""The decision between the grid and the hierarchical structures, one module per part:

- ``cost``      the cost model: per-scene records, the fitted constants, the estimates,
                and the break-even formula R* = T_B^H / (t_G - t_H);
- ``calfile``   the calibration file: its JSON format, where it holds, the load policy;
- ``measurements`` timing builds and traces, the calibration run, the true break-even;
- ``rule``      the plan's one decision rule (least predicted cost, ties to the grid);
- ``evaluate``  the paper's evaluation tables, from measured and estimated numbers.

``core.plan`` puts them together for one scene.
"""

from .calfile import (CALIBRATION_FORMAT, DEFAULT_PATH, Calibration, CalibrationError, current_version, load,
                      load_default, load_or_default, machine_fingerprint, package_version)
from .cost import (DEFAULT_MODEL, DEFAULT_SPREAD, MODELS, Estimate, KindFit, Measurement, SceneRecord, break_even, fit,
                   log2n, nlog2n)
from .measurements import (GRID_LARGE_RAYS, QUIET_SHARE, RAYS_PER_SCENE, SAMPLE_LADDER, BreakEven, OthersShare,
                           available_kinds, break_even_jobs, calibrate, in_passes, measure, measure_break_even,
                           measure_break_evens, prepare_mesh, time_trace, warm_up)
from .rule import REUSES_SAMPLES, choose
