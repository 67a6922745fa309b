"""A second truth family for the gap diagnosis, written independently of nanostage's models.

The seed axis is simulated here from the documents alone (docs/model.md, docs/controller.md),
with numpy and scipy only: nothing of nanostage's plant, friction, effect, simulation,
configuration or Rust core is imported (``nanostage.output`` writes the JSON file). What
differs from nanostage's own truth and candidates:

* **Integration.** scipy's ``solve_ivp`` (Radau, rtol 1e-9) over each control interval with
  the voltage held, split at the output update (latency) like the FPGA; no stick/slip mode
  switching: both friction laws are smooth state models.
* **Motor friction** is a LuGre bristle model (nanostage: a Stribeck map with true stiction),
  its damping fading with speed; **table friction** is an elasto-plastic law (Dupont et al.
  2002: a purely elastic region below a breakaway deflection, then a smooth transition to
  sliding; nanostage: Dahl).
* **Controller**: the fixed-point PID on integer encoder counts, re-implemented from
  docs/controller.md with Python integers (the seed formats copied as numbers).
* **Sensor**: encoder counts of the table position plus Gaussian noise before quantisation.
* **Nominal parameters** drawn off the seed preset (friction levels ±30 %, presliding
  stiffness ±30 %, table mass ±20 %, motor constants and inertia ±10–20 %) and a per-run
  friction level factor (lognormal), in every case, "none" included.
* **Hidden effects** from their physics (:data:`HIDDEN_EFFECTS`): backlash as a dead band
  closed by a Hertzian contact with Hunt-Crossley damping that can only push, amplifier
  dynamics as a first-order voltage lag, drive compliance as a two-mass chain (rotor and
  screw | table), an offset force, asymmetric friction (direction-dependent levels on both
  the motor and the table laws),
  dwell-dependent breakaway in Armstrong's form (the LuGre static level rises with the time
  at rest, counted per control interval), position-dependent table friction from
  random harmonics with a fine-pitch roughness term, a table friction falling with speed
  (``lugre``: the table law replaced by a LuGre law with a Stribeck drop) and a multi-element
  presliding (``presliding_gms``: a Maxwell-slip of elasto-plastic elements with that drop),
  and a pipelined controller (``computation_delay``: the output reaches the DAC one or two
  whole cycles late, after a longer computation latency).

:func:`write_case` writes a case folder like ``nanostage diagnose-benchmark``'s (a manifest,
CSV traces with ``command_v``, a ``truth.json`` naming the hidden effect and its
parameters), which ``nanostage diagnose`` reads.

Seed-preset numbers copied below come from the shipped seed model file
(``nanostage/model_files/seed.model.toml``, read by ``nanostage.presets.seed``, sources in
its provenance) and the Table 1 gains from ``nanostage.presets.table1_gains``; a test checks
the copies against the preset.
"""

from __future__ import annotations

import dataclasses as dc
import math
import multiprocessing
from collections import deque
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from fractions import Fraction
from pathlib import Path
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray
from scipy.integrate import solve_ivp

from ..output import write_json
from .case_manifest import UNCERTAIN_MOTOR_AND_INERTIA, case_manifest_head

__all__ = [
    "HIDDEN_EFFECTS",
    "MAX_RHS_PER_INTERVAL",
    "NOT_YET_WRITTEN",
    "SEED",
    "DesignedExperiment",
    "FixedPointPid",
    "IntegrationStalled",
    "Truth",
    "draw_truth",
    "experiment_design",
    "oracle_readings",
    "simulate_closed_loop",
    "simulate_open_loop",
    "write_case",
]

FloatArray = NDArray[np.float64]

#: Seed preset values (nanostage.presets.seed; SI units).
SEED: Final[dict[str, float]] = {
    "resistance_ohm": 3.4,
    "inductance_h": 7e-5,
    "torque_constant_nm_per_a": 6.6e-3,
    "back_emf_v_s_per_rad": 6.6e-3,
    "rotor_inertia_kg_m2": 1e-7,
    "static_torque_nm": 1.2e-4,
    "coulomb_torque_nm": 1e-4,
    "viscous_nm_s_per_rad": 2e-8,
    "stribeck_velocity_rad_per_s": 10.0,
    "gear_ratio": 19.0,
    "gear_efficiency": 0.8,
    "lead_m": 2e-3,
    "screw_efficiency": 0.9,
    "screw_inertia_kg_m2": 1e-7,
    "mass_kg": 0.5,
    "table_coulomb_force_n": 30.4,
    "table_stiffness_n_per_m": 7.5e7,
    "count_m": 1e-7,
    "amplifier_limit_v": 6.0,
    "sample_period_s": 1e-3,
    "latency_s": 130 / 40e6,
}

#: Table 1 gains (kp, ki, kd) per step size (nanostage.presets.table1_gains).
TABLE1_GAINS: Final[dict[float, tuple[float, float, float]]] = {
    100e-6: (450.0, 2.0, 40.0),
    500e-6: (450.0, 2.0, 40.0),
    1e-3: (450.0, 5.0, 10.0),
    10e-3: (450.0, 5.0, 25.0),
}

#: Hidden effects this family writes ("none": only the nominal mismatch).
HIDDEN_EFFECTS: Final[tuple[str, ...]] = (
    "none",
    "backlash",
    "amplifier_dynamics",
    "drive_compliance",
    "offset_force",
    "asymmetric_friction",
    "dwell_static_friction",
    "position_random_friction",
    "lugre",
    "presliding_gms",
    "computation_delay",
)

#: Hidden effects of the benchmark list not written in this family yet.
NOT_YET_WRITTEN: Final[tuple[str, ...]] = (
    "lead_periodic_friction",
    "frictional_memory",
)

#: Which diagnosed names count as finding each hidden effect. A table friction falling with
#: speed (``lugre``: a LuGre law with a Stribeck drop) is found by any of the friction laws
#: that carry a static excess over the Coulomb level (Stribeck, LuGre, GMS); a Maxwell-slip
#: presliding with a Stribeck drop (``presliding_gms``) by either presliding law that has
#: one (GMS, LuGre), as in the own family.
ACCEPT: Final[dict[str, frozenset[str]]] = {
    "position_random_friction": frozenset({"position_random_friction", "lead_periodic_friction"}),
    "lugre": frozenset({"lugre", "stribeck", "gms"}),
    "presliding_gms": frozenset({"gms", "lugre"}),
}

#: Right-hand-side evaluations allowed in one control interval before the integration is
#: declared stalled (a smooth interval takes tens to hundreds).
MAX_RHS_PER_INTERVAL: Final = 50_000


class IntegrationStalled(RuntimeError):
    """The truth's integrator made no headway in one control interval."""


# State indices; a Maxwell-slip table (``presliding_gms``) has its further elements' deflections
# after ``_UA``.
_X, _V, _TH, _W, _I, _ZM, _ZT, _UA = range(8)
_N_STATES = 8
#: Elements of the Maxwell-slip table law of ``presliding_gms``.
_N_SLIP_ELEMENTS = 4


@dc.dataclass(frozen=True)
class Truth:
    """One drawn truth: nominal parameters, the hidden effect and its parameters."""

    hidden: str
    p: dict[str, float]
    effect: dict[str, Any]
    seed: int

    @property
    def r(self) -> float:
        """Transmission, m of table per rad of motor."""
        return self.p["lead_m"] / (2.0 * math.pi * self.p["gear_ratio"])

    @property
    def eta(self) -> float:
        return self.p["gear_efficiency"] * self.p["screw_efficiency"]

    @property
    def rotor_side_inertia(self) -> float:
        """Rotating inertia at the motor shaft (rotor plus screw seen through the gear)."""
        return self.p["rotor_inertia_kg_m2"] + self.p["screw_inertia_kg_m2"] / (
            self.p["gear_ratio"] ** 2
        )

    @property
    def rigid(self) -> bool:
        return self.hidden not in ("backlash", "drive_compliance")


# --------------------------------------------------------------------------- drawing


def draw_truth(hidden: str, seed: int) -> Truth:
    """Nominal parameters off the seed preset and the hidden effect's parameters."""
    if hidden not in HIDDEN_EFFECTS:
        raise ValueError(f"unknown hidden effect {hidden!r}; valid: {', '.join(HIDDEN_EFFECTS)}")
    rng = np.random.default_rng(seed)

    def u(lo: float, hi: float) -> float:
        return float(rng.uniform(lo, hi))

    p = dict(SEED)
    p["coulomb_torque_nm"] *= u(0.7, 1.3)
    p["static_torque_nm"] = p["coulomb_torque_nm"] * u(1.1, 1.5)
    p["viscous_nm_s_per_rad"] *= u(0.7, 1.3)
    p["stribeck_velocity_rad_per_s"] *= u(0.5, 2.0)
    p["table_coulomb_force_n"] *= u(0.7, 1.3)
    p["table_stiffness_n_per_m"] *= u(0.7, 1.3)
    p["mass_kg"] *= u(0.8, 1.2)
    k = u(0.9, 1.1)
    p["torque_constant_nm_per_a"] *= k
    p["back_emf_v_s_per_rad"] *= k
    p["resistance_ohm"] *= u(0.9, 1.1)
    p["rotor_inertia_kg_m2"] *= u(0.8, 1.2)
    # LuGre bristles: the static torque is reached at a deflection of 0.5-2 mrad (8-34 nm
    # at the table); damping ratio 0.2-0.5 of the bristle mode with the whole axis.
    p["bristle_deflection_rad"] = u(0.5e-3, 2e-3)
    p["bristle_damping_ratio"] = u(0.2, 0.5)
    # Elasto-plastic table law: elastic up to 40-80 % of the sliding deflection.
    p["table_breakaway_ratio"] = u(0.4, 0.8)
    p["table_damping_ratio"] = u(0.05, 0.2)
    # Per-run friction level factor (lognormal, 3 %), and sensor noise.
    p["friction_run_spread"] = 0.03
    p["encoder_noise_m"] = u(3e-9, 8e-9)

    eff: dict[str, Any] = {}
    if hidden == "backlash":
        eff = {
            "width_m": u(5e-6, 30e-6),
            "contact_stiffness_n_per_m": u(1e7, 5e7),
            "contact_damping_n_s_per_m": u(200.0, 2000.0),
        }
    elif hidden == "amplifier_dynamics":
        eff = {"time_constant_s": u(0.1e-3, 0.5e-3)}
    elif hidden == "drive_compliance":
        eff = {
            "stiffness_n_per_m": u(1e7, 5e7),
            "damping_n_s_per_m": u(100.0, 1000.0),
        }
    elif hidden == "offset_force":
        eff = {"force_n": u(3.0, 10.0) * float(rng.choice([-1.0, 1.0]))}
    elif hidden == "asymmetric_friction":
        eff = {"asymmetry": u(0.15, 0.4) * float(rng.choice([-1.0, 1.0]))}
    elif hidden == "dwell_static_friction":
        eff = {"rise": u(1.5, 4.0), "time_constant_s": u(0.05, 0.5)}
    elif hidden == "position_random_friction":
        n = int(rng.integers(3, 7))
        wl = rng.uniform(0.3e-3, 5e-3, n)
        amp = rng.rayleigh(1.0, n)
        amp *= u(0.1, 0.25) / math.sqrt(0.5 * float(np.sum(amp**2)))
        # Fine-pitch roughness: many small harmonics of 20-100 µm wavelength.
        m = 20
        rough_wl = rng.uniform(20e-6, 100e-6, m)
        rough_amp = np.full(m, 0.02 / math.sqrt(0.5 * m))
        eff = {
            "wavelengths_m": [float(a) for a in np.concatenate([wl, rough_wl])],
            "amplitudes": [float(a) for a in np.concatenate([amp, rough_amp])],
            "phases_rad": [float(a) for a in rng.uniform(-math.pi, math.pi, n + m)],
        }
    elif hidden == "lugre":
        # The table's friction falls with speed: static level 1.3-2 times the Coulomb level,
        # over a Stribeck velocity of 0.1-1 mm/s.
        eff = {"static_ratio": u(1.3, 2.0), "stribeck_velocity_m_per_s": u(1e-4, 1e-3)}
    elif hidden == "presliding_gms":
        # Maxwell-slip elements: stiffness shares falling geometrically, slip-force shares
        # rising, so the elements' breakaway deflections spread over one to two decades and
        # the presliding curve bends gradually; the total stiffness 0.5-2 times the table's.
        ratio = u(0.3, 0.6)
        shares = np.array([ratio**i for i in range(_N_SLIP_ELEMENTS)])
        weights = np.arange(1.0, _N_SLIP_ELEMENTS + 1.0)
        k_total = u(0.5, 2.0) * p["table_stiffness_n_per_m"]
        eff = {
            "stiffnesses_n_per_m": [float(k) for k in k_total * shares / shares.sum()],
            "weights": [float(w) for w in weights / weights.sum()],
            "static_ratio": u(1.3, 1.8),
            "stribeck_velocity_m_per_s": u(2e-4, 2e-3),
        }
    elif hidden == "computation_delay":
        # A pipelined loop: the output computed at a sample reaches the DAC one or two
        # whole control cycles later, and after a longer computation latency (up to a
        # quarter of a cycle more than the preset's 3.25 µs).
        eff = {
            "pipeline_cycles": int(rng.integers(1, 3)),
            "extra_latency_s": u(0.0, 0.25) * p["sample_period_s"],
        }
    return Truth(hidden=hidden, p=p, effect=eff, seed=seed)


# --------------------------------------------------------------------------- the plant


@dc.dataclass
class _Run:
    """Per-run values: the truth, the friction level factor and the dwell state."""

    truth: Truth
    level: float
    dwell_s: float = 0.0

    def __post_init__(self) -> None:
        t = self.truth
        p = t.p
        self.r = t.r
        self.eta = t.eta
        self.j1 = t.rotor_side_inertia
        self.m_eq = p["mass_kg"] + self.eta * self.j1 / self.r**2
        self.sigma0_m = p["static_torque_nm"] / p["bristle_deflection_rad"]
        j_tot = self.m_eq * self.r**2 / self.eta
        self.sigma1_m = 2.0 * p["bristle_damping_ratio"] * math.sqrt(self.sigma0_m * j_tot)
        self.sigma0_t = p["table_stiffness_n_per_m"]
        self.sigma1_t = 2.0 * p["table_damping_ratio"] * math.sqrt(self.sigma0_t * self.m_eq)
        self.asym = (
            float(t.effect.get("asymmetry", 0.0)) if t.hidden == "asymmetric_friction" else 0.0
        )
        self.n_states = _N_STATES
        if t.hidden == "presliding_gms":
            self.slip_k = np.asarray(t.effect["stiffnesses_n_per_m"])
            self.slip_w = np.asarray(t.effect["weights"])
            # Each element's damper in proportion to its stiffness (the whole: σ1 of the
            # table's single-element law at the same total stiffness ratio).
            self.slip_c = self.sigma1_t * self.slip_k / self.sigma0_t
            self.n_states = _N_STATES + _N_SLIP_ELEMENTS - 1
        if t.hidden == "backlash":
            # Depth at which the Hertzian contact carries the table's sliding load with the
            # drawn tangent stiffness (dF/dδ = 1.5 F/δ).
            self.contact_ref_depth_m = (
                1.5 * p["table_coulomb_force_n"] / t.effect["contact_stiffness_n_per_m"]
            )
        if t.hidden == "position_random_friction":
            self.mod_k = 2.0 * math.pi / np.asarray(t.effect["wavelengths_m"])
            self.mod_a = np.asarray(t.effect["amplitudes"])
            self.mod_ph = np.asarray(t.effect["phases_rad"])
        self.active = self.active_states()
        self.active_atol = self.atol()[self.active]

    def motor_levels(self, w: float) -> tuple[float, float]:
        """(static, Coulomb) torque of the LuGre law for the direction of ``w``."""
        p = self.truth.p
        f = self.level * (1.0 + self.asym * (1.0 if w >= 0.0 else -1.0))
        ts = p["static_torque_nm"]
        if self.truth.hidden == "dwell_static_friction":
            e = self.truth.effect
            ts += e["rise"] * ts * self.dwell_s / (self.dwell_s + e["time_constant_s"])
        return f * ts, f * p["coulomb_torque_nm"]

    def table_level(self, x: float, v: float) -> float:
        """Sliding friction force of the table law at position ``x``, direction of ``v``."""
        f = self.level * (1.0 + self.asym * (1.0 if v >= 0.0 else -1.0))
        if self.truth.hidden == "position_random_friction":
            f *= 1.0 + float(np.sum(self.mod_a * np.cos(self.mod_k * x + self.mod_ph)))
        return f * self.truth.p["table_coulomb_force_n"]

    def lugre(self, w: float, z: float) -> tuple[float, float]:
        """Motor friction torque and the bristle rate."""
        ts, tc = self.motor_levels(w)
        ws = self.truth.p["stribeck_velocity_rad_per_s"]
        s = math.exp(-((w / ws) ** 2))
        g = tc + (ts - tc) * s
        dz = w - self.sigma0_m * abs(w) * z / g
        torque = (
            self.sigma0_m * z + self.sigma1_m * s * dz + self.truth.p["viscous_nm_s_per_rad"] * w
        )
        return torque, dz

    def stribeck_factor(self, v: float) -> float:
        """The sliding level over the Coulomb level at speed ``v``: 1 + (r − 1)·exp(−(v/vₛ)²)
        for a friction falling with speed (``lugre``, ``presliding_gms``), else 1."""
        e = self.truth.effect
        if self.truth.hidden not in ("lugre", "presliding_gms"):
            return 1.0
        s = math.exp(-((v / e["stribeck_velocity_m_per_s"]) ** 2))
        return 1.0 + (float(e["static_ratio"]) - 1.0) * s

    def table_friction(self, y: FloatArray, dy: FloatArray) -> float:
        """Table friction force; writes the friction states' rates into ``dy``."""
        x, v = y[_X], y[_V]
        if self.truth.hidden == "lugre":
            f, dy[_ZT] = self.lugre_table(x, v, y[_ZT])
            return f
        if self.truth.hidden == "presliding_gms":
            level = self.table_level(x, v) * self.stribeck_factor(v)
            idx = [_ZT, *range(_N_STATES, self.n_states)]
            total = 0.0
            for i, k in enumerate(idx):
                f_i, dy[k] = self.elasto_plastic_element(
                    v, y[k], self.slip_w[i] * level, self.slip_k[i], self.slip_c[i]
                )
                total += f_i
            return total
        f, dy[_ZT] = self.elasto_plastic(x, v, y[_ZT])
        return f

    def lugre_table(self, x: float, v: float, z: float) -> tuple[float, float]:
        """Table friction force and the bristle rate of a LuGre law (Canudas de Wit et al.
        1995) with a Stribeck drop; the bristles are the table's presliding stiffness and
        damping, the damping fading with speed as in the motor's law."""
        e = self.truth.effect
        g = self.table_level(x, v) * self.stribeck_factor(v)
        dz = v - self.sigma0_t * abs(v) * z / g
        s = math.exp(-((v / e["stribeck_velocity_m_per_s"]) ** 2))
        return self.sigma0_t * z + self.sigma1_t * s * dz, dz

    def elasto_plastic(self, x: float, v: float, z: float) -> tuple[float, float]:
        """Table friction force and the deflection rate (Dupont's elasto-plastic law)."""
        return self.elasto_plastic_element(
            v, z, self.table_level(x, v), self.sigma0_t, self.sigma1_t
        )

    def elasto_plastic_element(
        self, v: float, z: float, level: float, k: float, c: float
    ) -> tuple[float, float]:
        """Force and deflection rate of one elasto-plastic element (Dupont et al. 2002) of
        stiffness ``k``, damping ``c`` and sliding force ``level``."""
        z_ss = level / k
        z_ba = self.truth.p["table_breakaway_ratio"] * z_ss
        a = 0.0
        if v * z > 0.0:
            az = abs(z)
            if az >= z_ss:
                a = 1.0
            elif az > z_ba:
                a = 0.5 + 0.5 * math.sin(math.pi * (az - 0.5 * (z_ss + z_ba)) / (z_ss - z_ba))
        dz = v * (1.0 - a * abs(z) / z_ss)
        return k * z + c * dz, dz

    def link_force(self, y: FloatArray) -> float:
        """Force of the drive train on the table (two-mass chains)."""
        e = self.truth.effect
        d = self.r * y[_TH] - y[_X]
        dd = self.r * y[_W] - y[_V]
        if self.truth.hidden == "drive_compliance":
            return float(e["stiffness_n_per_m"] * d + e["damping_n_s_per_m"] * dd)
        half = 0.5 * e["width_m"]
        if abs(d) <= half:
            return 0.0
        # Hertzian flank contact (balls on the raceway: force ∝ depth^1.5) with Hunt-Crossley
        # damping (∝ depth^1.5 · rate), scaled so that at the table's sliding load the
        # contact's tangent stiffness and damping are the drawn ones. Force and stiffness
        # are zero at touch-down (no jump for the integrator), and the contact only pushes.
        s = math.copysign(1.0, d)
        depth = abs(d) - half
        ref = self.contact_ref_depth_m
        shape = (depth / ref) ** 1.5
        f_ref = self.truth.p["table_coulomb_force_n"]
        push = f_ref * shape + e["contact_damping_n_s_per_m"] * shape * s * dd
        return s * push if push > 0.0 else 0.0

    def rhs(self, u_cmd: float, y: FloatArray) -> FloatArray:
        t = self.truth
        p = t.p
        dy = np.zeros(self.n_states)
        if t.hidden == "amplifier_dynamics":
            u = y[_UA]
            dy[_UA] = (u_cmd - u) / t.effect["time_constant_s"]
        else:
            u = u_cmd
        w = y[_W] if not t.rigid else y[_V] / self.r
        kt = p["torque_constant_nm_per_a"]
        dy[_I] = (u - p["resistance_ohm"] * y[_I] - p["back_emf_v_s_per_rad"] * w) / p[
            "inductance_h"
        ]
        tm, dy[_ZM] = self.lugre(w, y[_ZM])
        ft = self.table_friction(y, dy)
        f_off = float(t.effect["force_n"]) if t.hidden == "offset_force" else 0.0
        dy[_X] = y[_V]
        if t.rigid:
            acc = (self.eta / self.r * (kt * y[_I] - tm) - ft - f_off) / self.m_eq
            # The rotor's angle and speed follow the table's (not integrated: advance).
            dy[_V] = acc
        else:
            fl = self.link_force(y)
            dy[_V] = (fl - ft - f_off) / p["mass_kg"]
            dy[_TH] = y[_W]
            dy[_W] = (kt * y[_I] - tm - self.r * fl / self.eta) / self.j1
        return dy

    def atol(self) -> FloatArray:
        a = np.full(self.n_states, 1e-13)
        a[_X], a[_V] = 1e-13, 1e-10
        a[_TH], a[_W] = 1e-13 / self.r, 1e-10 / self.r
        a[_I] = 1e-8
        a[_ZM] = 1e-13 / self.r
        a[_ZT] = 1e-13
        a[_UA] = 1e-8
        return a

    def active_states(self) -> NDArray[np.intp]:
        """The states the integrator carries: the amplifier's only with a voltage lag, the
        rotor's angle and speed only in a two-mass chain (rigid, they follow the table's).
        A state the right-hand side never reads would leave its Jacobian column zero, whose
        finite-difference step scipy then grows without bound."""
        drop = set() if self.truth.hidden == "amplifier_dynamics" else {_UA}
        if self.truth.rigid:
            drop |= {_TH, _W}
        return np.array([i for i in range(self.n_states) if i not in drop], dtype=np.intp)

    def advance(self, y: FloatArray, u_cmd: float, dt: float) -> FloatArray:
        """The state after ``dt`` s at the voltage ``u_cmd`` (Radau, rtol 1e-9). An interval
        where Radau makes no headway (over :data:`MAX_RHS_PER_INTERVAL` evaluations: its
        Newton iterations kept failing, as while a rotor at full voltage crosses a
        backlash's dead band) is integrated again from its start by LSODA at the same
        tolerances; :class:`IntegrationStalled` is raised when that stalls too."""
        try:
            return self._advance(y, u_cmd, dt, "Radau")
        except IntegrationStalled:
            return self._advance(y, u_cmd, dt, "LSODA")

    def _advance(self, y: FloatArray, u_cmd: float, dt: float, method: str) -> FloatArray:
        act = self.active
        full = np.array(y, dtype=np.float64)
        calls = 0

        def f(_t: float, s: FloatArray) -> FloatArray:
            nonlocal calls
            calls += 1
            if calls > MAX_RHS_PER_INTERVAL:
                raise IntegrationStalled(
                    f"the truth's integration stalled: over {MAX_RHS_PER_INTERVAL} "
                    f"right-hand-side evaluations ({method}) in one {dt:.3g} s interval at "
                    f"table position {y[_X]:.9g} m, speed {y[_V]:.3g} m/s, "
                    f"voltage {u_cmd:.4g} V"
                )
            z = full.copy()
            z[act] = s
            out: FloatArray = self.rhs(u_cmd, z)[act]
            return out

        sol = solve_ivp(
            f,
            (0.0, dt),
            full[act],
            method=method,
            rtol=1e-9,
            atol=self.active_atol,
            first_step=min(dt, 1e-6),
        )
        if not sol.success:
            raise IntegrationStalled(
                f"the truth's integration failed ({method}: {sol.message}) in a {dt:.3g} s "
                f"interval at table position {y[_X]:.9g} m, voltage {u_cmd:.4g} V"
            )
        out = full.copy()
        out[act] = sol.y[:, -1]
        if self.truth.rigid:
            out[_TH] = y[_TH] + (out[_X] - y[_X]) / self.r
            out[_W] = out[_V] / self.r
        return out


def _flank(truth: Truth, rng: np.random.Generator) -> float:
    """The flank a backlash rests against when a run starts (the side of the last move,
    drawn: ±1), 0 without a backlash (nothing drawn)."""
    return float(rng.choice([-1.0, 1.0])) if truth.hidden == "backlash" else 0.0


def _initial_state(run: _Run, x0: float, flank: float) -> FloatArray:
    y = np.zeros(run.n_states)
    y[_X] = x0
    d0 = 0.5 * run.truth.effect["width_m"] * flank if run.truth.hidden == "backlash" else 0.0
    y[_TH] = (x0 + d0) / run.r
    return y


# --------------------------------------------------------------------------- the controller

#: (signed, word_bits, int_bits, rounding, overflow) of the seed FPGA loop.
Fmt = tuple[bool, int, int, str, str]
SEED_FORMATS: Final[dict[str, Fmt]] = {
    "gain": (True, 24, 16, "half_even", "saturate"),
    "measurement": (True, 32, 32, "half_even", "wrap"),
    "error": (True, 32, 32, "half_even", "saturate"),
    "term": (True, 48, 40, "half_even", "saturate"),
    "integrator": (True, 48, 40, "half_even", "saturate"),
    "output": (True, 32, 24, "half_even", "saturate"),
    "dac": (True, 16, 16, "half_even", "saturate"),
    "dac_scale": (False, 16, 0, "half_even", "saturate"),
}
OUTPUT_UNIT_V: Final = 1e-4
DAC_LSB_V: Final = 20.0 / 65536
OUTPUT_LIMIT: Final = 60000.0


def _requant(raw: int, f_in: int, fmt: Fmt) -> int:
    """``raw * 2**-f_in`` in ``fmt`` (round, then handle overflow)."""
    signed, word, ib, rounding, overflow = fmt
    f = word - ib
    if f >= f_in:
        out = raw << (f - f_in)
    else:
        s = f_in - f
        q = raw >> s
        rem = raw - (q << s)
        half = 1 << (s - 1)
        if rounding == "truncate":
            out = q
        elif rounding == "half_up":
            out = q + (rem >= half)
        else:
            out = q + (rem > half or (rem == half and q & 1 == 1))
    lo, hi = (-(1 << (word - 1)), (1 << (word - 1)) - 1) if signed else (0, (1 << word) - 1)
    if lo <= out <= hi:
        return out
    if overflow == "saturate":
        return lo if out < lo else hi
    out &= (1 << word) - 1
    if signed and out > hi:
        out -= 1 << word
    return out


def _frac(fmt: Fmt) -> int:
    return fmt[1] - fmt[2]


def _host_quantise(value: float, fmt: Fmt) -> int:
    """A host constant in ``fmt``: nearest raw value, ties to even."""
    return round(Fraction(value) * Fraction(2) ** _frac(fmt))


class FixedPointPid:
    """The FPGA PID (docs/controller.md) on integer counts, conditional anti-windup."""

    def __init__(self, kp: float, ki: float, kd: float, formats: dict[str, Fmt] | None = None):
        self.f = dict(formats or SEED_FORMATS)
        g = self.f["gain"]
        self.kp, self.ki, self.kd = (_host_quantise(k, g) for k in (kp, ki, kd))
        self.out_max = _host_quantise(OUTPUT_LIMIT, self.f["output"])
        self.out_min = _host_quantise(-OUTPUT_LIMIT, self.f["output"])
        self.scale = _host_quantise(OUTPUT_UNIT_V / DAC_LSB_V, self.f["dac_scale"])
        self.acc = 0
        self.y_prev: int | None = None

    def step(self, r: int, y_counts: int) -> tuple[int, int]:
        """One sample: returns (output raw in the output format, DAC code)."""
        fm = self.f
        fy, fe, fg = _frac(fm["measurement"]), _frac(fm["error"]), _frac(fm["gain"])
        ft, fi, fo = _frac(fm["term"]), _frac(fm["integrator"]), _frac(fm["output"])
        y = _requant(y_counts, 0, fm["measurement"])
        if self.y_prev is None:
            self.y_prev = y
        fd = max(0, fy)
        e = _requant((r << fd) - (y << (fd - fy)), fd, fm["error"])
        dy = _requant(y - self.y_prev, fy, fm["error"])
        fp = fg + fe
        p = _requant(self.kp * e, fp, fm["term"])
        d = _requant(-(self.kd * dy), fp, fm["term"])
        inc = self.ki * e
        fa = max(fi, fp)
        cand = _requant((self.acc << (fa - fi)) + (inc << (fa - fp)), fa, fm["integrator"])
        fs = max(ft, fi, fo)
        total = (p << (fs - ft)) + (cand << (fs - fi)) + (d << (fs - ft))
        above = total > self.out_max << (fs - fo)
        below = total < self.out_min << (fs - fo)
        if not ((above and inc > 0) or (below and inc < 0)):
            self.acc = cand
        fs2 = max(ft, fi)
        s = (p << (fs2 - ft)) + (self.acc << (fs2 - fi)) + (d << (fs2 - ft))
        u = min(max(_requant(s, fs2, fm["output"]), self.out_min), self.out_max)
        code = _requant(u * self.scale, fo + _frac(fm["dac_scale"]), fm["dac"])
        self.y_prev = y
        return u, code


# --------------------------------------------------------------------------- simulation


@dc.dataclass(frozen=True)
class DesignedExperiment:
    """A designed experiment: reference per sample, the PID gains and the role."""

    name: str
    reference_m: FloatArray
    gains: tuple[float, float, float]
    role: str


def _gains(step_m: float) -> tuple[float, float, float]:
    best = min(TABLE1_GAINS, key=lambda s: abs(math.log(s / abs(step_m))))
    return TABLE1_GAINS[best]


def simulate_closed_loop(
    truth: Truth,
    reference_m: FloatArray,
    gains: tuple[float, float, float],
    seed: int,
    *,
    deterministic: bool = False,
    without_hidden: bool = False,
) -> dict[str, FloatArray]:
    """Run the closed loop on ``reference_m`` (one value per sample); returns ``time_s``,
    ``position_m`` (the encoder reading), ``command_v`` (controller output at the amplifier
    input), ``true_position_m`` and ``motor_position_m`` (r·θ).

    ``deterministic``: the truth's own deterministic model, from the same start (the
    position within the first count and a backlash's flank, drawn from ``seed`` as in the
    run): no encoder noise, and the run's friction level at its median (1). What a model of
    the truth's form with the truth's parameters predicts; the gap it leaves to the
    recorded run is the ceiling of any diagnosis. ``without_hidden``: the plant without its
    hidden effect (the nominal truth), from the same draws (a backlash's flank is drawn all
    the same), so that the difference from the run with it is the effect's footprint."""
    p = truth.p
    rng = np.random.default_rng(seed)
    level = float(rng.lognormal(0.0, p["friction_run_spread"]))
    plant = dc.replace(truth, hidden="none", effect={}) if without_hidden else truth
    run = _Run(plant, level=1.0 if deterministic else level)
    q, ts, lat = p["count_m"], p["sample_period_s"], p["latency_s"]
    # The axis rests in the middle half of the reference's first count.
    x0 = (math.floor(reference_m[0] / q) + float(rng.uniform(0.25, 0.75))) * q
    y = _initial_state(run, x0, _flank(truth, rng))
    noise_m = 0.0 if deterministic else p["encoder_noise_m"]
    pid = FixedPointPid(*gains)
    n = len(reference_m)
    pos, cmd, xt, xm = (np.empty(n) for _ in range(4))
    u_held = 0.0
    vmax = p["amplifier_limit_v"]
    # A pipelined loop (``computation_delay``): outputs wait in a queue of whole cycles.
    pipeline: deque[float] = deque()
    if plant.hidden == "computation_delay":
        pipeline.extend([0.0] * int(plant.effect["pipeline_cycles"]))
        lat += float(plant.effect["extra_latency_s"])
    for k in range(n):
        counts = math.floor((y[_X] + (rng.normal(0.0, noise_m) if noise_m else 0.0)) / q)
        r_counts = round(float(reference_m[k]) / q)
        out, code = pid.step(r_counts, counts)
        pos[k], cmd[k] = counts * q, out / (1 << _frac(pid.f["output"])) * OUTPUT_UNIT_V
        xt[k], xm[k] = y[_X], run.r * y[_TH]
        u_new = min(max(code * DAC_LSB_V, -vmax), vmax)
        if pipeline:
            pipeline.append(u_new)
            u_new = pipeline.popleft()
        th0 = y[_TH]
        if u_new == u_held:
            y = run.advance(y, u_held, ts)
        else:
            y = run.advance(y, u_held, lat)
            y = run.advance(y, u_new, ts - lat)
        u_held = u_new
        # Dwell clock: time at rest (motor turned less than a bristle deflection).
        still = abs(y[_TH] - th0) < p["bristle_deflection_rad"]
        run.dwell_s = run.dwell_s + ts if still else 0.0
    return {
        "time_s": np.arange(n, dtype=np.float64) * ts,
        "position_m": pos,
        "command_v": cmd,
        "true_position_m": xt,
        "motor_position_m": xm,
    }


def simulate_open_loop(
    truth: Truth, voltage_v: FloatArray, *, level: float = 1.0, x0_m: float = 0.0
) -> dict[str, FloatArray]:
    """Drive the plant with a voltage per sample (no controller, no noise, the given
    friction level factor); returns time, table and motor positions (m) and velocities."""
    run = _Run(truth, level=level)
    y = _initial_state(run, x0_m, _flank(truth, np.random.default_rng(truth.seed)))
    ts = truth.p["sample_period_s"]
    n = len(voltage_v)
    x, xm, v, vm = (np.empty(n + 1) for _ in range(4))
    for k in range(n + 1):
        x[k], xm[k], v[k] = y[_X], run.r * y[_TH], y[_V]
        vm[k] = run.r * (y[_W] if not truth.rigid else y[_V] / run.r)
        if k < n:
            th0 = y[_TH]
            y = run.advance(y, float(voltage_v[k]), ts)
            still = abs(y[_TH] - th0) < truth.p["bristle_deflection_rad"]
            run.dwell_s = run.dwell_s + ts if still else 0.0
    return {
        "time_s": np.arange(n + 1, dtype=np.float64) * ts,
        "position_m": x,
        "motor_position_m": xm,
        "velocity_m_per_s": v,
        "motor_velocity_m_per_s": vm,
    }


# --------------------------------------------------------------------------- design


def experiment_design(
    count: int = 12,
    *,
    move_s: float = 0.3,
    dwells_s: Sequence[float] = (0.05, 0.3, 1.5),
    ramp_speeds_m_per_s: Sequence[float] = (20e-6, 200e-6, 1e-3),
    ramp_length_m: float = 50e-6,
    micro_step_counts: int = 3,
    sample_period_s: float = 1e-3,
    start_m: float = 2e-3,
) -> list[DesignedExperiment]:
    """``count`` experiments cycling through steps (100 µm, 500 µm, 1 mm), micro-steps of
    ``micro_step_counts`` counts after each dwell, slow ramps out and back at each speed
    (a reversal), and step reversals; directions alternate, every third experiment
    validates. Each starts at its own position, ``move_s`` after the last move."""
    if count < 1:
        raise ValueError(f"count = {count} is invalid: expected at least 1")
    q = SEED["count_m"]
    mid = 0.3 * q

    def hold(x: float, s: float) -> FloatArray:
        return np.full(max(1, round(s / sample_period_s)), x)

    kinds: list[tuple[str, Any]] = []
    for s in (100e-6, 500e-6, 1e-3):
        kinds.append(("step", s))
    for d in dwells_s:
        kinds.append(("micro", d))
    for v in ramp_speeds_m_per_s:
        kinds.append(("ramp", v))
    kinds.append(("reversal", 200e-6))
    kinds.append(("reversal", 50e-6))
    kinds.append(("micro", dwells_s[-1] if dwells_s else move_s))
    out = []
    for i in range(count):
        kind, a = kinds[i % len(kinds)]
        sign = 1.0 if (i // len(kinds) + i) % 2 == 0 else -1.0
        x0 = start_m + (i % 20) * 2.2e-3 + mid
        g: tuple[float, float, float]
        if kind == "step":
            ref = np.concatenate([hold(x0, 0.02), hold(x0 + sign * a, move_s)])
            g = _gains(a)
        elif kind == "micro":
            ref = np.concatenate([hold(x0, a), hold(x0 + sign * micro_step_counts * q, move_s)])
            g = TABLE1_GAINS[100e-6]
        elif kind == "ramp":
            n = max(2, round(ramp_length_m / a / sample_period_s))
            up = x0 + sign * a * sample_period_s * np.arange(1, n + 1)
            down = up[-1] - sign * a * sample_period_s * np.arange(1, n + 1)
            ref = np.concatenate([hold(x0, 0.02), up, hold(up[-1], 0.05), down, hold(x0, move_s)])
            g = TABLE1_GAINS[100e-6]
        else:
            ref = np.concatenate([hold(x0, 0.02), hold(x0 + sign * a, move_s), hold(x0, move_s)])
            g = _gains(a)
        role = "validate" if i % 3 == 2 else "train"
        out.append(DesignedExperiment(f"exp{i:02d}_{kind}", ref, g, role))
    return out


# --------------------------------------------------------------------------- writing


def write_case(
    hidden: str,
    seed: int,
    out_dir: str | Path,
    *,
    design: Sequence[DesignedExperiment] | None = None,
    workers: int = 1,
    level_scatter: float | None = None,
) -> tuple[Path, dict[str, Any]]:
    """Draw a truth, simulate the design and write ``manifest.toml``, one CSV trace per
    experiment (``time_s, reference_m, position_m, command_v``) and ``truth.json`` into
    ``out_dir``; returns the manifest path and the truth record. ``level_scatter``: the
    manifest's ``[diagnosis]`` setting (0: left out; None: not written, the diagnosis's
    default applies).

    ``workers`` > 1 simulates the experiments in that many spawned processes (each
    experiment has its own random stream, so the files are the same to the last bit)."""
    _check_workers(workers)
    truth = draw_truth(hidden, seed)
    exps = list(design) if design is not None else experiment_design()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fc0 = SEED["table_coulomb_force_n"]
    ts0, tc0 = SEED["static_torque_nm"], SEED["coulomb_torque_nm"]
    # The manifest frees what this family draws off the preset (a user frees what the
    # datasheet does not pin down): the friction levels, and the motor constants, inertia,
    # viscous friction, Stribeck velocity and presliding stiffness.
    seed_key = {
        "plant.motor.torque_constant_nm_per_a": "torque_constant_nm_per_a",
        "plant.motor.resistance_ohm": "resistance_ohm",
        "plant.motor.rotor_inertia_kg_m2": "rotor_inertia_kg_m2",
        "plant.motor_friction.viscous_nm_s_per_rad": "viscous_nm_s_per_rad",
        "plant.motor_friction.stribeck_velocity_rad_per_s": "stribeck_velocity_rad_per_s",
        "plant.dahl.stiffness_n_per_m": "table_stiffness_n_per_m",
    }
    also = {
        path: (SEED[seed_key[path]], lo, hi)
        for path, (lo, hi) in UNCERTAIN_MOTOR_AND_INERTIA.items()
    }
    lines = case_manifest_head(fc0, ts0, tc0, seed, also_free=also, level_scatter=level_scatter)
    jobs = [
        (truth, e.reference_m, e.gains, seed * 1000 + i, False, False) for i, e in enumerate(exps)
    ]
    traces = _simulate_jobs(jobs, workers)
    for e, tr in zip(exps, traces, strict=True):
        data = np.column_stack([tr["time_s"], e.reference_m, tr["position_m"], tr["command_v"]])
        np.savetxt(
            out / f"{e.name}.csv",
            data,
            fmt="%.17g",
            delimiter=",",
            header="time_s,reference_m,position_m,command_v",
            comments="",
        )
        kp, ki, kd = e.gains
        lines += [
            "[[experiment]]",
            f'name = "{e.name}"',
            f'file = "{e.name}.csv"',
            f'role = "{e.role}"',
            f"controller = {{ kp = {kp}, ki = {ki}, kd = {kd} }}",
            "",
        ]
    manifest = out / "manifest.toml"
    manifest.write_text("\n".join(lines), encoding="utf-8")
    info = {
        "family": "independent",
        "hidden": hidden,
        "parameters": truth.effect,
        "nominal": truth.p,
        "seed": seed,
    }
    write_json(info, out / "truth.json", indent=1)
    return manifest, info


def _check_workers(workers: int) -> None:
    if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= 256:
        raise ValueError(f"workers = {workers!r} is invalid: expected an integer in [1, 256]")


#: One run of :func:`simulate_closed_loop`: ``(truth, reference_m, gains, seed,
#: deterministic, without_hidden)``.
_Job = tuple[Truth, FloatArray, tuple[float, float, float], int, bool, bool]


def _closed_loop_job(job: _Job) -> dict[str, FloatArray]:
    truth, reference_m, gains, seed, deterministic, without_hidden = job
    try:
        return simulate_closed_loop(
            truth,
            reference_m,
            gains,
            seed,
            deterministic=deterministic,
            without_hidden=without_hidden,
        )
    except IntegrationStalled as e:
        raise IntegrationStalled(
            f"hidden {truth.hidden!r}, case seed {truth.seed}, experiment {seed % 1000}: {e}"
        ) from e


def _simulate_jobs(jobs: Sequence[_Job], workers: int) -> list[dict[str, FloatArray]]:
    """:func:`simulate_closed_loop` of each job (:data:`_Job`), in ``workers`` spawned
    processes when more than one (each run has its own random stream: the same results to
    the last bit)."""
    if workers > 1 and len(jobs) > 1:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=ctx) as pool:
            return list(pool.map(_closed_loop_job, jobs))
    return [_closed_loop_job(job) for job in jobs]


def oracle_readings(
    hidden: str,
    seed: int,
    names: Sequence[str],
    *,
    design: Sequence[DesignedExperiment] | None = None,
    without_hidden: bool = False,
    workers: int = 1,
) -> dict[str, FloatArray]:
    """The mean readings (true table position − half a count, as the diagnosis simulates
    them) of the case :func:`write_case` writes for ``hidden`` and ``seed``, by the truth's
    own deterministic model (:func:`simulate_closed_loop` with ``deterministic``), for the
    experiments ``names`` of the design: the model no diagnosis can beat but by fitting
    noise. ``without_hidden``: the same without the hidden effect. By experiment name."""
    _check_workers(workers)
    truth = draw_truth(hidden, seed)
    exps = list(design) if design is not None else experiment_design()
    unknown = sorted(set(names) - {e.name for e in exps})
    if unknown:
        raise ValueError(
            f"names {', '.join(map(repr, unknown))} are not experiments of the design "
            f"({', '.join(e.name for e in exps)})"
        )
    chosen = [(i, e) for i, e in enumerate(exps) if e.name in set(names)]
    jobs = [
        (truth, e.reference_m, e.gains, seed * 1000 + i, True, without_hidden) for i, e in chosen
    ]
    q = truth.p["count_m"]
    return {
        e.name: tr["true_position_m"] - 0.5 * q
        for (_, e), tr in zip(chosen, _simulate_jobs(jobs, workers), strict=True)
    }
