"""The decision between the grid and the hierarchical structures, one module per part:

- ``cost``      the cost model: per-scene records, the fitted constants, the estimates,
                and the break-even formula R* = T_B^H / (t_G - t_H);
- ``calfile``   the calibration file: its JSON format, where it holds, the load policy;
- ``measurements`` timing builds and traces as a caller would, and the calibration run;
- ``settle``    what comes before every timed build (memory written, a rest, a busy spin);
- ``load_watch`` other processes' share of the CPU, retaken rounds, passes over scenes;
- ``truth``     the true break-even of the paper's evaluation, measured;
- ``rule``      the plan's one decision rule (least predicted cost, ties to the grid);
- ``evaluate``  the paper's evaluation: its tables, and the report's analysis.

``core.plan`` puts them together for one scene.
"""

from .calfile import (CALIBRATION_FORMAT, DEFAULT_PATH, Calibration, CalibrationError, current_version, load,
                      load_default, load_or_default, machine_fingerprint, package_version)
from .cost import (DEFAULT_MODEL, DEFAULT_SPREAD, MODELS, Cost, KindFit, Measurement, SceneRecord, break_even, fit,
                   log2n, nlog2n)
from .load_watch import QUIET_SHARE, OthersShare, in_passes, interleaved
from .measurements import GRID_LARGE_RAYS, RAYS_PER_SCENE, SAMPLE_LADDER, calibrate, measure, time_trace, warm_up
from .truth import BreakEven, break_even_jobs, measure_break_even, measure_break_evens
from .rule import REUSES_SAMPLES, choose, over_life
