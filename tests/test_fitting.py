"""The fitting toolkit shared by friction identification and the diagnosis
(nanostage.fitting): the shared pieces, and friction_fit results pinned to their values
from before friction_fit was moved onto them (computed with the code of that time)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nanostage.diagnosis.candidates import Param as CandidateParam
from nanostage.diagnosis.candidates import applicable_candidates
from nanostage.effects import LuGre, StaticFrictionMap
from nanostage.fitting import (
    Param,
    harmonic,
    information_criteria,
    simplest_of_ties,
    static_map,
)
from nanostage.friction import friction_response
from nanostage.friction_fit import MODELS, FrictionData, compare_models, fit_friction, gms_family
from nanostage.presets import preset_system

#: Relative tolerance of the pinned values: far below any change of the method, far above
#: the rounding differences of another BLAS or CPU.
REL = 1e-6
#: The same for the fits pinned after 10 and 25 evaluations, far from convergence, where
#: rounding differences grow with every step: the same code on an AMD EPYC (numpy 2.4.6
#: with its OpenBLAS) gave values up to 1.6e-3 relative from the pins, made on another
#: machine; a change of the method moves such a fit by far more.
REL_EARLY_STOP = 1e-2


def record() -> FrictionData:
    """Three repetitions of a 3 µm presliding sinusoid and 0.5, 2 and 8 mm/s velocity
    sinusoids (2 Hz, 200 Hz sampling), LuGre truth (Fc 10 N, Fs 15 N), force noise 0.1 N."""
    rng = np.random.default_rng(5)
    ts, vs, t0, fs = [], [], 0.0, 200.0
    for _ in range(3):
        for amp_v in (2 * np.pi * 2.0 * 3e-6, 0.5e-3, 2e-3, 8e-3):
            a = amp_v * rng.uniform(0.8, 1.2) * rng.choice([-1.0, 1.0])
            tt = (np.arange(100) + 0.5) / fs
            ts.append(t0 + tt)
            vs.append(a * np.sin(2 * np.pi * 2.0 * tt))
            t0 += 100 / fs
    t, v = np.concatenate(ts), np.concatenate(vs)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
    truth = LuGre(
        stiffness_n_per_m=1e7,
        damping_n_s_per_m=1e4,
        viscous_n_s_per_m=300.0,
        coulomb_force_n=10.0,
        static_force_n=15.0,
        stribeck_velocity_m_per_s=1e-3,
    )
    f = friction_response(truth, t, x, v) + np.random.default_rng(2).normal(0.0, 0.1, t.size)
    return FrictionData(t, x, v, f)


DATA = record()


def test_one_param_class() -> None:
    assert CandidateParam is Param
    p = Param(name="k", unit="N/m", lower=1e4, upper=1e8, initial=1e6, log=True)
    assert p.from_unit(0.5) == pytest.approx(1e6, rel=1e-12)
    assert p.to_unit(1e6) == pytest.approx(0.5, rel=1e-12)
    assert p.from_unit(2.0) == pytest.approx(1e8, rel=1e-12)  # clamped to the bounds
    lin = Param(name="a", unit="1", lower=-0.5, upper=0.5, initial=0.0)
    assert lin.from_unit(0.25) == -0.25


def test_information_criteria_by_hand() -> None:
    aic, bic = information_criteria(8.0, 100, 3)
    ll = 100 * math.log(0.08)
    assert aic == pytest.approx(ll + 6, rel=1e-15)
    assert bic == pytest.approx(ll + 3 * math.log(100), rel=1e-15)


def test_simplest_of_ties() -> None:
    ranked = [("c", 3), ("a", 1), ("b", 1), ("d", 0)]
    tied = {"c", "a", "b"}
    # Least complexity among the tied, the first in rank order when equal.
    assert simplest_of_ties(ranked, lambda r: r[0] in tied, lambda r: r[1]) == ("a", 1)


def test_shared_constructors() -> None:
    assert static_map(2.0, 0.0, 5.0) == StaticFrictionMap(
        static_force_n=2.0, coulomb_force_n=2.0, viscous_n_s_per_m=5.0
    )
    amp, kappa, phase = harmonic(3.0, 0.3, 0.4)
    assert amp == pytest.approx(0.5, rel=1e-15)
    assert kappa == 3.0
    x = 0.7
    assert amp * math.cos(kappa * x + phase) == pytest.approx(
        0.3 * math.cos(3.0 * x) + 0.4 * math.sin(3.0 * x), rel=1e-12
    )


def test_candidates_build_the_same_models_as_before() -> None:
    system = preset_system("seed")
    cands = {c.name: c for c in applicable_candidates(system)[0]}
    v = (2.0, 3.0, 4e6, 1e-3)
    assert cands["coulomb_viscous"].apply(system, v[:2]).effects.table_friction == (
        StaticFrictionMap(static_force_n=2.0, coulomb_force_n=2.0, viscous_n_s_per_m=3.0)
    )
    assert cands["stribeck"].apply(system, (2.0, 3.0, 1e-3)).effects.table_friction == (
        StaticFrictionMap(static_force_n=5.0, coulomb_force_n=2.0, stribeck_velocity_m_per_s=1e-3)
    )
    assert cands["lugre"].apply(system, v).effects.table_friction == LuGre(
        stiffness_n_per_m=4e6,
        damping_n_s_per_m=0.0,
        viscous_n_s_per_m=0.0,
        coulomb_force_n=2.0,
        static_force_n=5.0,
        stribeck_velocity_m_per_s=1e-3,
    )


def test_friction_fit_catalogue_builds() -> None:
    th = np.array([1e7, 1e3, 300.0, 10.0, 5.0, 1e-3])
    assert MODELS["lugre"].build(th) == LuGre(
        stiffness_n_per_m=1e7,
        damping_n_s_per_m=1e3,
        viscous_n_s_per_m=300.0,
        coulomb_force_n=10.0,
        static_force_n=15.0,
        stribeck_velocity_m_per_s=1e-3,
    )
    assert MODELS["stribeck"].build([10.0, 5.0, 1e-3, 300.0]) == StaticFrictionMap(
        static_force_n=15.0,
        coulomb_force_n=10.0,
        viscous_n_s_per_m=300.0,
        stribeck_velocity_m_per_s=1e-3,
    )


def test_pinned_gms_fit() -> None:
    fit = fit_friction(DATA, gms_family(1), n_starts=1, workers=1, max_nfev=10)
    expected = {
        "slip_force_n[0]": (9.35367341973289, 0.27195883944507004),
        "stiffness_n_per_m[0]": (11610685.205139881, 104620.79931469641),
        "static_excess_n": (4.504852807144732, 0.26487801420455875),
        "stribeck_velocity_m_per_s": (0.0013412781470534421, 7.335427835340508e-05),
        "viscous_n_s_per_m": (411.04989374858195, 48.46251738310957),
    }
    assert list(fit.parameters) == list(expected)
    for name, (value, se) in expected.items():
        assert fit.parameters[name] == pytest.approx(value, rel=REL_EARLY_STOP), name
        assert fit.std_errors[name] == pytest.approx(se, rel=REL_EARLY_STOP), name
        assert fit.parameter_status[name] == "ok"
    assert fit.bounds["stiffness_n_per_m[0]"] == pytest.approx(
        (64468.54796641356, 1939977927.8276622), rel=1e-12
    )
    assert fit.bounds["static_excess_n"][0] == 0.0
    assert fit.bounds["static_excess_n"][1] == pytest.approx(22.735732840620837, rel=1e-12)
    assert fit.aic == pytest.approx(226.32171893399558, rel=REL_EARLY_STOP)
    assert fit.bic == pytest.approx(250.33369275061713, rel=REL_EARLY_STOP)
    assert fit.rms_holdout_n == pytest.approx(0.7829605866118842, rel=REL_EARLY_STOP)


def test_pinned_bounds_override_without_holdout() -> None:
    fit = fit_friction(
        DATA,
        "stribeck",
        n_starts=2,
        workers=1,
        holdout=0.0,
        max_nfev=25,
        bounds={"viscous_n_s_per_m": (1.0, 1e3)},
    )
    assert fit.bounds["viscous_n_s_per_m"] == (1.0, 1000.0)
    assert fit.parameter_status["viscous_n_s_per_m"] == "at_bound"
    assert math.isnan(fit.rms_holdout_n)
    assert fit.parameters["coulomb_force_n"] == pytest.approx(4.687735444413763, rel=REL)
    assert fit.parameters["static_excess_n"] == pytest.approx(5.716830356713146, rel=REL)
    assert fit.aic == pytest.approx(4209.300817023402, rel=REL)
    assert fit.bic == pytest.approx(4229.661124366506, rel=REL)


def test_pinned_comparison() -> None:
    comp = compare_models(
        DATA, ("coulomb_viscous", "stribeck", "dahl"), n_starts=2, workers=1, max_nfev=25
    )
    assert comp.names == ("dahl", "stribeck", "coulomb_viscous")
    assert comp.best.model == "dahl" and comp.rule == "one_se"
    assert comp.threshold_n == pytest.approx(1.6780521913111728, rel=REL_EARLY_STOP)
    dahl = comp["dahl"]
    assert dahl.parameters["coulomb_force_n"] == pytest.approx(
        13.003995428540046, rel=REL_EARLY_STOP
    )
    assert dahl.parameters["exponent"] == pytest.approx(0.7058206655317061, rel=REL_EARLY_STOP)
    assert dahl.parameters["stiffness_n_per_m"] == pytest.approx(
        10172887.980078343, rel=REL_EARLY_STOP
    )
    assert dahl.aic == pytest.approx(673.5494949834348, rel=REL_EARLY_STOP)
    assert dahl.rms_holdout_n == pytest.approx(1.5775077416736791, rel=REL_EARLY_STOP)
    assert dahl.rms_holdout_se_n == pytest.approx(0.10054444963749358, rel=REL_EARLY_STOP)
    assert comp["coulomb_viscous"].parameters["coulomb_force_n"] == pytest.approx(
        10.101578411963153, rel=REL
    )
