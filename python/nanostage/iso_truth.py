"""Synthetic measured ISO 230-2 tests with one hidden effect, written without
nanostage's measurement chain, effects or simulator (the blind check of
``nanostage iso-diagnose``; docs/iso-diagnosis.md).

Everything here is its own formula from the physics, so that the diagnosis is not checked
against its own equations: a test on a 50 mm axis (11 targets with random offsets, 5 runs,
both directions, the ISO 230-2 standard cycle with trapezoidal moves, a dwell before each
reading), a loop that stops within about one encoder count of each target (a uniform stop
error whose width is the count times a nominal mismatch factor, plus a stick-slip-like
bias per target and direction), the interferometer's noise, and one hidden effect (or
none) added to the interferometer's reading at the functional point:

* ``scale_error``: the scale is longer than nominal, the reading runs off linearly from the
  scale's fixing point;
* ``abbe``: the carriage pitches along the travel (a linear and a bowed part) and tilts
  with the direction of the drive force, read through an Abbe offset, with a random
  angular repeatability per approach;
* ``thermal_drift``: the structure between the scale and the interferometer and the scale
  itself warm up along an exponential approach to a final rise;
* ``refractive_index_drift``: the air warms at a constant rate, the wavelength's
  compensation is not updated, the error grows with the beam's length (dead path
  included) and time;
* ``settling_residual``: the functional point creeps on after each move, a fraction of the
  move decaying with a time constant, and rings at a lightly damped mode read at a random
  phase;
* ``interferometer_noise``: air turbulence far above the nominal noise;
* ``interpolation_error``: the encoder's sub-divisional error, periodic in its signal
  period: the loop stops where the erroneous reading equals the target;
* ``backlash`` (in the loop): a gearhead dead band between the motor and the table. The
  encoder is on the table, so the loop closes on the table and recovers the lost motion of
  the approach, but not the coast at the stop: as the motor side decelerates, the table
  runs on inside the dead band against its friction by a fraction of the width, and
  pulling it back means reversing the motor across the whole dead band, which the loop's
  integral does not finish within the dwell. The table stays past the target in the
  approach's direction by that coast (the encoder sees it);
  A backlash wider than about 14 µm (half the cases) makes the loop hunt: the table
  sticks at one end of a swing of the order of the width while the motor crosses the dead
  band, then slips to the other end; each reading catches the cycle at a random phase;
* ``friction_scatter`` (in the loop): the friction varies from approach to approach, so the
  loop stops anywhere within its dead zone of about ±1 count (uniform), plus a stick-slip
  scatter of the last micro-slips (Gaussian); the encoder sees it.

Only the standard library and numpy are imported (tests/test_iso_diagnosis.py checks it).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any, Final

import numpy as np

__all__ = ["EFFECTS", "IN_LOOP", "TruthCase", "check_scale", "draw_case", "write_case"]

#: The hidden effects (and "none").
EFFECTS: Final[tuple[str, ...]] = (
    "none",
    "scale_error",
    "abbe",
    "thermal_drift",
    "refractive_index_drift",
    "settling_residual",
    "interferometer_noise",
    "interpolation_error",
    "backlash",
    "friction_scatter",
)

#: The hidden effects that act in the loop (the encoder sees them).
IN_LOOP: Final[tuple[str, ...]] = ("backlash", "friction_scatter")

TRAVEL_M: Final[float] = 0.05
N_TARGETS: Final[int] = 11
RUNS: Final[int] = 5
OVERRUN_M: Final[float] = 1e-3
DWELL_S: Final[float] = 0.5
VELOCITY_M_PER_S: Final[float] = 5e-3
ACCELERATION_M_PER_S2: Final[float] = 0.05
#: Rest at the start of the travel between two runs [s] (the operator's pace).
PAUSE_S: Final[float] = 60.0
#: The encoder's count [m] (the seed axis's 100 nm resolution).
COUNT_M: Final[float] = 1e-7
#: The encoder's signal period [m].
SIGNAL_PERIOD_M: Final[float] = 20e-6
#: The share of the backlash cases wide enough for the loop to hunt.
HUNTING_FRACTION: Final[float] = 0.5


class TruthCase:
    """One synthetic test: readings in the order of the test, what is hidden, and the
    hidden effect's error at each reading [m] (what it adds to the reading; for a friction
    scatter, its stop less the nominal stop)."""

    def __init__(
        self,
        effect: str,
        parameters: dict[str, float],
        rows: list[dict[str, Any]],
        hidden_error_m: np.ndarray,
    ):
        self.effect = effect
        self.parameters = parameters
        self.rows = rows
        self.hidden_error_m = hidden_error_m

    @property
    def hidden_size_counts(self) -> float:
        """The hidden error's RMS about its mean, in encoder counts (0 without an effect):
        the size the detection limit is read against."""
        return float(np.std(self.hidden_error_m)) / COUNT_M if self.hidden_error_m.size else 0.0


def _move_time_s(distance_m: float) -> float:
    """Duration of a trapezoidal move (rest to rest)."""
    d = abs(distance_m)
    v, a = VELOCITY_M_PER_S, ACCELERATION_M_PER_S2
    if d >= v * v / a:
        return d / v + v / a
    return 2.0 * math.sqrt(d / a)


def _schedule(rng: np.random.Generator) -> list[dict[str, float]]:
    """The standard cycle: per run, up through the targets, past the last, down through
    them, past the first. Each reading: target, direction, run, time, move, dwell."""
    spacing = TRAVEL_M / (N_TARGETS - 1)
    targets = []
    for i in range(N_TARGETS):
        lo = 0.0 if i == 0 else -0.25 * spacing
        hi = 0.0 if i == N_TARGETS - 1 else 0.25 * spacing
        targets.append(i * spacing + float(rng.uniform(lo, hi)))
    pos = targets[0] - OVERRUN_M
    t = DWELL_S
    out: list[dict[str, float]] = []

    def go(to: float) -> float:
        nonlocal pos, t
        step = to - pos
        t += _move_time_s(step) + DWELL_S
        pos = to
        return step

    for run in range(1, RUNS + 1):
        for p in targets:
            step = go(p)
            out.append({"target": p, "direction": 1, "run": run, "time": t, "move": step})
        go(targets[-1] + OVERRUN_M)
        for p in reversed(targets):
            step = go(p)
            out.append({"target": p, "direction": -1, "run": run, "time": t, "move": step})
        go(targets[0] - OVERRUN_M)
        t += PAUSE_S
    return out


def _magnitude(rng: np.random.Generator, lo: float, hi: float) -> float:
    """A magnitude uniform in log between lo and hi, with a random sign."""
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))) * rng.choice([-1.0, 1.0]))


def _hidden(
    effect: str, rng: np.random.Generator, sched: list[dict[str, float]]
) -> tuple[dict[str, float], np.ndarray]:
    """The hidden effect's parameters and its error at each reading [m]."""
    x = np.array([r["target"] for r in sched])
    d = np.array([r["direction"] for r in sched], dtype=float)
    t = np.array([r["time"] for r in sched])
    s = np.array([r["move"] for r in sched])
    n = x.shape[0]
    if effect == "none":
        return {}, np.zeros(n)
    if effect == "scale_error":
        eps = _magnitude(rng, 5e-6, 20e-6)
        fix = float(rng.uniform(-0.03, 0.0))
        return {"strain": eps, "fixing_point_m": fix}, eps * (x - fix)
    if effect == "abbe":
        h = float(rng.uniform(0.01, 0.03))
        pitch_rate = _magnitude(rng, 4e-4, 1.5e-3)  # rad per metre of travel
        bow = float(rng.uniform(-1.0, 1.0)) * 0.3  # rad/m² about mid-travel
        tilt = _magnitude(rng, 4e-6, 12e-6)  # ↑ minus ↓ [rad]
        wobble = float(rng.uniform(0.2e-6, 1.0e-6))
        u = x - TRAVEL_M / 2
        angle = pitch_rate * u + bow * u * u + d * tilt / 2 + wobble * rng.standard_normal(n)
        return (
            {
                "offset_m": h,
                "pitch_rad_per_m": pitch_rate,
                "bow_rad_per_m2": bow,
                "tilt_rad": tilt,
                "wobble_rad": wobble,
            },
            h * np.tan(angle),
        )
    if effect == "thermal_drift":
        rise = float(rng.uniform(1.0, 3.0)) * float(rng.choice([-1.0, 1.0]))
        tau = float(math.exp(rng.uniform(math.log(200.0), math.log(1500.0))))
        struct = float(rng.uniform(2e-6, 6e-6))  # m per kelvin of the structural loop
        glass = 8e-6
        fix = float(rng.uniform(-0.03, 0.0))
        warm = rise * (1.0 - np.exp(-t / tau))
        return (
            {"rise_k": rise, "tau_s": tau, "structure_m_per_k": struct, "fixing_point_m": fix},
            (struct + glass * (x - fix)) * warm,
        )
    if effect == "refractive_index_drift":
        # Air warming by K kelvin per hour: the index falls ~0.93e-6 per kelvin.
        k_per_h = float(rng.uniform(4.0, 10.0)) * float(rng.choice([-1.0, 1.0]))
        rate = -0.93e-6 * k_per_h / 3600.0
        dead = float(rng.uniform(0.3, 0.6))
        return (
            {"air_k_per_h": k_per_h, "dead_path_m": dead},
            (dead + x - x[0]) * rate * t,
        )
    if effect == "settling_residual":
        frac = float(rng.uniform(2e-3, 8e-3))
        tau = float(rng.uniform(0.1, 0.3))
        ring = float(rng.uniform(0.05e-6, 0.2e-6))
        phase = rng.uniform(-math.pi, math.pi, n)
        return (
            {"creep_fraction": frac, "creep_tau_s": tau, "ring_m": ring},
            -frac * s * math.exp(-DWELL_S / tau) + ring * np.cos(phase),
        )
    if effect == "interferometer_noise":
        sigma = float(rng.uniform(0.1e-6, 0.4e-6))
        return {"noise_m": sigma}, sigma * np.asarray(rng.standard_normal(n))
    if effect == "interpolation_error":
        amp = float(rng.uniform(0.1e-6, 0.3e-6))
        phase = float(rng.uniform(-math.pi, math.pi))
        # The loop stops where x + A·sin(2πx/λ + φ) reads the target: x ≈ P − A·sin(...).
        return (
            {"amplitude_m": amp, "phase_rad": phase},
            -amp * np.sin(2 * math.pi * x / SIGNAL_PERIOD_M + phase),
        )
    if effect == "backlash":
        if rng.uniform() < HUNTING_FRACTION:
            return _hunting_backlash(rng, d)
        width = float(rng.uniform(10e-6, 13e-6))
        coast = float(rng.uniform(0.012, 0.0135))  # of the width, at the stop
        jitter = float(rng.uniform(0.05, 0.15)) * COUNT_M
        return (
            {"width_m": width, "coast_fraction": coast, "jitter_m": jitter, "hunting": 0.0},
            d * coast * width + jitter * rng.uniform(-1.0, 1.0, n),
        )
    if effect == "friction_scatter":
        dead = float(rng.uniform(0.8, 1.2))  # ± counts
        slip = float(rng.uniform(60e-9, 150e-9))
        return (
            {"dead_zone_counts": dead, "stick_slip_m": slip},
            COUNT_M * dead * rng.uniform(-1.0, 1.0, n) + slip * np.asarray(rng.standard_normal(n)),
        )
    raise ValueError(f"effect = {effect!r} is invalid: expected one of {', '.join(EFFECTS)}")


def _hunting_backlash(
    rng: np.random.Generator, d: np.ndarray
) -> tuple[dict[str, float], np.ndarray]:
    """A backlash wide enough for the loop to hunt: the table sticks at one end of a swing
    while the motor crosses the dead band (the integral winds up), then slips across to the
    other end, and so on; the swing's centre lies past the target in the approach's
    direction. The cycle's period has nothing to do with the dwell, so each reading catches
    it at a random phase: at one end (the stuck part of the cycle), else anywhere between."""
    n = d.shape[0]
    width = float(rng.uniform(14e-6, 30e-6))
    swing = float(rng.uniform(0.5, 1.0))  # half the swing, of the width
    centre = float(rng.uniform(0.0, 0.4))  # the swing's centre past the target, of the width
    stuck = float(rng.uniform(0.6, 0.9))  # fraction of the cycle at an end
    at_end = rng.uniform(size=n) < stuck
    side = rng.choice([-1.0, 1.0], size=n)
    phase = np.where(at_end, side, rng.uniform(-1.0, 1.0, n))
    return (
        {
            "width_m": width,
            "swing_fraction": swing,
            "centre_fraction": centre,
            "stuck_fraction": stuck,
            "hunting": 1.0,
        },
        d * centre * width + swing * width * phase,
    )


def check_scale(scale: object) -> float:
    """``scale`` as a float, or a ``ValueError`` naming it and its valid range (0, 1]."""
    if isinstance(scale, bool) or not (isinstance(scale, int | float) and 0.0 < scale <= 1.0):
        raise ValueError(f"scale = {scale!r} is invalid: expected a number in (0, 1]")
    return float(scale)


def draw_case(effect: str, seed: int, *, scale: float = 1.0) -> TruthCase:
    """A synthetic test with ``effect`` hidden, drawn from ``seed``. ``scale`` (in (0, 1])
    multiplies the hidden effect's error at every reading (the draws stay those of
    ``scale = 1``): the detection limit's study. A friction scatter's stop becomes
    ``(1 − scale)`` times the nominal stop plus ``scale`` times its own."""
    scale = check_scale(scale)
    rng = np.random.default_rng([int(seed), 0x7AB])
    sched = _schedule(rng)
    params, err = _hidden(effect, rng, sched)
    err = scale * err
    n = len(sched)
    mismatch = float(rng.uniform(0.6, 1.4))
    stop = COUNT_M * mismatch * rng.uniform(-0.5, 0.5, n)
    # A stick-slip-like bias per target and direction, within a count.
    bias = {}
    for r in sched:
        key = (round(r["target"], 9), r["direction"])
        if key not in bias:
            bias[key] = float(rng.uniform(-0.3, 0.3)) * COUNT_M
    noise_m = float(rng.uniform(2e-9, 10e-9))
    # What the effect adds to each reading; a friction scatter's stop replaces (a share of)
    # the nominal stop.
    hidden_m = err - scale * stop if effect == "friction_scatter" else err
    rows = []
    for k, r in enumerate(sched):
        loop = stop[k] + bias[(round(r["target"], 9), r["direction"])]
        if effect in IN_LOOP:
            # Where the loop stops (the encoder on the table sees it); friction scatter's
            # stop within the dead zone takes the place of the nominal stop.
            if effect == "friction_scatter":
                loop -= scale * stop[k]
            loop += err[k]
            dev = loop
        else:
            dev = loop + err[k]
        dev += noise_m * float(rng.standard_normal())
        rows.append(
            {
                "target_m": r["target"],
                "direction": "+" if r["direction"] > 0 else "-",
                "run": int(r["run"]),
                "actual_m": r["target"] + dev,
                "time_s": r["time"],
                # The count the loop stopped at (an interpolation error moves the table,
                # not the reading the loop servoes).
                "encoder_m": COUNT_M * round((r["target"] + loop) / COUNT_M),
            }
        )
    params = dict(params, loop_mismatch=mismatch, reading_noise_m=noise_m)
    if scale != 1.0:
        params["magnitude_scale"] = scale
    return TruthCase(effect, params, rows, hidden_m)


def write_case(case: TruthCase, path: str | Path, *, encoder: bool = False) -> Path:
    """The case's readings as a measurement CSV (target_m, direction, run, actual_m,
    time_s, and with ``encoder`` the encoder's reading encoder_m)."""
    p = Path(path)
    with p.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["target_m", "direction", "run", "actual_m", "time_s"] + ["encoder_m"] * encoder)
        for r in case.rows:
            w.writerow(
                [
                    f"{r['target_m']:.12g}",
                    r["direction"],
                    r["run"],
                    f"{r['actual_m']:.12g}",
                    f"{r['time_s']:.6f}",
                ]
                + [f"{r['encoder_m']:.12g}"] * encoder
            )
    return p
