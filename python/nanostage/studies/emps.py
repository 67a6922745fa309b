"""The EMPS benchmark: loader, the logged controller law, and IDIM-LS identification.

EMPS (Electro-Mechanical Positioning System; A. Janot, M. Gautier and M. Brunot, "Data Set
and Reference Models of EMPS", 2019 Workshop on Nonlinear System Identification Benchmarks)
is a real ball-screw axis measured in closed loop at 1 kHz. This module

* reads ``DATA_EMPS.mat`` into the standard :class:`~nanostage.experiment.Experiment`
  trace (:func:`load_emps`),
* recomputes the documented dSPACE cascade controller in floating point
  (:func:`cascade_command_v`), an independent check of how the logged command was made,
* identifies the authors' rigid-body model with Coulomb and viscous friction by inverse
  dynamics and least squares (:func:`idim_ls`), and
* provides the authors' error yardstick (:func:`relative_error`) and the velocity and force
  channels of a trace (:func:`emps_velocity_force`) for closed-loop comparisons.

The data are never copied into the repository: by default the file is read from
``<repo>/../shared/data/emps/DATA_EMPS.mat``; set ``NANOSTAGE_EMPS_MAT`` to read another
copy. ``python -m nanostage.studies.emps`` prints the controller check and the identification
tables (see ``docs/emps.md``). This module needs scipy (``scipy.io``, ``scipy.signal``).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

try:
    from scipy import io as _sio
    from scipy import signal as _signal
except ImportError as exc:  # pragma: no cover - scipy is in the test extra
    raise ImportError("nanostage.studies.emps needs scipy (pip install scipy)") from exc

from ..experiment import Experiment

__all__ = [
    "EMPS_ENV_VAR",
    "PUBLISHED_ASYMMETRIC",
    "PUBLISHED_SYMMETRIC",
    "SAMPLE_PERIOD_S",
    "ControllerFit",
    "EmpsData",
    "IdimResult",
    "VelocityForce",
    "cascade_command_v",
    "controller_fit",
    "default_emps_path",
    "emps_velocity_force",
    "idim_ls",
    "load_emps",
    "main",
    "relative_error",
]

FloatArray = npt.NDArray[np.float64]

#: Environment variable that overrides the location of ``DATA_EMPS.mat``.
EMPS_ENV_VAR = "NANOSTAGE_EMPS_MAT"
#: The dSPACE sample period, s (1 kHz). The file's ``t`` carries ~3e-8 s float jitter.
SAMPLE_PERIOD_S = 1e-3
#: Largest allowed deviation of the file's ``t`` from ``k·SAMPLE_PERIOD_S``, s.
_TIME_JITTER_TOL_S = 1e-6
#: Drive saturation of the dSPACE controller output (``viradm`` in the reference model), V.
SATURATION_V = 10.0

#: The authors' IDIM-LS values, symmetric friction (M, Fv, Fc, offset).
PUBLISHED_SYMMETRIC: dict[str, float] = {
    "mass_kg": 95.1089,
    "viscous_n_s_per_m": 203.5034,
    "coulomb_n": 20.3935,
    "offset_n": -3.1648,
}
#: The authors' IDIM-LS values, asymmetric friction (M, Fv+, Fc+, Fv−, Fc−; no offset).
PUBLISHED_ASYMMETRIC: dict[str, float] = {
    "mass_kg": 95.1540,
    "viscous_pos_n_s_per_m": 166.7061,
    "coulomb_pos_n": 20.1440,
    "viscous_neg_n_s_per_m": 240.4236,
    "coulomb_neg_n": 20.6277,
}
#: The authors' IDIM relative errors ‖F − Xθ‖/‖F‖ (symmetric, asymmetric).
PUBLISHED_RELATIVE_ERROR: dict[str, float] = {"symmetric": 0.0408, "asymmetric": 0.0311}

_SYMMETRIC_NAMES = ("mass_kg", "viscous_n_s_per_m", "coulomb_n", "offset_n")
_ASYMMETRIC_NAMES = (
    "mass_kg",
    "viscous_pos_n_s_per_m",
    "coulomb_pos_n",
    "viscous_neg_n_s_per_m",
    "coulomb_neg_n",
)
_VECTOR_VARS = ("t", "qg", "qm", "vir")
_SCALAR_VARS = ("gtau", "kp", "kv")


# --------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class EmpsData:
    """One EMPS run: the trace and the constants stored beside it in the MAT file.

    Attributes
    ----------
    experiment : the trace; ``reference_m`` = ``qg``, ``position_m`` = ``qm`` (motor encoder
        expressed on the load side), ``command_v`` = ``vir`` (controller output, always set).
    drive_gain_n_per_v : ``gtau``, drive force per command volt, N/V.
    kp_per_s : ``kp``, outer position-loop gain, 1/s.
    kv_v_s_per_m : ``kv``, inner velocity-loop gain, V/(m/s).
    """

    experiment: Experiment
    drive_gain_n_per_v: float
    kp_per_s: float
    kv_v_s_per_m: float

    def __post_init__(self) -> None:
        if self.experiment.command_v is None:
            raise ValueError(f"{self.experiment.source or self.experiment.name}: no command_v")

    @property
    def command_v(self) -> FloatArray:
        """The drive command ``vir``, V."""
        assert self.experiment.command_v is not None  # checked in __post_init__
        return self.experiment.command_v

    @property
    def force_n(self) -> FloatArray:
        """Drive force ``gtau·vir``, N."""
        return self.drive_gain_n_per_v * self.command_v


def default_emps_path() -> Path:
    """Where :func:`load_emps` looks by default.

    ``$NANOSTAGE_EMPS_MAT`` if set, else ``<repo>/../shared/data/emps/DATA_EMPS.mat`` when
    this module lives in a source checkout ``<repo>`` (``<repo>/python/nanostage/emps.py``
    beside ``<repo>/pyproject.toml``) and that file exists.

    Raises
    ------
    FileNotFoundError
        Neither is there (an installed package has no default): pass the file's path.
    """
    env = os.environ.get(EMPS_ENV_VAR)
    if env:
        return Path(env)
    here = Path(__file__).resolve()
    repo = here.parents[3]
    candidate = repo.parent / "shared" / "data" / "emps" / "DATA_EMPS.mat"
    checkout = here.parents[2].name == "python" and (repo / "pyproject.toml").is_file()
    if checkout and candidate.is_file():
        return candidate
    where = (
        f"{candidate} does not exist"
        if checkout
        else "an installed package has no default (a source checkout looks in "
        "../shared/data/emps beside it)"
    )
    raise FileNotFoundError(
        f"no EMPS data file: pass the path of DATA_EMPS.mat (nanostage emps --mat PATH, "
        f"load_emps(PATH)) or set {EMPS_ENV_VAR}; {where}"
    )


#: Largest plausible position of an EMPS-like axis (a ball-screw positioning unit), m:
#: positions beyond it are taken as a unit mistake (millimetres in the metre variables).
MAX_POSITION_M = 5.0


def _vector(mat: dict[str, object], name: str, path: Path) -> FloatArray:
    try:
        arr = np.asarray(mat[name], dtype=np.float64)
    except (TypeError, ValueError):
        kind = type(mat[name]).__name__
        dtype = getattr(mat[name], "dtype", None)
        raise ValueError(
            f"{path}: variable {name!r} is not numeric ({kind}"
            f"{'' if dtype is None else f' of {dtype}'}), expected an N×1 vector of numbers"
        ) from None
    if arr.ndim != 2 or min(arr.shape) != 1:
        raise ValueError(f"{path}: variable {name!r} has shape {arr.shape}, expected N×1")
    out = arr.reshape(-1)
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{path}: variable {name!r} has non-finite values")
    return out


def _scalar(mat: dict[str, object], name: str, path: Path) -> float:
    try:
        arr = np.asarray(mat[name], dtype=np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.size != 1 or not np.isfinite(arr).all():
        shown = repr(mat[name]) if arr is None else repr(arr)
        raise ValueError(f"{path}: variable {name!r} should be one finite number, got {shown:.80}")
    return float(arr.reshape(-1)[0])


def _check_positions(qg: FloatArray, qm: FloatArray, path: Path) -> None:
    """Positions in metres: within ±:data:`MAX_POSITION_M`, and qg and qm in one unit."""
    for name, v in (("qg", qg), ("qm", qm)):
        peak = float(np.max(np.abs(v)))
        if peak > MAX_POSITION_M:
            raise ValueError(
                f"{path}: variable {name!r} reaches {peak:.6g}, beyond the ±{MAX_POSITION_M:g} m "
                "of a ball-screw positioning axis: the positions look like millimetres; "
                "store qg and qm in metres"
            )
    span_g = float(np.ptp(qg))
    span_m = float(np.ptp(qm))
    if span_g > 0.0 and span_m > 0.0 and not 0.01 <= span_m / span_g <= 100.0:
        raise ValueError(
            f"{path}: qm spans {span_m:.6g} but qg spans {span_g:.6g}: the measured and the "
            "reference position must be in the same unit (metres)"
        )


def load_emps(path: str | os.PathLike[str] | None = None) -> EmpsData:
    """Read ``DATA_EMPS.mat`` (or a file with the same variables) into :class:`EmpsData`.

    ``time_s`` is rebuilt as ``k·1e-3`` s: the file's ``t`` carries float jitter of up to
    ~3e-8 s, while the dSPACE controller runs at exactly 1 kHz. The file's ``t`` must agree
    with ``k·1e-3`` to 1 µs, otherwise this raises.

    Parameters
    ----------
    path : the MAT file; default :func:`default_emps_path`.

    Raises
    ------
    FileNotFoundError : the file does not exist (or, without ``path``, there is no default).
    IsADirectoryError : the path is a folder.
    ValueError : the file is not a readable MAT file, a variable is missing, not numeric, or
        has the wrong shape or non-finite values, there are fewer than 2 samples, or the
        positions are not plausibly metres (beyond ±5 m, or ``qg`` and ``qm`` spanning
        ranges more than a hundred times apart). The message names the file and variable.
    """
    p = Path(path) if path is not None else default_emps_path()
    if p.is_dir():
        raise IsADirectoryError(
            f"EMPS data file {p} is a folder: expected the path of DATA_EMPS.mat"
        )
    if not p.is_file():
        raise FileNotFoundError(
            f"EMPS data file not found: {p} (pass the path of DATA_EMPS.mat or set "
            f"{EMPS_ENV_VAR} to it)"
        )
    try:
        mat: dict[str, object] = _sio.loadmat(str(p))
    except Exception as exc:  # scipy raises several types for corrupt files
        raise ValueError(f"{p}: cannot read as a MAT file ({type(exc).__name__}: {exc})") from exc
    for name in _VECTOR_VARS + _SCALAR_VARS:
        if name not in mat:
            found = sorted(k for k in mat if not k.startswith("__"))
            raise ValueError(f"{p}: variable {name!r} missing (found {found})")
    t, qg, qm, vir = (_vector(mat, name, p) for name in _VECTOR_VARS)
    lengths = {name: len(v) for name, v in zip(_VECTOR_VARS, (t, qg, qm, vir), strict=True)}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"{p}: vectors differ in length: {lengths}")
    if len(t) < 2:
        raise ValueError(f"{p}: {len(t)} samples, expected at least 2")
    _check_positions(qg, qm, p)
    time_s = np.arange(len(t), dtype=np.float64) * SAMPLE_PERIOD_S
    jitter_s = float(np.max(np.abs(t - time_s))) if len(t) else 0.0
    if jitter_s > _TIME_JITTER_TOL_S:
        raise ValueError(
            f"{p}: variable 't' is not sampled at {SAMPLE_PERIOD_S:g} s "
            f"(deviates from k·dt by up to {jitter_s:.3g} s)"
        )
    experiment = Experiment(
        name=p.stem,
        source=str(p),
        time_s=time_s,
        reference_m=qg,
        position_m=qm,
        command_v=vir,
    )
    return EmpsData(
        experiment=experiment,
        drive_gain_n_per_v=_scalar(mat, "gtau", p),
        kp_per_s=_scalar(mat, "kp", p),
        kv_v_s_per_m=_scalar(mat, "kv", p),
    )


# --------------------------------------------------------------------------------------
# Controller
# --------------------------------------------------------------------------------------


def _as_1d(x: npt.ArrayLike, name: str) -> FloatArray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {arr.shape}")
    return arr


def cascade_command_v(
    reference_m: npt.ArrayLike,
    position_m: npt.ArrayLike,
    kp_per_s: float,
    kv_v_s_per_m: float,
    sample_period_s: float,
    saturation_v: float = SATURATION_V,
) -> FloatArray:
    """The documented dSPACE cascade P/P controller in floating point (plain numpy).

    ``v(k) = kp·kv·(qg(k) − qm(k)) − kv·v̂(k)``, saturated at ``±saturation_v``, with
    ``v̂(k) = (qf(k) − qf(k−1))/dt`` and ``qf(k) = 0.5·qm(k) + 0.5·qm(k−1)``, i.e.
    ``v̂(k) = (qm(k) − qm(k−2))/(2·dt)``. Before the first sample the state is
    ``qm(−1) = qm(−2) = qm(0)`` (so ``v̂(0) = 0``). There is no delay between the position
    samples and the command of the same index.
    """
    qg = _as_1d(reference_m, "reference_m")
    qm = _as_1d(position_m, "position_m")
    if qg.shape != qm.shape:
        raise ValueError(f"reference_m {qg.shape} and position_m {qm.shape} differ in shape")
    if not sample_period_s > 0.0:
        raise ValueError(f"sample_period_s must be > 0, got {sample_period_s}")
    if not saturation_v > 0.0:
        raise ValueError(f"saturation_v must be > 0, got {saturation_v}")
    if qm.size == 0:
        return np.empty(0, dtype=np.float64)
    qm_hist = np.concatenate((np.full(2, qm[0]), qm))  # qm(−2), qm(−1), qm(0), ...
    qf = 0.5 * qm_hist[1:] + 0.5 * qm_hist[:-1]  # qf(−1), qf(0), ...
    velocity_m_per_s = np.diff(qf) / sample_period_s  # v̂(0), v̂(1), ...
    v = kp_per_s * kv_v_s_per_m * (qg - qm) - kv_v_s_per_m * velocity_m_per_s
    return np.clip(v, -saturation_v, saturation_v)


class ControllerFit(NamedTuple):
    """How well :func:`cascade_command_v` reproduces the logged command."""

    rms_v: float
    max_abs_v: float
    n_compared: int


def controller_fit(
    data: EmpsData, *, start_sample: int = 2, shift_samples: int = 0
) -> ControllerFit:
    """Compare :func:`cascade_command_v` with the logged ``vir`` from ``start_sample`` on.

    The first two samples are left out by default: the log starts with the axis already
    under control (``qm(0) ≠ 0``), so the controller's velocity filter has a history the
    log does not contain and the assumed start state ``qm(−1) = qm(−2) = qm(0)`` is wrong
    there. ``shift_samples = s`` compares the law at ``k`` with ``vir(k + s)`` (a deliberate
    misalignment, for tests).
    """
    exp = data.experiment
    law = cascade_command_v(
        exp.reference_m,
        exp.position_m,
        data.kp_per_s,
        data.kv_v_s_per_m,
        SAMPLE_PERIOD_S,
    )
    logged = data.command_v
    n = len(law)
    k = np.arange(start_sample, n)
    k = k[(k + shift_samples >= 0) & (k + shift_samples < n)]
    if k.size == 0:
        raise ValueError("no samples to compare")
    err = law[k] - logged[k + shift_samples]
    return ControllerFit(
        rms_v=float(np.sqrt(np.mean(err**2))),
        max_abs_v=float(np.max(np.abs(err))),
        n_compared=int(k.size),
    )


# --------------------------------------------------------------------------------------
# Signals
# --------------------------------------------------------------------------------------


def _lowpass_zero_phase(
    x: FloatArray, cutoff_hz: float, filter_order: int, sample_rate_hz: float
) -> FloatArray:
    """Zero-phase Butterworth low-pass (``butter`` in sos form + ``sosfiltfilt``)."""
    if not 0.0 < cutoff_hz < 0.5 * sample_rate_hz:
        raise ValueError(
            f"cutoff_hz must be in (0, {0.5 * sample_rate_hz:g}) Hz (Nyquist), got {cutoff_hz}"
        )
    if filter_order < 1:
        raise ValueError(f"filter_order must be >= 1, got {filter_order}")
    sos = _signal.butter(filter_order, cutoff_hz, btype="low", fs=sample_rate_hz, output="sos")
    return np.asarray(_signal.sosfiltfilt(sos, x), dtype=np.float64)


def _sample_period(experiment: Experiment) -> float:
    dt = experiment.sample_period_s
    if not dt > 0.0:
        raise ValueError(f"{experiment.source or experiment.name}: need at least two samples")
    return dt


class VelocityForce(NamedTuple):
    """Velocity and drive force of a trace."""

    velocity_m_per_s: FloatArray
    force_n: FloatArray


def emps_velocity_force(
    experiment: Experiment,
    drive_gain_n_per_v: float,
    *,
    cutoff_hz: float = 100.0,
    filter_order: int = 4,
) -> VelocityForce:
    """Velocity and force of a (measured or simulated) trace, the way IDIM computes them.

    Velocity: central differences (``numpy.gradient``) of ``position_m`` after a zero-phase
    Butterworth low-pass (``cutoff_hz``, ``filter_order``). Force: ``drive_gain·command_v``,
    unfiltered. Use both on the measurement and on a closed-loop simulation and compare with
    :func:`relative_error`.
    """
    if experiment.command_v is None:
        raise ValueError(f"{experiment.source or experiment.name}: no command_v for the force")
    dt = _sample_period(experiment)
    qf = _lowpass_zero_phase(experiment.position_m, cutoff_hz, filter_order, 1.0 / dt)
    return VelocityForce(
        velocity_m_per_s=np.gradient(qf, dt),
        force_n=drive_gain_n_per_v * np.asarray(experiment.command_v, dtype=np.float64),
    )


def relative_error(measured: npt.ArrayLike, simulated: npt.ArrayLike) -> float:
    """The authors' yardstick ``‖measured − simulated‖ / ‖measured‖`` (2-norms)."""
    m = np.asarray(measured, dtype=np.float64)
    s = np.asarray(simulated, dtype=np.float64)
    if m.shape != s.shape:
        raise ValueError(f"measured {m.shape} and simulated {s.shape} differ in shape")
    norm = float(np.linalg.norm(m))
    if norm == 0.0:
        raise ValueError("measured is all zeros: relative error undefined")
    return float(np.linalg.norm(m - s)) / norm


# --------------------------------------------------------------------------------------
# IDIM-LS
# --------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class IdimResult:
    """Result of :func:`idim_ls`.

    Attributes
    ----------
    names : parameter names (SI units in the names), in the order of ``values``.
    values : least-squares estimates.
    std_errors : standard deviations ``sqrt(diag(σ̂²·(XᵀX)⁻¹))``,
        ``σ̂² = ‖F − Xθ‖²/(n − p)``.
    relative_std_errors : ``std_errors / |values|``.
    relative_error : ``‖F − Xθ‖ / ‖F‖`` over the samples used.
    n_samples : rows of the regression (after trimming, speed threshold and decimation).
    asymmetric : which friction model.
    """

    names: tuple[str, ...]
    values: FloatArray
    std_errors: FloatArray
    relative_std_errors: FloatArray
    relative_error: float
    n_samples: int
    asymmetric: bool

    def as_dict(self) -> dict[str, float]:
        """``{name: value}``."""
        return {n: float(v) for n, v in zip(self.names, self.values, strict=True)}

    def __getitem__(self, name: str) -> float:
        """The value of parameter ``name``."""
        return float(self.values[self.names.index(name)])

    def std_error(self, name: str) -> float:
        """The standard error of parameter ``name``."""
        return float(self.std_errors[self.names.index(name)])


def idim_ls(
    data: EmpsData,
    *,
    cutoff_hz: float = 100.0,
    filter_order: int = 4,
    asymmetric: bool = False,
    decimate: int = 1,
    min_speed_m_per_s: float = 1e-3,
    edge_s: float = 0.05,
) -> IdimResult:
    """Inverse-dynamics identification by least squares (IDIM-LS), as the EMPS authors do.

    1. Filter ``qm`` and the force ``gtau·vir`` with the same zero-phase Butterworth low-pass
       (``cutoff_hz``, ``filter_order``; ``sosfiltfilt``) — parallel filtering, so the
       regressors and the force see the same filter.
    2. Velocity ``q̇`` = central differences of the filtered position, acceleration ``q̈`` =
       central differences of that velocity (``numpy.gradient`` twice).
    3. Drop ``edge_s`` at both ends (filter start-up transients) and keep every
       ``decimate``-th sample; this requires ``cutoff_hz <= fs/(2·decimate)`` so the filter
       already band-limits the rows to the new Nyquist frequency (no second anti-alias
       filter is applied). Then drop every sample with ``|q̇| < min_speed_m_per_s``: there
       the sign regressor is undefined (static friction, velocity reversals smeared by the
       filter). A zero threshold still drops samples with exactly zero velocity.
    4. Solve ``X·θ ≈ F`` in the least-squares sense with

       * symmetric: ``M·q̈ + Fv·q̇ + Fc·sign(q̇) + offset = F``,
         ``θ = (mass_kg, viscous_n_s_per_m, coulomb_n, offset_n)``;
       * asymmetric: ``M·q̈ + Fv+·q̇·[q̇>0] + Fc+·[q̇>0] + Fv−·q̇·[q̇<0] − Fc−·[q̇<0] = F``,
         ``θ = (mass_kg, viscous_pos_n_s_per_m, coulomb_pos_n, viscous_neg_n_s_per_m,
         coulomb_neg_n)``.

    There is no offset column in the asymmetric model: with every used sample moving,
    ``[q̇>0] + [q̇<0] = 1``, so an offset column equals the sum of the two Coulomb columns and
    XᵀX is singular. The offset is absorbed into the Coulomb terms:
    ``Fc+ = Fc+_true + offset`` and ``Fc− = Fc−_true − offset``. That is also how the
    authors' published asymmetric values behave (their Fc± match this fit, not one with the
    offset removed first).
    """
    exp = data.experiment
    dt = _sample_period(exp)
    fs = 1.0 / dt
    if decimate < 1:
        raise ValueError(f"decimate must be >= 1, got {decimate}")
    if decimate > 1 and cutoff_hz > 0.5 * fs / decimate * (1.0 + 1e-9):
        raise ValueError(
            f"cutoff_hz {cutoff_hz:g} Hz must not exceed the decimated Nyquist frequency "
            f"{0.5 * fs / decimate:g} Hz (decimate={decimate})"
        )
    if min_speed_m_per_s < 0.0 or edge_s < 0.0:
        raise ValueError("min_speed_m_per_s and edge_s must be >= 0")
    qf = _lowpass_zero_phase(exp.position_m, cutoff_hz, filter_order, fs)
    force = _lowpass_zero_phase(data.force_n, cutoff_hz, filter_order, fs)
    vel = np.gradient(qf, dt)
    acc = np.gradient(vel, dt)

    n = exp.n_samples
    edge = round(edge_s * fs)
    rows = np.arange(edge, n - edge, decimate)
    rows = rows[np.abs(vel[rows]) >= max(min_speed_m_per_s, np.finfo(float).tiny)]
    v, a, f = vel[rows], acc[rows], force[rows]
    names: tuple[str, ...]
    if asymmetric:
        pos = (v > 0.0).astype(np.float64)
        neg = (v < 0.0).astype(np.float64)
        x = np.column_stack((a, v * pos, pos, v * neg, -neg))
        names = _ASYMMETRIC_NAMES
    else:
        x = np.column_stack((a, v, np.sign(v), np.ones_like(v)))
        names = _SYMMETRIC_NAMES
    n_rows, n_par = x.shape
    if n_rows <= n_par:
        raise ValueError(f"only {n_rows} usable samples for {n_par} parameters")
    q, r = np.linalg.qr(x)
    if np.min(np.abs(np.diag(r))) <= 1e-12 * np.max(np.abs(np.diag(r))):
        raise ValueError(
            "regressor matrix is rank deficient (e.g. no motion in one direction for the "
            "asymmetric model)"
        )
    theta = np.linalg.solve(r, q.T @ f)
    residual = f - x @ theta
    sigma2 = float(residual @ residual) / (n_rows - n_par)
    r_inv = np.linalg.inv(r)
    cov = sigma2 * (r_inv @ r_inv.T)
    std = np.sqrt(np.diag(cov))
    return IdimResult(
        names=names,
        values=np.asarray(theta, dtype=np.float64),
        std_errors=np.asarray(std, dtype=np.float64),
        relative_std_errors=np.asarray(std / np.abs(theta), dtype=np.float64),
        relative_error=float(np.linalg.norm(residual) / np.linalg.norm(f)),
        n_samples=int(n_rows),
        asymmetric=asymmetric,
    )


# --------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------


def _table(result: IdimResult, published: dict[str, float], published_rel_err: float) -> str:
    lines = [
        f"{'parameter':<24}{'value':>11}{'± std':>9}{'rel std':>9}{'published':>11}{'diff':>8}",
    ]
    for name, val, std, rstd in zip(
        result.names, result.values, result.std_errors, result.relative_std_errors, strict=True
    ):
        pub = published[name]
        lines.append(
            f"{name:<24}{val:>11.3f}{std:>9.3f}{100 * rstd:>8.2f}%{pub:>11.3f}"
            f"{100 * (val - pub) / abs(pub):>+7.2f}%"
        )
    lines.append(
        f"{'relative error':<24}{100 * result.relative_error:>10.2f}%{'':>18}"
        f"{100 * published_rel_err:>10.2f}%"
    )
    lines.append(f"({result.n_samples} samples)")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m nanostage.studies.emps [PATH]``: print the controller check and IDIM-LS
    tables."""
    parser = argparse.ArgumentParser(
        prog="python -m nanostage.studies.emps", description=main.__doc__
    )
    parser.add_argument("path", nargs="?", default=None, help="DATA_EMPS.mat (default: shared)")
    parser.add_argument(
        "--decimate",
        type=int,
        nargs="+",
        default=[1, 5],
        help="decimation factors to report (default: 1 5)",
    )
    args = parser.parse_args(argv)
    try:
        data = load_emps(args.path)
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    exp = data.experiment
    print(f"{exp.source}: {exp.n_samples} samples, {exp.time_s[-1]:.3f} s")
    print(
        f"gtau = {data.drive_gain_n_per_v:.4f} N/V, kp = {data.kp_per_s:.2f} 1/s, "
        f"kv = {data.kv_v_s_per_m:.2f} V·s/m"
    )
    fit = controller_fit(data)
    print(
        f"\ncontroller law vs logged vir (k >= 2, {fit.n_compared} samples): "
        f"rms {fit.rms_v:.4f} V, max {fit.max_abs_v:.4f} V"
    )
    for s in (-1, 1):
        shifted = controller_fit(data, shift_samples=s)
        print(f"  with a {s:+d} sample shift: rms {shifted.rms_v:.4f} V")
    for dec in args.decimate:
        for asym in (False, True):
            try:
                res = idim_ls(data, asymmetric=asym, decimate=dec)
            except ValueError as exc:
                print(f"error: {exc}", file=sys.stderr)
                return 1
            kind = "asymmetric" if asym else "symmetric"
            pub = PUBLISHED_ASYMMETRIC if asym else PUBLISHED_SYMMETRIC
            print(f"\nIDIM-LS, {kind} friction, 100 Hz order-4 Butterworth, decimate {dec}")
            print(_table(res, pub, PUBLISHED_RELATIVE_ERROR[kind]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
