"""The paper's repeated-step ISO 230-2 figures by Monte Carlo: calibrate one stochastic
friction spread on the 100 µm result, predict the 1 mm result (``nanostage reproduce
--campaigns``).

The paper (docs/SEED.md) measured repeated 100 µm and 1 mm steps from one start position
with an interferometer and reports "unidirectional positioning accuracy and repeatability"
of 3.19 µm (100 µm) and 1.83 µm (1 mm), without saying whether the figure is A↑ or R↑.

Method:

* Cycle: :func:`nanostage.cycles.step_cycle` with ``repeats`` steps (5, as ISO 230-2's
  standard cycle has 5 runs), ``dwell_s`` at the target before the reading and ``return_s``
  at the start; the paper gives none of these.
* System: :func:`nanostage.presets.seed` with the Table 1 gains of each step size (or a
  given ``model``, e.g. from :func:`nanostage.load_model`, with the Table 1 gains of each
  step size in place of its PID gains: :func:`nanostage.presets.table1_system`, or with
  ``gains="model"`` its own gains at both step sizes), plus
  :class:`~nanostage.effects.StochasticFriction` ``(level_spread=s)`` (one setting: a per-
  trial factor on every friction level, log-normal with mean 1; no within-trial
  fluctuation); with ``CampaignSettings.backlash_width_m`` also the gearhead backlash (a
  check of that explanation, docs/campaigns.md).
* A trial is one whole test (``repeats`` steps), read with the true table position (the
  paper's interferometer). The simulated figure is the mean over ``n_trials`` trials of the
  trial's A↑ (or R↑), since the paper's number is one such test.
* Calibration: the spread ``s`` in [0, 0.5] (the core's range) is scanned on a grid with
  the same trial seeds at every ``s`` (common random numbers: trial ``i`` draws the same
  standard normal at every ``s``), and, where the scan brackets the paper's 3.19 µm, refined
  with Brent's method. Done separately on A↑ and on R↑. The 1 mm figure is then predicted at
  the calibrated ``s`` with no retuning. If no ``s`` reaches 3.19 µm, the reachable range is
  reported and the prediction is made at the ``s`` that comes closest, flagged as such.
* A second reading, "pooled", takes every trial's steps as further runs of one test (as if
  the friction level changed from step to step); it is reported alongside.

Note on A↑ vs R↑: a step test has a single target, and for one target ISO 230-2 gives
A↑ = (x̄ + 2s) − (x̄ − 2s) = 4s = R↑ exactly. The two readings of the paper's number cannot be
told apart by these tests; that may be why the paper quotes one number for both.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Final

import numpy as np
from scipy.optimize import brentq

from .._core import ConfigError
from ..campaign import MAX_THREADS, MAX_TRIALS, CampaignResult, run_campaign
from ..checks import int_arg
from ..config import System
from ..cycles import Cycle, step_cycle
from ..effects import Backlash, StochasticFriction
from ..output import staged_output, write_json
from .reproduce import GainSource, study_system

__all__ = [
    "GIVEN_MODEL_NAME",
    "PAPER_FIGURES_M",
    "SEED_PRESET_NAME",
    "CampaignSettings",
    "check_threads",
    "paper_campaigns",
    "step_campaign",
    "write_paper_campaigns",
]

#: The paper's ISO 230-2 figures by step size [m].
PAPER_FIGURES_M: Final[dict[float, float]] = {100e-6: 3.19e-6, 1e-3: 1.83e-6}
#: The result's ``model`` without a model: the seed preset.
SEED_PRESET_NAME: Final[str] = "seed preset"
#: The result's ``model`` with a model (a System) given without a name.
GIVEN_MODEL_NAME: Final[str] = "a given System (no name given)"
#: Largest backlash width of the campaigns [m] (five times the gearhead's 20 µm).
MAX_BACKLASH_M: Final[float] = 1e-4
#: Calibration step and prediction step [m].
CALIBRATION_STEP_M: Final[float] = 100e-6
PREDICTION_STEP_M: Final[float] = 1e-3
#: Readings: (key, ISO attribute, symbol).
READINGS: Final[tuple[tuple[str, str, str], ...]] = (
    ("A_up", "accuracy_up_m", "A↑"),
    ("R_up", "repeatability_up_m", "R↑"),
)
#: Calibrations: (name, reading key, statistic, label). Per trial (the paper's number is one
#: test) first; pooled (every step of every trial as runs of one test) as the second reading.
CALIBRATIONS: Final[tuple[tuple[str, str, str, str], ...]] = (
    ("A_up", "A_up", "mean_m", "A↑ (mean over trials)"),
    ("R_up", "R_up", "mean_m", "R↑ (mean over trials)"),
    ("A_up_pooled", "A_up", "pooled_m", "A↑ (pooled)"),
    ("R_up_pooled", "R_up", "pooled_m", "R↑ (pooled)"),
)


@dataclass(frozen=True, slots=True, kw_only=True)
class CampaignSettings:
    """Settings of the step campaigns (none of them is given by the paper).

    Attributes
    ----------
    repeats : int
        Steps per test (runs of the one ISO target).
    dwell_s : float
        Rest at the target before the reading [s].
    return_s : float
        Rest at the start before each step [s].
    n_trials : int
        Trials (tests) per campaign.
    seed : int
        Campaign seed; the same at every spread (common random numbers).
    spreads : tuple of float
        Grid of ``level_spread`` values scanned, in [0, 0.5].
    xtol : float
        Absolute tolerance of the refined spread.
    backlash_width_m : float
        Gearhead backlash in the loop [m], in [0, 1e-4]: 0 (default) is the paper's model;
        any other width adds :class:`~nanostage.effects.Backlash` with the library's
        contact stiffness and damping (the held-out check of a model with the backlash the
        paper's steps are meant to avoid, docs/campaigns.md).
    """

    repeats: int = 5
    dwell_s: float = 0.5
    return_s: float = 0.5
    n_trials: int = 32
    seed: int = 0
    spreads: tuple[float, ...] = (0.0, 0.025, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5)
    xtol: float = 1e-3
    backlash_width_m: float = 0.0

    def __post_init__(self) -> None:
        w = self.backlash_width_m
        if not (isinstance(w, int | float) and math.isfinite(w) and 0.0 <= w <= MAX_BACKLASH_M):
            raise ConfigError(
                f"CampaignSettings.backlash_width_m = {w!r} is invalid: expected a width in "
                f"[0, {MAX_BACKLASH_M:g}] m (0: no backlash)"
            )
        int_arg("CampaignSettings.n_trials", self.n_trials, 1, MAX_TRIALS, strict=True)
        int_arg("CampaignSettings.seed", self.seed, 0, 2**64 - 1, strict=True)
        int_arg("CampaignSettings.repeats", self.repeats, 1, 2**31 - 1, strict=True)
        spreads = self.spreads
        if (
            not isinstance(spreads, tuple)
            or not spreads
            or not all(
                isinstance(s, int | float) and not isinstance(s, bool) and 0.0 <= s <= 0.5
                for s in spreads
            )
        ):
            raise ConfigError(
                f"CampaignSettings.spreads = {spreads!r} is invalid: expected a non-empty "
                "tuple of level spreads in [0, 0.5]"
            )
        x = self.xtol
        if not (isinstance(x, int | float) and math.isfinite(x) and 0.0 < x <= 0.1):
            raise ConfigError(
                f"CampaignSettings.xtol = {x!r} is invalid: expected a tolerance in (0, 0.1]"
            )
        # The cycle's own checks (dwell and return times, total length), before any work.
        for step in (CALIBRATION_STEP_M, PREDICTION_STEP_M):
            _cycle(step, self)


def check_threads(threads: int | None) -> None:
    """Check a campaign thread count (``None``: all cores) before any work.

    Raises
    ------
    ConfigError
        ``threads`` is not an integer in [1, :data:`~nanostage.campaign.MAX_THREADS`].
    """
    if threads is not None and (
        isinstance(threads, bool) or not isinstance(threads, int) or not 1 <= threads <= MAX_THREADS
    ):
        raise ConfigError(
            f"threads = {threads!r} is invalid: expected an integer in [1, {MAX_THREADS}] "
            "(or None: all cores)"
        )


def _cycle(step_m: float, st: CampaignSettings) -> Cycle:
    return step_cycle(
        step_m=step_m,
        repeats=st.repeats,
        dwell_s=st.dwell_s,
        return_s=st.return_s,
        sample_period_s=1e-3,
    )


def _system(
    step_m: float,
    spread: float,
    backlash_width_m: float = 0.0,
    model: System | None = None,
    gains: GainSource = "table1",
) -> System:
    base = study_system(step_m, model, gains)
    backlash = Backlash(width_m=backlash_width_m) if backlash_width_m > 0.0 else None
    return replace(
        base,
        effects=replace(
            base.effects, stochastic=StochasticFriction(level_spread=spread), backlash=backlash
        ),
    )


def step_campaign(
    step_m: float,
    spread: float,
    st: CampaignSettings,
    *,
    threads: int | None = None,
    model: System | None = None,
    gains: GainSource = "table1",
) -> CampaignResult:
    """One campaign of repeated ``step_m`` steps at ``level_spread = spread`` (on the seed
    axis, or on ``model`` with the Table 1 gains, or its own with ``gains="model"``)."""
    return run_campaign(
        _system(step_m, spread, st.backlash_width_m, model, gains),
        _cycle(step_m, st),
        n_trials=st.n_trials,
        seed=st.seed,
        threads=threads,
        progress=False,
    )


def _readings(r: CampaignResult) -> dict[str, Any]:
    """Mean, median and 5–95 % of A↑ and R↑ over trials, and the pooled values [m]."""
    dist = r.distribution()
    pooled = r.evaluate()
    out: dict[str, Any] = {"n_failed": r.n_failed, "compute_s": r.compute_s}
    for key, attr, _ in READINGS:
        v = dist[attr][np.isfinite(dist[attr])]
        out[key] = {
            "mean_m": float(np.mean(v)),
            "median_m": float(np.median(v)),
            "p5_m": float(np.percentile(v, 5.0)),
            "p95_m": float(np.percentile(v, 95.0)),
            "pooled_m": float(getattr(pooled, attr)),
        }
    mean_dev = np.nanmean(r.position_m) - float(r.cycle.target_m[0])
    out["mean_deviation_m"] = float(mean_dev)
    return out


def _calibrate(
    objective: Callable[[float], float],
    grid: list[tuple[float, float]],
    target_m: float,
    xtol: float,
) -> dict[str, Any]:
    """Root of ``objective(s) = target`` bracketed by the grid, refined with brentq."""
    values = [v for _, v in grid]
    for (s0, v0), (s1, v1) in itertools.pairwise(grid):
        if (v0 - target_m) * (v1 - target_m) <= 0.0:
            if v0 == target_m:
                s = s0
            elif v1 == target_m:
                s = s1
            else:
                s = float(brentq(lambda x: objective(x) - target_m, s0, s1, xtol=xtol))
            return {"reached": True, "spread": s, "bracket": [s0, s1]}
    best = min(grid, key=lambda p: abs(p[1] - target_m))
    return {
        "reached": False,
        "spread": best[0],
        "closest_m": best[1],
        "reachable_range_m": [min(values), max(values)],
    }


def paper_campaigns(
    st: CampaignSettings | None = None,
    *,
    threads: int | None = None,
    log: Callable[[str], None] | None = None,
    model: System | None = None,
    gains: GainSource = "table1",
    model_name: str | None = None,
) -> dict[str, Any]:
    """Scan, calibrate on the 100 µm figure (on A↑ and on R↑ separately) and predict 1 mm.

    ``model``: the axis (default: the seed preset), with the Table 1 gains of each step
    size in place of its PID gains, or with ``gains="model"`` its own gains at both step
    sizes (:func:`nanostage.studies.reproduce.study_system`); checked before any campaign
    runs. ``model_name``: what the result and the Markdown call the model (e.g. its file's
    path); default :data:`SEED_PRESET_NAME` without a ``model``, :data:`GIVEN_MODEL_NAME`
    with one.

    Returns
    -------
    dict
        ``settings``, ``model`` (the model's name), ``gains``, ``paper_m``, ``scan``
        (readings per spread for both step sizes), ``calibration`` (per reading: the
        spread, whether 3.19 µm was reached, the 100 µm value at that spread and the 1 mm
        prediction with its ratio to 1.83 µm), ``better_reading`` and ``compute_s``.
        Lengths in metres.
    """
    st = st or CampaignSettings()
    for step in (CALIBRATION_STEP_M, PREDICTION_STEP_M):
        _system(step, 0.0, st.backlash_width_m, model, gains)
    used_model = _model_name(model, model_name)
    say = log or (lambda _msg: None)
    t0 = time.perf_counter()
    cache: dict[tuple[float, float], dict[str, Any]] = {}

    def readings(step_m: float, s: float) -> dict[str, Any]:
        key = (step_m, s)
        if key not in cache:
            cache[key] = _readings(
                step_campaign(step_m, s, st, threads=threads, model=model, gains=gains)
            )
            r = cache[key]
            say(
                f"  {step_m * 1e6:6.0f} µm, spread {s:.4f}: A↑ mean "
                f"{r['A_up']['mean_m'] * 1e6:.3f} µm, R↑ mean {r['R_up']['mean_m'] * 1e6:.3f} µm"
                f" ({r['compute_s']:.1f} s)"
            )
        return cache[key]

    scan: dict[str, list[dict[str, Any]]] = {}
    for step in (CALIBRATION_STEP_M, PREDICTION_STEP_M):
        say(f"scan {step * 1e6:.0f} µm steps, {st.n_trials} trials per spread")
        scan[f"{step * 1e6:.0f}um"] = [{"spread": s, **readings(step, s)} for s in st.spreads]
    calibration: dict[str, Any] = {}
    target = PAPER_FIGURES_M[CALIBRATION_STEP_M]
    paper_1mm = PAPER_FIGURES_M[PREDICTION_STEP_M]
    for name, key, stat, label in CALIBRATIONS:
        say(f"calibrate on {label}")

        def objective(s: float, key: str = key, stat: str = stat) -> float:
            return float(readings(CALIBRATION_STEP_M, s)[key][stat])

        grid = [(s, objective(s)) for s in st.spreads]
        cal = _calibrate(objective, grid, target, st.xtol)
        s = float(cal["spread"])
        at_100 = readings(CALIBRATION_STEP_M, s)
        at_1mm = readings(PREDICTION_STEP_M, s)
        cal["label"] = label
        cal["simulated_100um_m"] = {k: at_100[k][stat] for k, _, _ in READINGS}
        cal["predicted_1mm_m"] = {k: at_1mm[k][stat] for k, _, _ in READINGS}
        cal["predicted_1mm_over_paper"] = at_1mm[key][stat] / paper_1mm
        cal["predicted_ratio_100um_to_1mm"] = at_100[key][stat] / at_1mm[key][stat]
        calibration[name] = cal
    errs = {k: abs(math.log(calibration[k]["predicted_1mm_over_paper"])) for k in ("A_up", "R_up")}
    if math.isclose(errs["A_up"], errs["R_up"], rel_tol=1e-9, abs_tol=1e-12):
        better = "indistinguishable (one target: A↑ = R↑)"
    else:
        better = min(errs, key=errs.__getitem__)
    return {
        "settings": asdict(st),
        "model": used_model,
        "gains": gains,
        "paper_m": {"100um": PAPER_FIGURES_M[100e-6], "1mm": PAPER_FIGURES_M[1e-3]},
        "paper_ratio_100um_to_1mm": PAPER_FIGURES_M[100e-6] / PAPER_FIGURES_M[1e-3],
        "scan": scan,
        "calibration": calibration,
        "better_reading": better,
        "compute_s": time.perf_counter() - t0,
    }


def _model_name(model: System | None, model_name: str | None) -> str:
    if model_name is not None:
        if model is None:
            raise ConfigError(
                f"model_name = {model_name!r} is given without a model: the campaigns run on "
                "the seed preset (give model= as well, or no model_name)"
            )
        if not isinstance(model_name, str) or not model_name.strip():
            raise ConfigError(
                f"model_name = {model_name!r} is invalid: expected a non-empty string (e.g. "
                "the model file's path)"
            )
        return model_name
    return SEED_PRESET_NAME if model is None else GIVEN_MODEL_NAME


def _axis_words(res: dict[str, Any]) -> str:
    """The axis the campaigns ran on, for the Markdown: "Seed axis" for the seed preset
    (also for a result without ``model``, written before it was recorded)."""
    name = res.get("model", SEED_PRESET_NAME)
    return "Seed axis" if name == SEED_PRESET_NAME else f"Axis of the model {name}"


def _um(v: float) -> str:
    return f"{v * 1e6:.3f}"


def _backlash_words(width_m: float) -> str:
    return f" with {width_m * 1e6:g} µm gearhead backlash" if width_m > 0.0 else ""


def markdown(res: dict[str, Any]) -> str:
    """The results of :func:`paper_campaigns` as Markdown."""
    st = res["settings"]
    gain_words = (
        "the model's own gains"
        if res.get("gains", "table1") == "model"
        else "Table 1 gains per step size"
    )
    lines = [
        "# ISO 230-2 step campaigns: calibration on 100 µm, prediction of 1 mm",
        "",
        f"{_axis_words(res)}{_backlash_words(st['backlash_width_m'])}, {gain_words}, "
        "`StochasticFriction(level_spread=s)` "
        f"(log-normal per-trial friction level, mean 1). Step cycle: {st['repeats']} steps, "
        f"dwell {st['dwell_s']} s, return {st['return_s']} s; {st['n_trials']} trials per "
        f"campaign, seed {st['seed']} at every spread (common random numbers). Readings: "
        "true table position (interferometer); per-trial values averaged over trials; "
        "'pooled' takes all trials' steps as runs of one test.",
        "",
        f"Paper: 3.19 µm (100 µm), 1.83 µm (1 mm); ratio {res['paper_ratio_100um_to_1mm']:.2f}.",
        "",
        "## Scan [µm]",
        "",
        "| step | spread s | A↑ mean | R↑ mean | R↑ median | R↑ 5–95 % | R↑ pooled "
        "| mean deviation | failed |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for step, rows in res["scan"].items():
        for r in rows:
            ru = r["R_up"]
            lines.append(
                f"| {step} | {r['spread']:.3f} | {_um(r['A_up']['mean_m'])} "
                f"| {_um(ru['mean_m'])} | {_um(ru['median_m'])} "
                f"| {_um(ru['p5_m'])}–{_um(ru['p95_m'])} | {_um(ru['pooled_m'])} "
                f"| {_um(r['mean_deviation_m'])} | {r['n_failed']} |"
            )
    lines += [
        "",
        "## Calibration",
        "",
        "| calibrated on | reached 3.19 µm | spread s | 100 µm A↑ / R↑ [µm] "
        "| predicted 1 mm A↑ / R↑ [µm] | predicted / 1.83 µm | ratio 100 µm / 1 mm "
        "| note |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, _, _, label in CALIBRATIONS:
        c = res["calibration"][name]
        note = (
            f"bracket {c['bracket']}"
            if c["reached"]
            else "not reachable: reachable range "
            f"{_um(c['reachable_range_m'][0])}–{_um(c['reachable_range_m'][1])} µm; "
            "prediction at the closest spread"
        )
        a, r = c["simulated_100um_m"], c["predicted_1mm_m"]
        lines.append(
            f"| {label} | {'yes' if c['reached'] else 'no'} | {c['spread']:.4f} "
            f"| {_um(a['A_up'])} / {_um(a['R_up'])} | {_um(r['A_up'])} / {_um(r['R_up'])} "
            f"| {c['predicted_1mm_over_paper']:.3f} "
            f"| {c['predicted_ratio_100um_to_1mm']:.2f} "
            f"(paper {res['paper_ratio_100um_to_1mm']:.2f}) "
            f"| {note} |"
        )
    lines += [
        "",
        f"Which reading the paper's numbers fit better: {res['better_reading']}.",
        "",
        f"Compute time: {res['compute_s']:.1f} s.",
        "",
    ]
    return "\n".join(lines)


def write_paper_campaigns(
    out_dir: str | Path,
    st: CampaignSettings | None = None,
    *,
    threads: int | None = None,
    log: Callable[[str], None] | None = None,
    model: System | None = None,
    gains: GainSource = "table1",
    model_name: str | None = None,
) -> dict[str, Any]:
    """Run :func:`paper_campaigns`, write ``campaigns.json`` and ``campaigns.md``.

    The folder is written whole or not at all (:func:`nanostage.output.staged_output`): it
    must be new, empty or an earlier run's folder, which is checked before any work.
    """
    check_threads(threads)
    with staged_output(out_dir, "reproduce --campaigns") as folder:
        return write_paper_campaigns_into(
            folder, st, threads=threads, log=log, model=model, gains=gains, model_name=model_name
        )


def write_paper_campaigns_into(
    folder: Path,
    st: CampaignSettings | None = None,
    *,
    threads: int | None = None,
    log: Callable[[str], None] | None = None,
    model: System | None = None,
    gains: GainSource = "table1",
    model_name: str | None = None,
) -> dict[str, Any]:
    """:func:`write_paper_campaigns` writing straight into an existing ``folder`` (a staged
    one)."""
    check_threads(threads)
    out = Path(folder)
    res = paper_campaigns(
        st, threads=threads, log=log, model=model, gains=gains, model_name=model_name
    )
    write_json(res, out / "campaigns.json", indent=2)
    md = markdown(res)
    (out / "campaigns.md").write_text(md, encoding="utf-8")
    res["markdown"] = md
    return res
