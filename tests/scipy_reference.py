"""Independent SciPy reference implementation of the seed axis plant (docs/model.md).

This module is the oracle for the Rust integrator and the SciPy side of the speed comparison.
It is written from docs/model.md only and must not import ``nanostage``.

Model summary (docs/model.md)
-----------------------------
State ``y = [x, v, z, i]`` (``[x, v, z]`` with ``quasi_static_current``) plus a discrete mode:
``STUCK`` or ``SLIP`` with a direction ``d`` in {+1, -1}.  In SLIP, ``d`` replaces ``sign(v)``
so every SLIP segment is a smooth ODE integrated by ``scipy.integrate.solve_ivp`` with a
terminal event on ``v*d`` (crossing from positive to negative).  In STUCK, ``x, v, z`` are
frozen and only the current moves.

Choices made where docs/model.md is silent (the Rust side is expected to match):

* Sampling convention.  ``voltage_v[k]`` is held on ``[t_k, t_{k+1})``.  The arrays returned at
  ``t_k`` (k >= 1) are the state at the *end* of the integration of interval k-1 (left limit)
  after every event located in ``(t_{k-1}, t_k]`` has been processed; index 0 is the initial
  state.  The mode is re-evaluated with the new voltage at the start of interval k, which
  does not change ``x, v, z, i`` (only the mode can change).
* ``current_a`` with ``quasi_static_current``: the algebraic current using the voltage of the
  interval that *ends* at ``t_k`` (``u[k-1]``); at ``t_0`` the voltage ``u[0]`` is used.
* STUCK mode with an inductive motor.  ``di/dt = (u - R i)/L`` with constant ``u`` is solved
  in closed form, ``i(t) = u/R + (i0 - u/R) exp(-(t - t0) R/L)``, and the breakaway instant
  (where ``|T_req|`` reaches the threshold below) is computed in closed form as well.  This
  is exact (no integration error) and is the event "inside the interval" of the doc.  With
  ``quasi_static_current`` the current is ``u/R`` and ``T_req`` is constant while stuck, so
  breakaway can only happen at the start of an interval (or never within it).
* Breakaway/stick threshold.  ``|T_req| > Ts + tol_T`` breaks away and ``|T_req| <= Ts + tol_T``
  sticks, with ``tol_T = 1e-12 * (Ts + r*(Fc + |F_ext|)/eta)`` (``TORQUE_REL_MARGIN``).  The
  tiny margin guarantees that right after a breakaway ``d*dv/dt`` is positive by far more
  than rounding, so the ``v*d`` event cannot fire at the instant the segment starts.  At a
  breakaway located inside an interval the current is set to the value where
  ``|T_req| = Ts + tol_T`` exactly.
* At a SLIP event (``v*d`` reaches 0) the new direction is ``sign(T_req)`` which, in exact
  arithmetic, is always ``-d`` when ``|T_req| > Ts`` (docs/model.md "opposite direction").
  The same "rest rule" (stick, or slip with ``d = sign(T_req)``) is applied whenever a SLIP
  segment would start with ``v*d <= 0`` (e.g. a reversal located exactly at a sample instant).
* Event refinement.  ``solve_ivp`` locates the root of ``v*d`` on the dense-output polynomial
  (which is less accurate than the step end points).  With ``refine_events=True`` the state
  at the event is recomputed by integrating from the last accepted step point to the event
  time with the same method and tolerances, and the event time is polished with a Newton step
  ``dt = -v/(dv/dt)`` (at most ``EVENT_NEWTON_ITERS`` times, while ``|v|`` exceeds
  ``atol_v*1e-3``).  ``v`` is then set to exactly 0.
* Zeno guard.  Every mode transition happening within ``ZENO_DT_REL * T`` of the previous one
  increments a counter (reset when time advances).  When it reaches ``ZENO_MAX_TRANSITIONS``
  the axis is forced STUCK with breakaway disabled until the end of the current sample
  interval, and ``n_zeno_guard`` is incremented.  This never triggers in the self-tests
  (asserted there); it exists so that degenerate parameter sets (e.g. ``|T_req| == Ts``
  to rounding with no current change) cannot hang the oracle.
* Default ``atol`` (per component, SI): position 1e-13 m, velocity 1e-10 m/s, Dahl force 1e-7
  N, current 1e-9 A (the last one dropped with ``quasi_static_current``).  A scalar ``atol``
  is applied to all components.
* The analytic Jacobian is passed to the implicit methods (Radau, BDF, LSODA) unless
  ``use_jacobian=False``.  ``n_rhs`` counts every call of the right-hand side (including the
  finite-difference Jacobian calls that SciPy's ``nfev`` leaves out, and the event-refinement
  re-integrations); Jacobian evaluations (analytic or numerical) are reported as ``n_jac``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

__all__ = [
    "DEFAULT_ATOL",
    "PARAM_FIELDS",
    "derived_quantities",
    "seed_like_params",
    "simulate_plant_scipy",
    "slip_jacobian",
    "slip_rhs",
]

#: Fields of the core's parameters that this reference does not model: accepted at 0 only
#: (the table's Dahl law is symmetric here).
ZERO_ONLY_FIELDS: dict[str, tuple[str, ...]] = {"dahl": ("asymmetry",)}

PARAM_FIELDS: dict[str, tuple[str, ...]] = {
    "motor": (
        "resistance_ohm",
        "inductance_h",
        "torque_constant_nm_per_a",
        "back_emf_v_s_per_rad",
        "rotor_inertia_kg_m2",
        "quasi_static_current",
    ),
    "motor_friction": (
        "static_torque_nm",
        "coulomb_torque_nm",
        "viscous_nm_s_per_rad",
        "stribeck_velocity_rad_per_s",
        "stribeck_exponent",
    ),
    "gearhead": ("ratio", "efficiency"),
    "screw": ("lead_m", "efficiency", "inertia_kg_m2"),
    "table": ("mass_kg", "external_force_n"),
    "dahl": ("coulomb_force_n", "stiffness_n_per_m", "exponent"),
}

#: Default absolute tolerances [x (m), v (m/s), z (N), i (A)].
DEFAULT_ATOL = (1e-13, 1e-10, 1e-7, 1e-9)

TORQUE_REL_MARGIN = 1e-12
ZENO_DT_REL = 1e-12
ZENO_MAX_TRANSITIONS = 4
EVENT_NEWTON_ITERS = 3
MAX_SEGMENTS_PER_INTERVAL = 10_000

_IMPLICIT_METHODS = ("Radau", "BDF", "LSODA")


def seed_like_params() -> dict:
    """A plausible parameter set (DOMAIN.md sections 4 and 7) for self-tests."""
    return {
        "motor": {
            "resistance_ohm": 3.4,
            "inductance_h": 70e-6,
            "torque_constant_nm_per_a": 6.6e-3,
            "back_emf_v_s_per_rad": 6.6e-3,
            "rotor_inertia_kg_m2": 1.0e-7,
            "quasi_static_current": False,
        },
        "motor_friction": {
            "static_torque_nm": 0.15e-3,
            "coulomb_torque_nm": 0.1e-3,
            "viscous_nm_s_per_rad": 3.6e-8,
            "stribeck_velocity_rad_per_s": 10.0,
            "stribeck_exponent": 2.0,
        },
        "gearhead": {"ratio": 19.0, "efficiency": 0.8},
        "screw": {"lead_m": 2e-3, "efficiency": 0.9, "inertia_kg_m2": 1e-7},
        "table": {"mass_kg": 0.5, "external_force_n": 0.0},
        "dahl": {"coulomb_force_n": 30.4, "stiffness_n_per_m": 7.5e7, "exponent": 1.0},
    }


@dataclass(frozen=True)
class _Plant:
    R: float
    L: float
    kt: float
    ke: float
    Jm: float
    quasi_static: bool
    Ts: float
    Tc: float
    b: float
    ws: float
    delta: float
    N: float
    P: float
    Js: float
    m: float
    F_ext: float
    Fc: float
    sigma: float
    n_dahl: float
    r: float
    eta: float
    m_eq: float
    tol_T: float

    @property
    def dim(self) -> int:
        return 3 if self.quasi_static else 4


def _plant_from_params(params: dict) -> _Plant:
    for block, fields in PARAM_FIELDS.items():
        if block not in params:
            raise KeyError(f"params is missing block {block!r}")
        got = params[block]
        missing = [f for f in fields if f not in got]
        if missing:
            raise KeyError(f"params[{block!r}] is missing {missing}")
        unknown = [f for f in got if f not in fields and f not in ZERO_ONLY_FIELDS.get(block, ())]
        if unknown:
            raise ValueError(f"params[{block!r}] has unknown fields {unknown}")
        nonzero = [f for f in ZERO_ONLY_FIELDS.get(block, ()) if float(got.get(f, 0.0)) != 0.0]
        if nonzero:
            raise ValueError(
                f"params[{block!r}]: {nonzero} not 0; the reference models them only at 0"
            )
    mo, fr, gh, sc, tb, dl = (params[b] for b in PARAM_FIELDS)
    quasi = bool(mo["quasi_static_current"])
    R = float(mo["resistance_ohm"])
    L = float(mo["inductance_h"])
    kt = float(mo["torque_constant_nm_per_a"])
    N = float(gh["ratio"])
    P = float(sc["lead_m"])
    Jm = float(mo["rotor_inertia_kg_m2"])
    Js = float(sc["inertia_kg_m2"])
    m = float(tb["mass_kg"])
    Fc = float(dl["coulomb_force_n"])
    eta = float(gh["efficiency"]) * float(sc["efficiency"])
    Ts = float(fr["static_torque_nm"])
    F_ext = float(tb["external_force_n"])
    checks = {
        "resistance_ohm > 0": R > 0,
        "inductance_h > 0 (or quasi_static_current)": quasi or L > 0,
        "torque_constant_nm_per_a > 0": kt > 0,
        "ratio > 0": N > 0,
        "lead_m > 0": P > 0,
        "efficiency product > 0": eta > 0,
        "coulomb_force_n > 0": Fc > 0,
        "stribeck_velocity_rad_per_s > 0": float(fr["stribeck_velocity_rad_per_s"]) > 0,
        "static_torque_nm >= 0": Ts >= 0,
    }
    bad = [k for k, ok in checks.items() if not ok]
    if bad:
        raise ValueError(f"invalid parameters: {bad}")
    r = P / (2.0 * math.pi * N)
    m_eq = m + eta * Jm / r**2 + float(sc["efficiency"]) * Js * (2.0 * math.pi / P) ** 2
    tol_T = TORQUE_REL_MARGIN * (Ts + r * (Fc + abs(F_ext)) / eta)
    return _Plant(
        R=R,
        L=L,
        kt=kt,
        ke=float(mo["back_emf_v_s_per_rad"]),
        Jm=Jm,
        quasi_static=quasi,
        Ts=Ts,
        Tc=float(fr["coulomb_torque_nm"]),
        b=float(fr["viscous_nm_s_per_rad"]),
        ws=float(fr["stribeck_velocity_rad_per_s"]),
        delta=float(fr["stribeck_exponent"]),
        N=N,
        P=P,
        Js=Js,
        m=m,
        F_ext=F_ext,
        Fc=Fc,
        sigma=float(dl["stiffness_n_per_m"]),
        n_dahl=float(dl["exponent"]),
        r=r,
        eta=eta,
        m_eq=m_eq,
        tol_T=tol_T,
    )


def derived_quantities(params: dict) -> dict[str, float]:
    """Derived constants of docs/model.md: r, eta, m_eq (and the stick threshold margin)."""
    p = _plant_from_params(params)
    return {"r": p.r, "eta": p.eta, "m_eq": p.m_eq, "tol_T": p.tol_T}


# ---------------------------------------------------------------------------------------------
# SLIP-mode right-hand side and Jacobian
# ---------------------------------------------------------------------------------------------


def _slip_rhs(p: _Plant, u: float, d: float, y) -> np.ndarray:
    v = y[1]
    z = y[2]
    w = v / p.r
    s = math.exp(-(abs(w / p.ws) ** p.delta))
    Tf = d * (p.Tc + (p.Ts - p.Tc) * s) + p.b * w
    if p.quasi_static:
        i = (u - p.ke * w) / p.R
    else:
        i = y[3]
    F_drv = p.eta * (p.kt * i - Tf) / p.r
    dv = (F_drv - z - p.F_ext) / p.m_eq
    q = 1.0 - z * d / p.Fc
    if p.n_dahl == 1.0:
        dz = p.sigma * v * q
    else:
        dz = p.sigma * v * abs(q) ** p.n_dahl * math.copysign(1.0, q) if q != 0.0 else 0.0
    if p.quasi_static:
        return np.array((v, dv, dz))
    di = (u - p.R * i - p.ke * w) / p.L
    return np.array((v, dv, dz, di))


def _slip_jac(p: _Plant, u: float, d: float, y) -> np.ndarray:
    v = y[1]
    z = y[2]
    w = v / p.r
    a = abs(w / p.ws)
    s = math.exp(-(a**p.delta))
    # d/dw of exp(-|w/ws|^delta) = -s * delta * |w/ws|^(delta-1) * sign(w) / ws
    if w == 0.0:
        ds_dw = 0.0  # 0 for delta > 1; infinite for delta < 1 (only affects Newton convergence)
    else:
        ds_dw = -s * p.delta * a ** (p.delta - 1.0) * math.copysign(1.0, w) / p.ws
    dTf_dv = (d * (p.Ts - p.Tc) * ds_dw + p.b) / p.r
    J = np.zeros((p.dim, p.dim))
    J[0, 1] = 1.0
    dv_dv = -p.eta * dTf_dv / p.r
    if p.quasi_static:
        dv_dv += p.eta * p.kt / p.r * (-p.ke / (p.r * p.R))
    else:
        J[1, 3] = p.eta * p.kt / (p.r * p.m_eq)
        J[3, 1] = -p.ke / (p.r * p.L)
        J[3, 3] = -p.R / p.L
    J[1, 1] = dv_dv / p.m_eq
    J[1, 2] = -1.0 / p.m_eq
    q = 1.0 - z * d / p.Fc
    if p.n_dahl == 1.0:
        J[2, 1] = p.sigma * q
        J[2, 2] = -p.sigma * v * d / p.Fc
    elif q != 0.0:
        J[2, 1] = p.sigma * abs(q) ** p.n_dahl * math.copysign(1.0, q)
        J[2, 2] = p.sigma * v * p.n_dahl * abs(q) ** (p.n_dahl - 1.0) * (-d / p.Fc)
    return J


def slip_rhs(params: dict, u: float, d: int, y) -> np.ndarray:
    """Public SLIP right-hand side (for tests): dy/dt for direction d and voltage u."""
    return _slip_rhs(_plant_from_params(params), float(u), float(d), np.asarray(y, float))


def slip_jacobian(params: dict, u: float, d: int, y) -> np.ndarray:
    """Public analytic Jacobian of :func:`slip_rhs` with respect to y."""
    return _slip_jac(_plant_from_params(params), float(u), float(d), np.asarray(y, float))


# ---------------------------------------------------------------------------------------------
# Hybrid simulation
# ---------------------------------------------------------------------------------------------


def _t_req(p: _Plant, i: float, z: float) -> float:
    return p.kt * i - p.r * (z + p.F_ext) / p.eta


def _sign(x: float) -> float:
    return 1.0 if x > 0.0 else -1.0


class _Sim:
    def __init__(self, p, method, rtol, atol, use_jacobian, refine_events):
        self.p = p
        self.method = method
        self.rtol = rtol
        self.atol = atol
        self.use_jac = use_jacobian and method in _IMPLICIT_METHODS
        self.refine = refine_events
        self.n_rhs = 0
        self.n_jac = 0
        self.n_events = 0
        self.n_breakaways = 0
        self.n_zeno = 0
        self.n_segments = 0
        self.atol_v = float(atol[1]) if np.ndim(atol) else float(atol)

    # -- helpers --------------------------------------------------------------------------
    def current(self, y, u):
        p = self.p
        if p.quasi_static:
            return (u - p.ke * y[1] / p.r) / p.R
        return y[3]

    def rest_rule(self, y, u):
        """Mode at v = 0: (stuck, d)."""
        T = _t_req(self.p, self.current(y, u), y[2])
        if abs(T) <= self.p.Ts + self.p.tol_T:
            return True, 0.0
        return False, _sign(T)

    def _solve(self, t0, t1, y0, u, d, with_event):
        p = self.p
        kw = {}
        if with_event:

            def ev(t, y):
                return y[1] * d

            ev.terminal = True
            ev.direction = -1
            kw["events"] = [ev]
        if self.use_jac:
            kw["jac"] = lambda t, y: _slip_jac(p, u, d, y)

        def fun(t, y):
            self.n_rhs += 1
            return _slip_rhs(p, u, d, y)

        sol = solve_ivp(
            fun,
            (t0, t1),
            y0,
            method=self.method,
            rtol=self.rtol,
            atol=self.atol,
            **kw,
        )
        self.n_jac += int(sol.njev)
        if sol.status < 0:
            raise RuntimeError(f"solve_ivp failed on [{t0}, {t1}]: {sol.message}")
        return sol

    # -- one SLIP segment -------------------------------------------------------------------
    def slip_segment(self, t, t_end, y, u, d):
        """Integrate SLIP(d) from t; return (t_new, y_new, event_happened)."""
        self.n_segments += 1
        sol = self._solve(t, t_end, y, u, d, with_event=True)
        if sol.status != 1:
            return t_end, sol.y[:, -1].copy(), False
        t_e = float(sol.t_events[0][0])
        y_e = np.array(sol.y_events[0][0], dtype=float)
        if self.refine and len(sol.t) >= 2:
            # Last accepted step point strictly before the event (full step accuracy).
            k = len(sol.t) - 2
            while k > 0 and sol.t[k] >= t_e:
                k -= 1
            t_a, y_a = float(sol.t[k]), sol.y[:, k].copy()
            if t_e > t_a:
                for _ in range(EVENT_NEWTON_ITERS):
                    y_r = self._solve(t_a, t_e, y_a, u, d, with_event=False).y[:, -1]
                    y_e = y_r.copy()
                    if abs(y_r[1]) <= 1e-3 * self.atol_v:
                        break
                    acc = _slip_rhs(self.p, u, d, y_r)[1]
                    if acc == 0.0:
                        break
                    t_new = min(max(t_e - y_r[1] / acc, t_a), t_end)
                    if t_new == t_e or t_new <= t_a:
                        break
                    t_e = t_new
        y_e[1] = 0.0
        self.n_events += 1
        return t_e, y_e, True

    # -- STUCK segment ------------------------------------------------------------------------
    def stuck_segment(self, t, t_end, y, u, blocked):
        """Advance STUCK from t; return (t_new, y_new, breakaway_direction or 0)."""
        p = self.p
        thr = p.Ts + p.tol_T
        c = p.r * (y[2] + p.F_ext) / p.eta
        if p.quasi_static:
            T = p.kt * u / p.R - c
            if abs(T) > thr and not blocked:
                return t, y, _sign(T)
            return t_end, y, 0.0
        i0 = y[3]
        T0 = p.kt * i0 - c
        if abs(T0) > thr and not blocked:
            return t, y, _sign(T0)
        tau = p.L / p.R
        i_inf = u / p.R
        T_inf = p.kt * i_inf - c
        if not blocked and abs(T_inf) > thr:
            d = _sign(T_inf)
            i_star = (d * thr + c) / p.kt
            ratio = (i0 - i_star) / (i_star - i_inf)  # >= 0: both factors have the sign -d
            s = tau * math.log1p(ratio)
            if t + s < t_end:
                y = y.copy()
                y[3] = i_star
                return t + s, y, d
        y = y.copy()
        y[3] = i0 + (i_inf - i0) * -math.expm1(-(t_end - t) / tau)
        return t_end, y, 0.0


def simulate_plant_scipy(
    params: dict,
    voltage_v,
    sample_period_s: float,
    *,
    method: str = "Radau",
    rtol: float = 1e-10,
    atol=None,
    initial=None,
    use_jacobian: bool = True,
    refine_events: bool = True,
) -> dict[str, np.ndarray]:
    """Simulate the hybrid stick/slip plant of docs/model.md with ``solve_ivp``.

    ``voltage_v[k]`` is held on ``[k*T, (k+1)*T)``.  Returns arrays at ``t_k = k*T``,
    k = 0..n: ``time_s``, ``position_m``, ``velocity_m_per_s``, ``dahl_force_n``,
    ``current_a``, ``stuck`` (bool), ``direction`` (int8: 0 stuck, +-1 slip), and counters
    ``n_rhs`` (right-hand-side evaluations), ``n_jac``, ``n_events`` (located v*d = 0
    events), ``n_breakaways``, ``n_segments`` (solve_ivp SLIP segments), ``n_zeno_guard``.
    See the module docstring for the conventions.
    """
    p = _plant_from_params(params)
    u_arr = np.asarray(voltage_v, dtype=float)
    if u_arr.ndim != 1:
        raise ValueError("voltage_v must be one-dimensional")
    if not np.all(np.isfinite(u_arr)):
        raise ValueError("voltage_v must be finite")
    T = float(sample_period_s)
    if not T > 0:
        raise ValueError("sample_period_s must be > 0")
    n = len(u_arr)
    dim = p.dim
    if atol is None:
        atol_arr = np.array(DEFAULT_ATOL[:dim])
    else:
        atol_arr = np.broadcast_to(np.asarray(atol, dtype=float), (dim,)).copy()

    init = {
        "position_m": 0.0,
        "velocity_m_per_s": 0.0,
        "dahl_force_n": 0.0,
        "current_a": 0.0,
        "stuck": True,
    }
    if initial is not None:
        unknown = set(initial) - set(init)
        if unknown:
            raise ValueError(f"unknown initial keys {sorted(unknown)}")
        init.update(initial)
        if "stuck" not in initial:
            init["stuck"] = float(init["velocity_m_per_s"]) == 0.0
    y = np.array(
        [init["position_m"], init["velocity_m_per_s"], init["dahl_force_n"], init["current_a"]],
        dtype=float,
    )[:dim]
    stuck = bool(init["stuck"])
    if stuck and y[1] != 0.0:
        raise ValueError("initial state is stuck but velocity is non-zero")
    d = 0.0 if stuck else _sign(y[1])

    sim = _Sim(p, method, rtol, atol_arr, use_jacobian, refine_events)

    out_x = np.empty(n + 1)
    out_v = np.empty(n + 1)
    out_z = np.empty(n + 1)
    out_i = np.empty(n + 1)
    out_stuck = np.empty(n + 1, dtype=bool)
    out_dir = np.empty(n + 1, dtype=np.int8)

    def record(k, u_for_current):
        out_x[k], out_v[k], out_z[k] = y[0], y[1], y[2]
        if p.quasi_static:
            out_i[k] = (u_for_current - p.ke * y[1] / p.r) / p.R
        else:
            out_i[k] = y[3]
        out_stuck[k] = stuck
        out_dir[k] = 0 if stuck else int(d)

    record(0, u_arr[0] if n else float(init["current_a"]) * p.R)

    zeno_dt = ZENO_DT_REL * T
    last_transition_t = -math.inf
    same_instant = 0

    for k in range(n):
        u = float(u_arr[k])
        t = k * T
        t_end = (k + 1) * T
        blocked = False
        if not stuck and y[1] * d <= 0.0:
            # At rest in SLIP at a sample instant (v*d = 0 event located exactly at t_k):
            # re-apply the rest rule with the new voltage.
            y[1] = 0.0
            stuck, d = sim.rest_rule(y, u)
        for _ in range(MAX_SEGMENTS_PER_INTERVAL):
            if t >= t_end:
                break
            if stuck:
                t_new, y, d_new = sim.stuck_segment(t, t_end, y, u, blocked)
                t = t_new
                if d_new == 0.0:
                    continue
                sim.n_breakaways += 1
                stuck, d = False, d_new
            else:
                t_new, y, evented = sim.slip_segment(t, t_end, y, u, d)
                t = t_new
                if not evented:
                    continue
                stuck, d = sim.rest_rule(y, u)
            # A mode transition happened at time t.
            if t - last_transition_t <= zeno_dt:
                same_instant += 1
            else:
                same_instant = 0
            last_transition_t = t
            if same_instant >= ZENO_MAX_TRANSITIONS:
                stuck, d = True, 0.0
                y[1] = 0.0
                blocked = True
                sim.n_zeno += 1
                same_instant = 0
        else:
            raise RuntimeError(f"too many mode switches in sample interval {k}")
        record(k + 1, u)

    return {
        "time_s": np.arange(n + 1) * T,
        "position_m": out_x,
        "velocity_m_per_s": out_v,
        "dahl_force_n": out_z,
        "current_a": out_i,
        "stuck": out_stuck,
        "direction": out_dir,
        "n_rhs": np.int64(sim.n_rhs),
        "n_jac": np.int64(sim.n_jac),
        "n_events": np.int64(sim.n_events),
        "n_breakaways": np.int64(sim.n_breakaways),
        "n_segments": np.int64(sim.n_segments),
        "n_zeno_guard": np.int64(sim.n_zeno),
    }
