"""The fits' secant Jacobian (:class:`~nanostage.diagnosis.fit.SecantJacobian`): forward
differences exactly as scipy takes them, Broyden's update between them, a difference
Jacobian again after a rejected step and at the optimum, and the same optimum as scipy's
``2-point`` for fewer residual evaluations."""

from __future__ import annotations

import dataclasses as dc
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
from diagnosis_cases import friction_problems, step_case
from scipy.optimize import least_squares
from scipy.optimize._numdiff import approx_derivative

from nanostage.diagnosis.fit import FitProblem, SecantJacobian
from nanostage.diagnosis.run import diagnose
from nanostage.diagnosis.settings import DiagnosisSettings
from nanostage.effects import Effects

T = np.linspace(0.0, 3.0, 40)


class Curve:
    """A smooth least-squares problem in the fits' normalised coordinates (each parameter
    in [1, 2]): a damped exponential plus an offset, against data made from known values;
    counts its residual evaluations as :class:`FitProblem` does."""

    def __init__(self) -> None:
        self.data = self.model(np.array([1.6, 1.3, 1.8]))
        self.n_evaluations = 0

    @staticmethod
    def model(u: np.ndarray) -> np.ndarray:
        a, b, c = 2.0 * u[0], 1.5 * u[1], 0.5 * u[2]
        return np.asarray(a * np.exp(-b * T) + c * np.sin(2.0 * T))

    def _vectors(self, us: list[np.ndarray]) -> list[np.ndarray]:
        self.n_evaluations += len(us)
        return [self.model(np.asarray(u)) - self.data for u in us]

    def _vector(self, u: np.ndarray) -> np.ndarray:
        return self._vectors([u])[0]


def _secant(curve: Curve, refresh: int) -> SecantJacobian:
    return SecantJacobian(cast(FitProblem, curve), 0.03, refresh)


@pytest.mark.parametrize("u", [[1.2, 1.5, 1.9], [1.0, 1.99, 1.971], [2.0, 1.0, 1.5]])
def test_differences_are_scipys_two_point_steps(u: list[float]) -> None:
    """Relative step ``diff_step``, backward where the step would pass the upper bound:
    bit for bit scipy's ``2-point`` Jacobian within the bounds [1, 2]."""
    curve = Curve()
    x = np.array(u)
    f = curve._vector(x)
    ours = _secant(curve, 3).differences(x, f)
    theirs = approx_derivative(
        curve._vector, x, method="2-point", rel_step=0.03, f0=f, bounds=(1.0, 2.0)
    )
    np.testing.assert_array_equal(ours, theirs)


def test_broyden_update_between_difference_jacobians() -> None:
    """The first Jacobian is a difference one; the next ``refresh − 1`` accepted steps are
    Broyden's rank-one updates (secant condition J·dx = df holds exactly), then one by
    differences again; after a rejected trial step (two residual evaluations since the last
    Jacobian) always by differences."""
    curve = Curve()
    sec = _secant(curve, 3)
    x0 = np.array([1.2, 1.5, 1.9])
    f0 = sec.fun(x0)
    j0 = sec.jac(x0)
    assert sec.fresh
    np.testing.assert_array_equal(j0, sec.differences(x0, f0))
    x1 = x0 + np.array([0.05, -0.02, 0.01])
    f1 = sec.fun(x1)
    before = curve.n_evaluations
    j1 = sec.jac(x1)
    assert not sec.fresh and curve.n_evaluations == before  # an update costs nothing
    np.testing.assert_allclose(j1 @ (x1 - x0), f1 - f0, rtol=1e-12, atol=1e-12)
    x2 = x1 + np.array([0.01, 0.03, -0.02])
    f2 = sec.fun(x2)
    j2 = sec.jac(x2)
    assert not sec.fresh
    np.testing.assert_allclose(j2 @ (x2 - x1), f2 - f1, rtol=1e-12, atol=1e-12)
    x3 = x2 + np.array([0.02, 0.0, 0.01])
    sec.fun(x3)
    sec.jac(x3)
    assert sec.fresh  # the third accepted step: differences again
    x4 = x3 + np.array([0.01, 0.01, 0.01])
    sec.fun(x4)
    sec.jac(x4)
    assert not sec.fresh
    sec.fun(x4 + 0.2)  # a trial step that the optimiser rejected
    x5 = x4 + np.array([0.005, 0.0, 0.0])
    sec.fun(x5)
    sec.jac(x5)
    assert sec.fresh


def test_same_optimum_as_two_point_for_fewer_evaluations() -> None:
    """From the same start, trf with the secant Jacobian ends at scipy's ``2-point``
    optimum (the data's values, within the step tolerance) with fewer residual
    evaluations, counting every difference point."""
    runs = {}
    for refresh in (1, 4):
        curve = Curve()
        kw: dict[str, Any] = dict(
            bounds=(1.0, 2.0), method="trf", diff_step=0.03, xtol=1e-10, ftol=1e-10, gtol=1e-12
        )
        if refresh == 1:
            sol = least_squares(curve._vector, np.array([1.1, 1.9, 1.2]), **kw)
        else:
            sec = _secant(curve, refresh)
            sol = least_squares(sec.fun, np.array([1.1, 1.9, 1.2]), jac=sec.jac, **kw)
        runs[refresh] = (sol, curve.n_evaluations)
    for sol, _ in runs.values():
        np.testing.assert_allclose(sol.x, [1.6, 1.3, 1.8], atol=1e-6)
    assert runs[4][1] < runs[1][1]


def test_fit_with_secant_jacobian_matches_and_takes_its_errors_from_differences(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A simulation-in-the-loop fit with ``jacobian_refresh`` 4 reaches the training gap of
    the difference-Jacobian fit (no more than 2 % above it) with fewer simulations, and its standard
    errors come from a difference Jacobian at its optimum, not from an update."""
    import nanostage.diagnosis.fit as eng

    problem = friction_problems(
        step_case(tmp_path, Effects(), seed=6),
        force_initial_n=24.0,
        torque_upper_nm=1.2e-4,
        torque_initial_nm=0.7e-4,
    )
    st = DiagnosisSettings(jacobian_refresh=1)
    plain = problem().fit(1, st, seed=0)
    solutions: list[Any] = []
    real = eng.least_squares

    def recording(fun: Any, x0: np.ndarray, **kw: Any) -> Any:
        sol = real(fun, x0, **kw)
        solutions.append(sol)
        return sol

    monkeypatch.setattr(eng, "least_squares", recording)
    secant = problem().fit(1, dc.replace(st, jacobian_refresh=4), seed=0)
    assert secant.train_rms_m <= 1.02 * plain.train_rms_m
    assert secant.n_evaluations < plain.n_evaluations
    assert len(solutions) == 1
    # Whatever the last step's Jacobian was, the fit's errors use the differences there.
    sol = solutions[0]
    diff = SecantJacobian(problem(), st.diff_step, 4)
    np.testing.assert_array_equal(sol.jac, diff.differences(sol.x, diff.fun(sol.x)))
    cov = secant.unit_covariance
    assert cov.shape == (2, 2) and np.all(np.linalg.eigvalsh(cov) >= -1e-12 * np.abs(cov).max())


def test_jacobian_refresh_is_checked_before_any_work(tmp_path: Path) -> None:
    m = step_case(tmp_path, Effects(), seed=6)
    for bad in (0, -2, 2.5, True, "4"):
        with pytest.raises(ValueError, match=r"jacobian_refresh = .*integer ≥ 1"):
            diagnose(
                m,
                None,
                settings=DiagnosisSettings(jacobian_refresh=bad),  # type: ignore[arg-type]
                progress=False,
            )
