"""Typed stubs of the Rust extension (checked by mypy.stubtest in CI)."""

from typing import Any, final

import numpy as np
import numpy.typing as npt

__all__ = [
    "CampaignControl",
    "ConfigError",
    "ConfigTypeError",
    "SimulationError",
    "StopFlag",
    "__version__",
    "campaign_run",
    "cascade_run",
    "friction_response",
    "fxp_requantize",
    "pid_run",
    "simulate_open_loop",
    "simulate_system",
    "simulate_system_batch",
    "simulate_system_open_loop",
    "validate_controller",
    "validate_integrator",
    "validate_plant",
    "validate_system",
]

__version__: str

class ConfigError(ValueError):
    field: str
    value: str
    expected: str

class ConfigTypeError(ConfigError, TypeError): ...

class SimulationError(RuntimeError):
    t_s: float
    state: list[float]

@final
class StopFlag:
    """A stop request for the runs it is passed to (``stop=``)."""

    def __init__(self) -> None: ...
    def request_stop(self) -> None: ...
    @property
    def stop_requested(self) -> bool: ...

@final
class CampaignControl:
    """Stop request and progress counter of one campaign (``control=``)."""

    def __init__(self) -> None: ...
    def request_stop(self) -> None: ...
    @property
    def stop_requested(self) -> bool: ...
    @property
    def progress(self) -> int: ...

def simulate_system(
    system: Any,
    reference_m: npt.NDArray[np.float64],
    force_disturbance_n: npt.NDArray[np.float64] | None = None,
    command_disturbance_v: npt.NDArray[np.float64] | None = None,
    seed: int = 0,
    initial_position_m: float = 0.0,
    *,
    stop: StopFlag | None = None,
) -> dict[str, Any]: ...
def simulate_system_batch(
    systems: list[Any],
    references_m: list[npt.NDArray[np.float64]],
    force_disturbances_n: list[npt.NDArray[np.float64] | None],
    command_disturbances_v: list[npt.NDArray[np.float64] | None],
    seeds: list[int],
    initial_positions_m: list[float],
    threads: int = 0,
    *,
    stop: StopFlag | None = None,
) -> list[dict[str, Any]]: ...
def simulate_open_loop(
    plant: Any,
    integrator: Any,
    voltage_v: npt.NDArray[np.float64],
    sample_period_s: float,
    *,
    stop: StopFlag | None = None,
) -> dict[str, Any]: ...
def pid_run(
    controller: Any,
    reference_counts: npt.NDArray[np.int64],
    measured_counts: npt.NDArray[np.int64],
) -> dict[str, Any]: ...
def cascade_run(
    controller: Any, reference_m: npt.NDArray[np.float64], position_m: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]: ...
def fxp_requantize(
    raw: npt.NDArray[np.int64], frac_in: int, fmt: Any
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.bool_]]: ...
def validate_plant(plant: Any) -> None: ...
def validate_controller(controller: Any) -> None: ...
def validate_integrator(integrator: Any) -> None: ...
def validate_system(system: Any) -> None: ...
def simulate_system_open_loop(
    system: Any,
    voltage_v: npt.NDArray[np.float64],
    sample_period_s: float,
    force_n: npt.NDArray[np.float64] | None = None,
    *,
    stop: StopFlag | None = None,
) -> dict[str, Any]: ...
def friction_response(
    friction: Any,
    time_s: npt.NDArray[np.float64],
    position_m: npt.NDArray[np.float64],
    velocity_m_per_s: npt.NDArray[np.float64],
    integrator: Any,
    terms: list[tuple[float, float, float]] = ...,
    *,
    stop: StopFlag | None = None,
) -> npt.NDArray[np.float64]: ...
def campaign_run(
    system: Any,
    reference_m: npt.NDArray[np.float64],
    measure_index: npt.NDArray[np.int64],
    trial_start: int,
    trial_stop: int,
    seed: int,
    threads: int,
    *,
    control: CampaignControl | None = None,
) -> dict[str, Any]: ...
