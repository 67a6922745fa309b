"""nanostage: an ultra-high-precision positioning axis with friction, a bit-exact emulation
of its FPGA PID, ISO 230-2 evaluation and Monte Carlo campaigns, sim-to-real gap diagnosis
(``nanostage.diagnosis``) and off-line PID tuning (``nanostage.tune``).

Units are SI everywhere and appear in the names (``mass_kg``, ``lead_m``).
"""

from . import presets
from ._core import ConfigError, SimulationError, __version__
from .analysis import StepMetrics, step_metrics
from .config import (
    BallScrew,
    DahlFriction,
    Encoder,
    FpgaPid,
    Fxp,
    Gearhead,
    IntegratorOptions,
    Motor,
    OutputStage,
    Plant,
    StribeckFriction,
    System,
    Table,
)
from .model_file import ModelFileError, load_model, load_model_file, save_model
from .simulate import (
    OpenLoopTrace,
    Trace,
    simulate,
    simulate_plant,
    simulate_step,
    step_reference,
)

__all__ = [
    "BallScrew",
    "ConfigError",
    "DahlFriction",
    "Encoder",
    "FpgaPid",
    "Fxp",
    "Gearhead",
    "IntegratorOptions",
    "ModelFileError",
    "Motor",
    "OpenLoopTrace",
    "OutputStage",
    "Plant",
    "SimulationError",
    "StepMetrics",
    "StribeckFriction",
    "System",
    "Table",
    "Trace",
    "__version__",
    "load_model",
    "load_model_file",
    "presets",
    "save_model",
    "simulate",
    "simulate_plant",
    "simulate_step",
    "step_metrics",
    "step_reference",
]
