//! The component plant as a hybrid ODE: a chain of 1–3 masses with links (spring, damper,
//! dead band), a DC motor or force drive, optional amplifier dynamics, static friction maps
//! with true stiction per mass, and a dynamic friction model (Dahl, LuGre, GMS) on the
//! table. The state layout is built from the components; the Jacobian is analytic
//! ([`Drive::jacobian`], checked against forward differences in the tests), an arrowhead
//! (hub: the velocity) for one mass without amplifier state. Tolerances follow the rigid
//! plant's scales ([`Drive::new`]), and a stuck phase (every mass stuck) is solved in closed
//! form, as in the rigid plant: with every effect off the component plant takes the rigid
//! plant's steps.
use super::component_params::{
    Actuator, Amplifier, DriveParams, Modulation, StaticMap, TableFriction,
};
use super::friction::{
    direction_factor, modulation, sliding_direction, smoothstep, GMS_ELASTIC_FRACTION,
};
use super::hybrid::{self, HybridPlant, StuckPhase};
use crate::error::{ConfigError, SimError};
use crate::integrate::{IntegratorOptions, OdeSystem, Rodas4, SegmentEnd, Stats};
use nalgebra::{Const, DimMin, SMatrix, SVector};

/// Most masses in the chain.
pub const MAX_MASSES: usize = 3;

/// Inputs held constant over one segment.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Inputs {
    /// Command voltage (DC motor: motor terminal voltage; force drive: drive command), V.
    pub u_v: f64,
    /// Known force disturbance on the table, N, positive along +x.
    pub force_n: f64,
    /// Multiplier of every friction level (stochastic within-trial fluctuation), > 0.
    pub friction_scale: f64,
}

impl Inputs {
    /// A voltage with no disturbance and nominal friction.
    pub fn voltage(u_v: f64) -> Self {
        Self {
            u_v,
            force_n: 0.0,
            friction_scale: 1.0,
        }
    }
}

/// The discrete mode of one mass.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum MassMode {
    /// No static friction map on this mass: it always moves freely.
    Free,
    /// Held by static friction: v = 0 exactly.
    Stuck,
    /// Slipping in direction ±1 (replaces sgn v in the friction laws).
    Slip(f64),
}

/// Validated parameters and the derived layout.
#[derive(Debug, Clone)]
pub struct Drive {
    /// Parameters.
    pub params: DriveParams,
    /// Number of masses.
    pub n_mass: usize,
    /// Masses, kg (table-equivalent).
    pub mass_kg: [f64; MAX_MASSES],
    /// Number of states.
    pub n_state: usize,
    i_current: Option<usize>,
    i_amp: Option<usize>,
    i_clock: [Option<usize>; MAX_MASSES],
    i_lag_motor: Option<usize>,
    i_lag_table: Option<usize>,
    i_fric: usize,
    n_fric: usize,
    /// Transmission r, m per motor radian (1 for a force drive).
    pub transmission_m_per_rad: f64,
    /// Forward efficiency η (1 for a force drive).
    pub efficiency: f64,
    /// Typical magnitude of each state (test states, the forward-difference check).
    pub scales: Vec<f64>,
    /// Absolute tolerance of each state per metre of position tolerance, on the rigid
    /// plant's principle (`Axis::state_scales`, docs/model.md "Tolerances"): positions 1,
    /// velocities and lagged velocities 1e3/s, a Dahl force σ, LuGre and GMS deflections 1
    /// (lengths), the current the larger of the current that produces the presliding force of
    /// one position tolerance and `m_0/(τ_e²·η·k_t/r)`; the amplifier voltage likewise
    /// (the voltage of that force, or `m_0/(τ_a²·F/V)`); dwell clocks 1e3 per unit. With the
    /// seed axis's components they equal the rigid plant's.
    pub tol_scales: Vec<f64>,
    /// The Jacobian is an arrowhead with the (only) velocity as hub: one mass, no amplifier
    /// state, and no table modulation acting on a dynamic friction state.
    arrowhead: bool,
    /// `StaticMap::negligible_exponent` of the motor and the table static maps.
    negligible: [f64; 2],
    /// Solve a stuck phase of the whole chain (every mass stuck) in closed form: the
    /// amplifier voltage relaxes exponentially (at its slew limit first), the current follows
    /// it, dwell clocks run, lagged velocities decay, nothing else moves. Always on; the
    /// tests switch it off to compare with the integrated phase.
    closed_form_stuck: bool,
}

impl Drive {
    /// Validate and build the layout.
    pub fn new(params: DriveParams) -> Result<Self, ConfigError> {
        params.validate()?;
        let (r, eta, masses): (f64, f64, Vec<f64>) = match &params.actuator {
            Actuator::DcMotor {
                motor,
                gearhead,
                screw,
            } => {
                let r = screw.metres_per_motor_radian(gearhead);
                let k = screw.screw_radians_per_metre();
                let eta = gearhead.efficiency * screw.efficiency;
                let m_motor = eta * motor.rotor_inertia_kg_m2 / (r * r);
                let m_screw = screw.efficiency * screw.inertia_kg_m2 * k * k;
                let m_table = params.table_mass_kg;
                let masses = match params.n_links {
                    0 => vec![m_motor + m_screw + m_table],
                    1 => vec![m_motor, m_screw + m_table],
                    _ => vec![m_motor, m_screw, m_table],
                };
                (r, eta, masses)
            }
            Actuator::ForceDrive { drive_mass_kg, .. } => {
                let masses = match params.n_links {
                    0 => vec![drive_mass_kg + params.table_mass_kg],
                    _ => vec![*drive_mass_kg, params.table_mass_kg],
                };
                (1.0, 1.0, masses)
            }
        };
        let n_mass = masses.len();
        let mut mass_kg = [0.0; MAX_MASSES];
        mass_kg[..n_mass].copy_from_slice(&masses);
        let mut scales: Vec<f64> = Vec::new();
        for _ in 0..n_mass {
            scales.push(1e-3); // position, m
            scales.push(1e-2); // velocity, m/s
        }
        let mut next = 2 * n_mass;
        let mut take = |scale: f64, scales: &mut Vec<f64>| {
            scales.push(scale);
            next += 1;
            next - 1
        };
        let i_current = match &params.actuator {
            Actuator::DcMotor { motor, .. } if !motor.quasi_static_current => {
                Some(take(0.1, &mut scales))
            }
            _ => None,
        };
        let i_amp = params.amplifier.map(|_| take(1.0, &mut scales));
        let table = n_mass - 1;
        let table_map = match &params.table_friction {
            TableFriction::Static(m) => Some(*m),
            _ => None,
        };
        let mut i_clock = [None; MAX_MASSES];
        let motor_dwell = params.motor_friction.is_some_and(|m| m.dwell.is_some());
        let table_dwell = table_map.is_some_and(|m| m.dwell.is_some());
        if motor_dwell || (table == 0 && table_dwell) {
            i_clock[0] = Some(take(1.0, &mut scales));
        }
        if table > 0 && table_dwell {
            i_clock[table] = Some(take(1.0, &mut scales));
        }
        let i_lag_motor = params
            .motor_friction
            .and_then(|m| m.memory_lag_s)
            .map(|_| take(1e-2, &mut scales));
        let i_lag_table = table_map
            .and_then(|m| m.memory_lag_s)
            .map(|_| take(1e-2, &mut scales));
        let i_fric = next;
        let n_fric = match &params.table_friction {
            TableFriction::Dahl(d) => {
                scales.push(d.law.coulomb_force_n);
                1
            }
            TableFriction::LuGre(l) => {
                scales.push(l.coulomb_force_n / l.stiffness_n_per_m);
                1
            }
            TableFriction::Gms(g) => {
                for i in 0..g.n_elements {
                    scales.push(g.weights[i] * g.coulomb_force_n / g.stiffness_n_per_m[i]);
                }
                g.n_elements
            }
            _ => 0,
        };
        let n_state = i_fric + n_fric;
        let tol_scales = Self::tolerance_scales(
            &params,
            &masses,
            r,
            eta,
            &scales,
            (i_current, i_amp, [i_lag_motor, i_lag_table], i_fric),
        );
        Ok(Self {
            params,
            n_mass,
            mass_kg,
            n_state,
            i_current,
            i_amp,
            i_clock,
            i_lag_motor,
            i_lag_table,
            i_fric,
            n_fric,
            transmission_m_per_rad: r,
            efficiency: eta,
            scales,
            tol_scales,
            arrowhead: n_mass == 1
                && i_amp.is_none()
                && (n_fric == 0 || params.table_modulation.n_terms == 0),
            closed_form_stuck: true,
            negligible: [
                params
                    .motor_friction
                    .map_or(f64::INFINITY, |m| m.negligible_exponent()),
                table_map.map_or(f64::INFINITY, |m| m.negligible_exponent()),
            ],
        })
    }

    /// Absolute tolerance per metre of position tolerance for each state, on the rigid
    /// plant's principle (`Axis::state_scales`, docs/model.md "Tolerances"): position 1;
    /// velocity 1e3/s (one position tolerance per ms); lag states (lagged velocities) the
    /// same; a Dahl force σ (the force of one position tolerance of presliding); LuGre and
    /// GMS deflections 1 (they are lengths); the current the larger of the current that
    /// produces that Dahl force and `m / (τ_e²·η·k_t/r)`, the current error whose transient
    /// (τ_e = L/R) moves the masses by one position tolerance; the amplifier voltage on the
    /// same principle (the voltage that gives that Dahl force, or whose error, decaying with
    /// τ_a = 1/(2π·bandwidth), moves mass 0 by one position tolerance); dwell clocks 1 per
    /// unit. With the seed axis's components the scales equal the rigid plant's.
    fn tolerance_scales(
        params: &DriveParams,
        masses: &[f64],
        r: f64,
        eta: f64,
        scales: &[f64],
        layout: (Option<usize>, Option<usize>, [Option<usize>; 2], usize),
    ) -> Vec<f64> {
        let (i_current, i_amp, i_lags, i_fric) = layout;
        // Dwell clocks: one unit per millimetre, as before.
        let mut t: Vec<f64> = scales.iter().map(|s| s / 1e-3).collect();
        for j in 0..masses.len() {
            t[2 * j] = 1.0;
            t[2 * j + 1] = 1e3;
        }
        for k in i_lags.into_iter().flatten() {
            t[k] = 1e3;
        }
        let presliding = match &params.table_friction {
            TableFriction::Dahl(d) => {
                t[i_fric] = d.law.stiffness_n_per_m;
                d.law.stiffness_n_per_m
            }
            TableFriction::LuGre(l) => {
                t[i_fric] = 1.0;
                l.stiffness_n_per_m
            }
            TableFriction::Gms(g) => {
                for v in t.iter_mut().skip(i_fric).take(g.n_elements) {
                    *v = 1.0;
                }
                g.stiffness_n_per_m[..g.n_elements].iter().sum()
            }
            TableFriction::None | TableFriction::Static(_) => 0.0,
        };
        if let (Some(k), Actuator::DcMotor { motor, .. }) = (i_current, &params.actuator) {
            let force_per_amp = eta * motor.torque_constant_nm_per_a / r;
            let tau_e = motor.inductance_h / motor.resistance_ohm;
            t[k] = drive_state_scale(presliding, masses[0], tau_e, force_per_amp);
        }
        if let (Some(k), Some(a)) = (i_amp, &params.amplifier) {
            let force_per_volt = match &params.actuator {
                Actuator::DcMotor { motor, .. } => {
                    eta * motor.torque_constant_nm_per_a / (r * motor.resistance_ohm)
                }
                Actuator::ForceDrive { gain_n_per_v, .. } => *gain_n_per_v,
            };
            let tau_a = 1.0 / (2.0 * std::f64::consts::PI * a.bandwidth_hz);
            t[k] = drive_state_scale(presliding, masses[0], tau_a, force_per_volt);
        }
        t
    }

    /// Index of the table mass.
    #[inline]
    pub fn table(&self) -> usize {
        self.n_mass - 1
    }

    /// Whether mass `j` carries a static map (and so can stick).
    pub fn can_stick(&self, j: usize) -> bool {
        (j == 0 && self.params.motor_friction.is_some())
            || (j == self.table() && matches!(self.params.table_friction, TableFriction::Static(_)))
    }

    /// Initial modes: stuck where a static map holds the mass, free elsewhere.
    pub fn initial_modes(&self) -> [MassMode; MAX_MASSES] {
        let mut m = [MassMode::Free; MAX_MASSES];
        for (j, mode) in m.iter_mut().enumerate().take(self.n_mass) {
            if self.can_stick(j) {
                *mode = MassMode::Stuck;
            }
        }
        m
    }

    /// Voltage at the actuator (the amplifier state when modelled).
    #[inline]
    fn applied_v(&self, y: &[f64], inp: &Inputs) -> f64 {
        self.i_amp.map_or(inp.u_v, |k| y[k])
    }

    /// Motor current (DC motor), A; 0 for a force drive.
    pub fn current_a(&self, y: &[f64], inp: &Inputs) -> f64 {
        match &self.params.actuator {
            Actuator::DcMotor { motor, .. } => match self.i_current {
                Some(k) => y[k],
                None => {
                    (self.applied_v(y, inp)
                        - motor.back_emf_v_s_per_rad * y[1] / self.transmission_m_per_rad)
                        / motor.resistance_ohm
                }
            },
            Actuator::ForceDrive { .. } => 0.0,
        }
    }

    /// Actuator force on mass 0, N.
    #[inline]
    fn drive_force(&self, y: &[f64], inp: &Inputs) -> f64 {
        match &self.params.actuator {
            Actuator::DcMotor { motor, .. } => {
                self.efficiency * motor.torque_constant_nm_per_a * self.current_a(y, inp)
                    / self.transmission_m_per_rad
            }
            Actuator::ForceDrive { gain_n_per_v, .. } => gain_n_per_v * self.applied_v(y, inp),
        }
    }

    fn direction(mode: MassMode, v: f64) -> f64 {
        match mode {
            MassMode::Slip(d) => d,
            MassMode::Stuck => 0.0,
            MassMode::Free => {
                if v > 0.0 {
                    1.0
                } else if v < 0.0 {
                    -1.0
                } else {
                    0.0
                }
            }
        }
    }

    /// Force of link `k` on mass `k` (the mass on its drive side), N: `−(k·dz(δ) + c·δ̇·c(δ))`
    /// with δ = x_k − x_{k+1}, dz the dead-zone function and c(δ) a contact ramp over 1 nm.
    fn link_force(&self, k: usize, y: &[f64]) -> f64 {
        let l = &self.params.links[k];
        let delta = y[2 * k] - y[2 * k + 2];
        let ddelta = y[2 * k + 1] - y[2 * k + 3];
        let half = 0.5 * l.backlash_m;
        let pen = if delta > half {
            delta - half
        } else if delta < -half {
            delta + half
        } else {
            0.0
        };
        let contact = if l.backlash_m == 0.0 {
            1.0
        } else {
            (pen.abs() / 1e-9).min(1.0)
        };
        l.stiffness_n_per_m * pen + l.damping_n_s_per_m * ddelta * contact
    }

    /// Dynamic table friction force (not the static map), N, and its state derivatives
    /// (written to `dfric` if given).
    fn dynamic_friction(
        &self,
        y: &[f64],
        v: f64,
        d: f64,
        s: f64,
        dfric: Option<&mut [f64]>,
    ) -> f64 {
        let z = &y[self.i_fric..self.i_fric + self.n_fric];
        self.params.table_friction.dynamic(z, v, d, s, dfric)
    }

    /// The modulation factor `1 + Σ a_k·cos(κ_k·x + φ_k)` at `x`.
    pub fn modulation_factor(m: &Modulation, x: f64) -> f64 {
        modulation(m, x).0
    }

    /// Friction level scale of a side at position `x`.
    #[inline]
    fn level(&self, m: &Modulation, x: f64, inp: &Inputs) -> f64 {
        inp.friction_scale * modulation(m, x).0
    }

    /// Forces on each mass except its static maps, and the static maps' sliding force and
    /// capacity per mass. Returns (non-static force, static sliding force, capacity(+), capacity(−)).
    fn forces(
        &self,
        y: &[f64],
        inp: &Inputs,
        modes: &[MassMode; MAX_MASSES],
        dfric: Option<&mut [f64]>,
    ) -> [[f64; 4]; MAX_MASSES] {
        let p = &self.params;
        let mut out = [[0.0; 4]; MAX_MASSES];
        out[0][0] += self.drive_force(y, inp);
        for k in 0..p.n_links {
            let f = self.link_force(k, y);
            out[k][0] -= f;
            out[k + 1][0] += f;
        }
        let t = self.table();
        let vt = y[2 * t + 1];
        let dt = Self::direction(modes[t], vt);
        let st = self.level(&p.table_modulation, y[2 * t], inp);
        out[t][0] += inp.force_n - p.external_force_n - self.dynamic_friction(y, vt, dt, st, dfric);
        if let Some(m) = &p.motor_friction {
            let v0 = y[1];
            let d0 = Self::direction(modes[0], v0);
            let s0 = self.level(&p.motor_modulation, y[0], inp);
            let w = self.i_lag_motor.map_or(v0, |k| y[k]);
            let dwell = self.i_clock[0].map_or(0.0, |k| y[k]);
            if d0 != 0.0 {
                let rise = m.sliding_rise(dwell);
                out[0][1] += m.sliding_force_with(v0, w, d0, s0, rise, self.negligible[0]);
            }
            out[0][2] += m.capacity(1.0, s0, dwell);
            out[0][3] += m.capacity(-1.0, s0, dwell);
        }
        if let TableFriction::Static(m) = &p.table_friction {
            let w = self.i_lag_table.map_or(vt, |k| y[k]);
            let dwell = self.i_clock[t].map_or(0.0, |k| y[k]);
            if dt != 0.0 {
                let rise = m.sliding_rise(dwell);
                out[t][1] += m.sliding_force_with(vt, w, dt, st, rise, self.negligible[1]);
            }
            out[t][2] += m.capacity(1.0, st, dwell);
            out[t][3] += m.capacity(-1.0, st, dwell);
        }
        out
    }

    /// The static map whose dwell clock belongs to mass `j` (the motor's on mass 0, the
    /// table's on the table; the table's on mass 0 when it is the only mass).
    fn clock_map(&self, j: usize) -> Option<&StaticMap> {
        let table = match &self.params.table_friction {
            TableFriction::Static(m) if m.dwell.is_some() => Some(m),
            _ => None,
        };
        let motor = self
            .params
            .motor_friction
            .as_ref()
            .filter(|m| m.dwell.is_some());
        if j == 0 {
            motor.or(if self.table() == 0 { table } else { None })
        } else if j == self.table() {
            table
        } else {
            None
        }
    }

    /// Right-hand side for the given modes.
    pub fn rhs(&self, y: &[f64], dy: &mut [f64], inp: &Inputs, modes: &[MassMode; MAX_MASSES]) {
        dy.iter_mut().for_each(|v| *v = 0.0);
        let (head, fric) = dy.split_at_mut(self.i_fric);
        let f = self.forces(y, inp, modes, Some(&mut fric[..self.n_fric]));
        for j in 0..self.n_mass {
            if modes[j] == MassMode::Stuck {
                head[2 * j] = 0.0;
                head[2 * j + 1] = 0.0;
            } else {
                head[2 * j] = y[2 * j + 1];
                head[2 * j + 1] = (f[j][0] - f[j][1]) / self.mass_kg[j];
            }
        }
        let u = self.applied_v(y, inp);
        if let (Some(k), Actuator::DcMotor { motor, .. }) = (self.i_current, &self.params.actuator)
        {
            head[k] = (u
                - motor.resistance_ohm * y[k]
                - motor.back_emf_v_s_per_rad * y[1] / self.transmission_m_per_rad)
                / motor.inductance_h;
        }
        if let (Some(k), Some(a)) = (self.i_amp, &self.params.amplifier) {
            head[k] = (2.0 * std::f64::consts::PI * a.bandwidth_hz * (inp.u_v - y[k]))
                .clamp(-a.slew_v_per_s, a.slew_v_per_s);
        }
        for (j, (clock, mode)) in self.i_clock.iter().zip(modes).enumerate().take(self.n_mass) {
            if let (Some(k), Some(m)) = (*clock, self.clock_map(j)) {
                head[k] = if *mode == MassMode::Stuck {
                    1.0
                } else {
                    m.clock_rate(y[2 * j + 1], y[k]).0
                };
            }
        }
        if let (Some(k), Some(m)) = (self.i_lag_motor, &self.params.motor_friction) {
            let tau = m.memory_lag_s.unwrap_or(1.0);
            head[k] = (y[1] - y[k]) / tau;
        }
        if let (Some(k), TableFriction::Static(m)) = (self.i_lag_table, &self.params.table_friction)
        {
            let tau = m.memory_lag_s.unwrap_or(1.0);
            let t = self.table();
            head[k] = (y[2 * t + 1] - y[k]) / tau;
        }
    }

    /// The Jacobian of [`Self::rhs`] (same modes and inputs), analytic: `set(r, c, v)` adds
    /// `v` to entry (r, c). Entries that are structurally zero are never touched (the
    /// arrowhead declaration relies on it). Kinks (dead band edges, the contact ramp's ends,
    /// the amplifier's slew limit, the GMS yield thresholds) take the derivative of the side
    /// the state is on.
    pub fn jacobian(
        &self,
        y: &[f64],
        inp: &Inputs,
        modes: &[MassMode; MAX_MASSES],
        set: &mut impl FnMut(usize, usize, f64),
    ) {
        let p = &self.params;
        let n = self.n_state;
        // Gradient of the net force (drive, links, table, minus sliding) on each mass.
        let mut grad = [[0.0; 32]; MAX_MASSES];
        match &p.actuator {
            Actuator::DcMotor { motor, .. } => {
                let fpa =
                    self.efficiency * motor.torque_constant_nm_per_a / self.transmission_m_per_rad;
                match self.i_current {
                    Some(k) => grad[0][k] += fpa,
                    None => {
                        grad[0][1] -= fpa * motor.back_emf_v_s_per_rad
                            / (self.transmission_m_per_rad * motor.resistance_ohm);
                        if let Some(a) = self.i_amp {
                            grad[0][a] += fpa / motor.resistance_ohm;
                        }
                    }
                }
            }
            Actuator::ForceDrive { gain_n_per_v, .. } => {
                if let Some(a) = self.i_amp {
                    grad[0][a] += gain_n_per_v;
                }
            }
        }
        for k in 0..p.n_links {
            let l = &p.links[k];
            let delta = y[2 * k] - y[2 * k + 2];
            let ddelta = y[2 * k + 1] - y[2 * k + 3];
            let half = 0.5 * l.backlash_m;
            let (pen, dpen) = if delta > half {
                (delta - half, 1.0)
            } else if delta < -half {
                (delta + half, 1.0)
            } else {
                (0.0, 0.0)
            };
            let (contact, dcontact) = if l.backlash_m == 0.0 {
                (1.0, 0.0)
            } else if pen.abs() / 1e-9 < 1.0 {
                (pen.abs() / 1e-9, pen.signum() / 1e-9 * dpen)
            } else {
                (1.0, 0.0)
            };
            let df_dd = l.stiffness_n_per_m * dpen + l.damping_n_s_per_m * ddelta * dcontact;
            let df_dv = l.damping_n_s_per_m * contact;
            for (mass, sign) in [(k, -1.0), (k + 1, 1.0)] {
                grad[mass][2 * k] += sign * df_dd;
                grad[mass][2 * k + 2] -= sign * df_dd;
                grad[mass][2 * k + 1] += sign * df_dv;
                grad[mass][2 * k + 3] -= sign * df_dv;
            }
        }
        let t = self.table();
        let vt = y[2 * t + 1];
        let dt = Self::direction(modes[t], vt);
        let (mod_t, dmod_t) = modulation(&p.table_modulation, y[2 * t]);
        let st = inp.friction_scale * mod_t;
        let dst_dx = inp.friction_scale * dmod_t;
        let table_modulated = p.table_modulation.n_terms > 0;
        let zi = self.i_fric;
        // Rows of the dynamic friction states, and the table force's gradient.
        match &p.table_friction {
            TableFriction::Dahl(dahl) => {
                grad[t][zi] -= 1.0;
                // The level Fc·st·(1 + a·d) is constant in v inside a segment of direction d
                // (d as in `TableFriction::dynamic`: 1 at rest).
                let dd = if dt == 0.0 { 1.0 } else { dt };
                let scaled = dahl.scaled(st, dd);
                let (_, dz_dv, dz_dz) = scaled.rate(vt, y[zi], dd);
                set(zi, 2 * t + 1, dz_dv);
                set(zi, zi, dz_dz);
                if table_modulated {
                    set(zi, 2 * t, -(y[zi] / st) * dz_dz * dst_dx);
                }
            }
            TableFriction::LuGre(l) => {
                let z = y[zi];
                let q = vt / l.stribeck_velocity_m_per_s;
                let ex = (-q * q).exp();
                let gg = l.coulomb_force_n + (l.static_force_n - l.coulomb_force_n) * ex;
                let dgg_dv = (l.static_force_n - l.coulomb_force_n)
                    * ex
                    * (-2.0 * q / l.stribeck_velocity_m_per_s);
                // The direction factor is constant in v inside a segment of direction d.
                let k = direction_factor(l.asymmetry, sliding_direction(vt, dt));
                let sd = st * k;
                let g = sd * gg;
                let s0 = l.stiffness_n_per_m;
                let dzd_dz = -s0 * vt.abs() / g;
                let dzd_dv = 1.0 - s0 * z * (vt.signum() * g - vt.abs() * sd * dgg_dv) / (g * g);
                let dzd_ds = s0 * vt.abs() * z * (gg * k) / (g * g);
                set(zi, zi, dzd_dz);
                set(zi, 2 * t + 1, dzd_dv);
                grad[t][zi] -= s0 + l.damping_n_s_per_m * dzd_dz;
                grad[t][2 * t + 1] -= l.damping_n_s_per_m * dzd_dv + l.viscous_n_s_per_m;
                if table_modulated {
                    set(zi, 2 * t, dzd_ds * dst_dx);
                    grad[t][2 * t] -= l.damping_n_s_per_m * dzd_ds * dst_dx;
                }
            }
            TableFriction::Gms(g) => {
                grad[t][2 * t + 1] -= g.viscous_n_s_per_m;
                let q = vt / g.stribeck_velocity_m_per_s;
                let ex = (-q * q).exp();
                // The direction factor is constant in v inside a segment of direction d.
                let sd = st * direction_factor(g.asymmetry, sliding_direction(vt, dt));
                let sv = g.slip_force(vt, sd);
                let dsv_dv = sd
                    * (g.static_force_n - g.coulomb_force_n)
                    * ex
                    * (-2.0 * q / g.stribeck_velocity_m_per_s);
                let beta = GMS_ELASTIC_FRACTION;
                for i in 0..g.n_elements {
                    let k = zi + i;
                    grad[t][k] -= g.stiffness_n_per_m[i];
                    let z_max = g.weights[i] * sv / g.stiffness_n_per_m[i];
                    let w = vt.signum() * y[k] / z_max;
                    let (alpha, dalpha) = if w <= beta {
                        (0.0, 0.0)
                    } else if w <= 1.0 {
                        let u = (w - beta) / (1.0 - beta);
                        (smoothstep(u), 6.0 * u * (1.0 - u) / (1.0 - beta))
                    } else {
                        (w, 1.0)
                    };
                    if vt == 0.0 {
                        // The forward difference in v sees the rate v·(1 − α) from v = 0.
                        let w0 = y[k] / z_max;
                        let a0 = if w0 <= beta {
                            0.0
                        } else if w0 <= 1.0 {
                            smoothstep((w0 - beta) / (1.0 - beta))
                        } else {
                            w0
                        };
                        set(k, 2 * t + 1, 1.0 - a0);
                        continue;
                    }
                    let dzmax_dv = g.weights[i] * dsv_dv / g.stiffness_n_per_m[i];
                    set(k, k, -vt.abs() * dalpha / z_max);
                    set(
                        k,
                        2 * t + 1,
                        (1.0 - alpha) + vt * dalpha * (w / z_max) * dzmax_dv,
                    );
                    if table_modulated {
                        set(k, 2 * t, vt * dalpha * w / st * dst_dx);
                    }
                }
            }
            TableFriction::None | TableFriction::Static(_) => {}
        }
        if let Some(m) = &p.motor_friction {
            let v0 = y[1];
            let d0 = Self::direction(modes[0], v0);
            if d0 != 0.0 {
                let (mod0, dmod0) = modulation(&p.motor_modulation, y[0]);
                let s0 = inp.friction_scale * mod0;
                let w = self.i_lag_motor.map_or(v0, |k| y[k]);
                let age = self.i_clock[0].map_or(0.0, |k| y[k]);
                let (dv, dw, ds, drise) = m.sliding_partials(w, d0, s0, m.sliding_rise(age));
                grad[0][1] -= dv;
                if let Some(k) = self.i_clock[0] {
                    grad[0][k] -= drise * m.sliding_rise_slope(age);
                }
                match self.i_lag_motor {
                    Some(k) => grad[0][k] -= dw,
                    None => grad[0][1] -= dw,
                }
                if p.motor_modulation.n_terms > 0 {
                    grad[0][0] -= ds * inp.friction_scale * dmod0;
                }
            }
        }
        if let TableFriction::Static(m) = &p.table_friction {
            if dt != 0.0 {
                let w = self.i_lag_table.map_or(vt, |k| y[k]);
                let age = self.i_clock[t].map_or(0.0, |k| y[k]);
                let (dv, dw, ds, drise) = m.sliding_partials(w, dt, st, m.sliding_rise(age));
                grad[t][2 * t + 1] -= dv;
                if let Some(k) = self.i_clock[t] {
                    grad[t][k] -= drise * m.sliding_rise_slope(age);
                }
                match self.i_lag_table {
                    Some(k) => grad[t][k] -= dw,
                    None => grad[t][2 * t + 1] -= dw,
                }
                if table_modulated {
                    grad[t][2 * t] -= ds * dst_dx;
                }
            }
        }
        for j in 0..self.n_mass {
            if modes[j] == MassMode::Stuck {
                continue;
            }
            set(2 * j, 2 * j + 1, 1.0);
            for (c, g) in grad[j].iter().enumerate().take(n) {
                if *g != 0.0 {
                    set(2 * j + 1, c, g / self.mass_kg[j]);
                }
            }
        }
        if let (Some(k), Actuator::DcMotor { motor, .. }) = (self.i_current, &p.actuator) {
            set(k, k, -motor.resistance_ohm / motor.inductance_h);
            set(
                k,
                1,
                -motor.back_emf_v_s_per_rad / (self.transmission_m_per_rad * motor.inductance_h),
            );
            if let Some(a) = self.i_amp {
                set(k, a, 1.0 / motor.inductance_h);
            }
        }
        if let (Some(k), Some(a)) = (self.i_amp, &p.amplifier) {
            let w = 2.0 * std::f64::consts::PI * a.bandwidth_hz;
            if (w * (inp.u_v - y[k])).abs() < a.slew_v_per_s {
                set(k, k, -w);
            }
        }
        for j in 0..self.n_mass {
            if let (Some(k), Some(m)) = (self.i_clock[j], self.clock_map(j)) {
                if modes[j] != MassMode::Stuck && m.ageing().is_some() {
                    let (_, d_age, d_v) = m.clock_rate(y[2 * j + 1], y[k]);
                    set(k, k, d_age);
                    set(k, 2 * j + 1, d_v);
                }
            }
        }
        if let (Some(k), Some(m)) = (self.i_lag_motor, &p.motor_friction) {
            let tau = m.memory_lag_s.unwrap_or(1.0);
            set(k, 1, 1.0 / tau);
            set(k, k, -1.0 / tau);
        }
        if let (Some(k), TableFriction::Static(m)) = (self.i_lag_table, &p.table_friction) {
            let tau = m.memory_lag_s.unwrap_or(1.0);
            set(k, 2 * t + 1, 1.0 / tau);
            set(k, k, -1.0 / tau);
        }
    }

    /// Net force that the static maps of stuck mass `j` must hold, N, and its capacity in that
    /// direction.
    pub fn holding(
        &self,
        y: &[f64],
        inp: &Inputs,
        modes: &[MassMode; MAX_MASSES],
        j: usize,
    ) -> (f64, f64) {
        let mut m = *modes;
        m[j] = MassMode::Stuck;
        let f = self.forces(y, inp, &m, None)[j];
        let cap = if f[0] >= 0.0 { f[2] } else { f[3] };
        (f[0], cap)
    }

    /// Event value per mass: v·d while slipping, capacity − |holding force| while stuck.
    fn event_values(
        &self,
        y: &[f64],
        inp: &Inputs,
        modes: &[MassMode; MAX_MASSES],
    ) -> [f64; MAX_MASSES] {
        let mut e = [f64::INFINITY; MAX_MASSES];
        for j in 0..self.n_mass {
            e[j] = match modes[j] {
                MassMode::Free => f64::INFINITY,
                MassMode::Slip(d) => y[2 * j + 1] * d,
                MassMode::Stuck => {
                    let (f, cap) = self.holding(y, inp, modes, j);
                    cap - f.abs()
                }
            };
        }
        e
    }

    /// Recorded friction forces: (motor side, table side), N, with the present modes.
    pub fn friction_forces(
        &self,
        y: &[f64],
        inp: &Inputs,
        modes: &[MassMode; MAX_MASSES],
    ) -> (f64, f64) {
        let p = &self.params;
        let t = self.table();
        let vt = y[2 * t + 1];
        let dt = Self::direction(modes[t], vt);
        let st = self.level(&p.table_modulation, y[2 * t], inp);
        let mut table = self.dynamic_friction(y, vt, dt, st, None);
        let mut motor = 0.0;
        let f = self.forces(y, inp, modes, None);
        if p.motor_friction.is_some() {
            motor = if modes[0] == MassMode::Stuck && t > 0 {
                f[0][0]
            } else {
                f[0][1]
            };
        }
        if matches!(p.table_friction, TableFriction::Static(_)) {
            table += if modes[t] == MassMode::Stuck && t > 0 {
                f[t][0]
            } else {
                f[t][1]
            };
        }
        if t == 0 && modes[0] == MassMode::Stuck {
            // Rigid and stuck: the static maps together hold the net force; attribute it to
            // the motor map when there is one.
            let hold = f[0][0];
            if p.motor_friction.is_some() {
                motor = hold;
            } else {
                table += hold;
            }
        }
        (motor, table)
    }
}

/// Absolute-tolerance scale of a drive state that makes force through `force_per_unit`
/// (the motor current, N/A; the amplifier voltage, N/V) and relaxes with time constant
/// `tau_s`: the larger of the state that gives the presliding force of one position
/// tolerance (`presliding_n_per_m`), and the error whose transient moves `mass_kg` by one
/// position tolerance, `m / (τ²·force_per_unit)` (an error of such a state is not sustained).
fn drive_state_scale(
    presliding_n_per_m: f64,
    mass_kg: f64,
    tau_s: f64,
    force_per_unit: f64,
) -> f64 {
    let transient = mass_kg / (tau_s * tau_s * force_per_unit);
    (presliding_n_per_m / force_per_unit).max(transient)
}

/// The drive over one segment (inputs and modes held), as an [`OdeSystem`] of padded size N.
struct Segment<'a> {
    drive: &'a Drive,
    inp: Inputs,
    modes: [MassMode; MAX_MASSES],
}

#[cfg(test)]
impl Segment<'_> {
    /// Forward-difference Jacobian at `y` given `f0 = f(y)` (the check of the analytic one).
    fn difference_jacobian<const N: usize>(
        &self,
        y: &SVector<f64, N>,
        f0: &SVector<f64, N>,
        jac: &mut SMatrix<f64, N, N>,
    ) {
        let n = self.drive.n_state;
        jac.fill(0.0);
        let mut f1 = [0.0; 32];
        let mut yp = [0.0; 32];
        yp[..n].copy_from_slice(&y.as_slice()[..n]);
        for c in 0..n {
            let h = 1e-7 * yp[c].abs().max(self.drive.scales[c]);
            let keep = yp[c];
            yp[c] = keep + h;
            let h = yp[c] - keep;
            self.drive
                .rhs(&yp[..n], &mut f1[..n], &self.inp, &self.modes);
            yp[c] = keep;
            for r in 0..n {
                jac[(r, c)] = (f1[r] - f0[r]) / h;
            }
        }
    }
}

impl<const N: usize> OdeSystem<N> for Segment<'_> {
    fn rhs(&self, y: &SVector<f64, N>, dy: &mut SVector<f64, N>) {
        let n = self.drive.n_state;
        self.drive.rhs(
            &y.as_slice()[..n],
            &mut dy.as_mut_slice()[..n],
            &self.inp,
            &self.modes,
        );
    }

    fn jacobian(&self, y: &SVector<f64, N>, jac: &mut SMatrix<f64, N, N>) {
        let n = self.drive.n_state;
        jac.fill(0.0);
        self.drive.jacobian(
            &y.as_slice()[..n],
            &self.inp,
            &self.modes,
            &mut |r, c, v| jac[(r, c)] += v,
        );
    }

    fn arrowhead_hub(&self) -> Option<usize> {
        if self.drive.arrowhead {
            Some(1)
        } else {
            None
        }
    }

    fn event(&self, y: &SVector<f64, N>) -> Option<f64> {
        let n = self.drive.n_state;
        let e = self
            .drive
            .event_values(&y.as_slice()[..n], &self.inp, &self.modes);
        let m = e.iter().copied().fold(f64::INFINITY, f64::min);
        if m.is_finite() {
            Some(m)
        } else {
            None
        }
    }
}

/// The amplifier's output voltage a time `dt` after it was `v0_v` with the command `u_v`
/// held: the solution of `dv/dt = clamp(ω·(u − v), −S, S)` (ω = 2π·bandwidth, S the slew
/// limit), a ramp at the slew limit while `ω·|u − v| > S`, then the exponential approach.
/// Monotone in `dt` (the stuck phase's breakaway search relies on it).
fn amplifier_voltage(v0_v: f64, u_v: f64, a: &Amplifier, dt: f64) -> f64 {
    let omega = 2.0 * std::f64::consts::PI * a.bandwidth_hz;
    let e0 = u_v - v0_v;
    let e_slew = a.slew_v_per_s / omega;
    let (e, t) = if e0.abs() > e_slew {
        let t_ramp = (e0.abs() - e_slew) / a.slew_v_per_s;
        if dt <= t_ramp {
            return v0_v + e0.signum() * a.slew_v_per_s * dt;
        }
        (e0.signum() * e_slew, dt - t_ramp)
    } else {
        (e0, dt)
    };
    u_v - e * (-omega * t).exp()
}

/// The amplifier's voltage and the motor current a time `dt` after they were `v0_v` and
/// `i0_a`, the command `u_v` held and the motor at rest: [`amplifier_voltage`] drives
/// `di/dt = (v − R·i)/L`. Solved in closed form: while the amplifier slews,
/// `i = e^{−at}·i₀ + (v₀/R)(1 − e^{−at}) ± (S/R)(t − (1 − e^{−at})/a)` (a = R/L); then, with
/// `e` the amplifier's remaining error, `i = u/R + (i₀ − u/R)e^{−at} − (e/L)·h(t)`,
/// `h(t) = (e^{−ωt} − e^{−at})/(a − ω)` (→ `t·e^{−at}` as ω → a), written with `expm1` so
/// that close rates lose no digits. Not monotone in `dt` in general: the current lags a
/// moving voltage.
fn amplifier_and_current(
    v0_v: f64,
    i0_a: f64,
    u_v: f64,
    a: &Amplifier,
    motor: &crate::model::Motor,
    dt: f64,
) -> (f64, f64) {
    let r = motor.resistance_ohm;
    let rate = r / motor.inductance_h;
    let omega = 2.0 * std::f64::consts::PI * a.bandwidth_hz;
    let e0 = u_v - v0_v;
    let e_slew = a.slew_v_per_s / omega;
    // While slewing at ±S: the voltage is a ramp.
    let v = amplifier_voltage(v0_v, u_v, a, dt);
    // The current at time t of a ramp at ±S from (v0, i0).
    let ramp = |t: f64| {
        let s = e0.signum() * a.slew_v_per_s;
        let decay = -(-rate * t).exp_m1();
        (-rate * t).exp() * i0_a + v0_v / r * decay + s / r * (t - decay / rate)
    };
    let (v_s, i_s, t) = if e0.abs() > e_slew {
        let t_ramp = (e0.abs() - e_slew) / a.slew_v_per_s;
        if dt <= t_ramp {
            return (v, ramp(dt));
        }
        (
            amplifier_voltage(v0_v, u_v, a, t_ramp),
            ramp(t_ramp),
            dt - t_ramp,
        )
    } else {
        (v0_v, i0_a, dt)
    };
    let e = u_v - v_s;
    let (lo, gap) = (rate.min(omega), (rate - omega).abs());
    let h = (-lo * t).exp()
        * if gap > 0.0 {
            -(-gap * t).exp_m1() / gap
        } else {
            t
        };
    let i_inf = u_v / r;
    (
        v,
        i_inf + (i_s - i_inf) * (-rate * t).exp() - e / motor.inductance_h * h,
    )
}

/// A running component plant with state padded to `N`.
#[derive(Debug, Clone)]
pub struct DrivePlant<const N: usize> {
    /// The model.
    pub drive: Drive,
    /// State (first `drive.n_state` entries used).
    pub y: SVector<f64, N>,
    /// Modes per mass.
    pub modes: [MassMode; MAX_MASSES],
    /// The integrator.
    pub integrator: Rodas4<N>,
    atol: SVector<f64, N>,
    /// Command voltage of the last `advance` call (NaN before the first).
    u_last: f64,
    /// Error norm per (volt of input jump · s³ of first step) seen after the last jump.
    jump_error_rate: Option<f64>,
}

impl<const N: usize> DrivePlant<N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    fn new(drive: Drive, options: IntegratorOptions) -> Result<Self, ConfigError> {
        let integrator = Rodas4::new(options)?;
        let mut atol = SVector::<f64, N>::repeat(1.0);
        // Tolerances relative to the position tolerance, scaled per state like the rigid
        // plant: a velocity of 1e3/s, a force state σ·x, etc. (state scale / 1 mm).
        for (k, s) in drive.tol_scales.iter().enumerate() {
            atol[k] = options.atol_position_m * s;
        }
        let modes = drive.initial_modes();
        Ok(Self {
            drive,
            y: SVector::zeros(),
            modes,
            integrator,
            atol,
            u_last: f64::NAN,
            jump_error_rate: None,
        })
    }

    /// The mass whose event value ([`Drive::event_values`]) is the smallest (the first of
    /// equals): the one whose mode changes at an event.
    fn event_mass(&self, inp: &Inputs) -> usize {
        let e = self
            .drive
            .event_values(&self.y.as_slice()[..self.drive.n_state], inp, &self.modes);
        let mut j = 0;
        for k in 1..self.drive.n_mass {
            if e[k] < e[j] {
                j = k;
            }
        }
        j
    }

    /// The state a time `dt` into a stuck phase of the chain (every mass stuck; see
    /// [`Drive::closed_form_stuck`]) that starts at `y0` with the inputs `inp`.
    fn stuck_state(&self, y0: &SVector<f64, N>, inp: &Inputs, dt: f64) -> SVector<f64, N> {
        let d = &self.drive;
        let mut y = *y0;
        match (
            d.i_amp,
            &d.params.amplifier,
            d.i_current,
            &d.params.actuator,
        ) {
            (Some(ka), Some(a), Some(kc), Actuator::DcMotor { motor, .. }) => {
                (y[ka], y[kc]) = amplifier_and_current(y0[ka], y0[kc], inp.u_v, a, motor, dt);
            }
            (Some(ka), Some(a), _, _) => y[ka] = amplifier_voltage(y0[ka], inp.u_v, a, dt),
            (_, _, Some(k), Actuator::DcMotor { motor, .. }) => {
                // di/dt = (u − R·i)/L with the velocity zero.
                let i_inf = inp.u_v / motor.resistance_ohm;
                let rate = motor.resistance_ohm / motor.inductance_h;
                y[k] = i_inf + (y0[k] - i_inf) * (-rate * dt).exp();
            }
            _ => {}
        }
        for k in d.i_clock.iter().take(d.n_mass).flatten() {
            y[*k] = y0[*k] + dt;
        }
        if let (Some(k), Some(m)) = (d.i_lag_motor, &d.params.motor_friction) {
            let tau = m.memory_lag_s.unwrap_or(1.0);
            y[k] = y0[k] * (-dt / tau).exp();
        }
        if let (Some(k), TableFriction::Static(m)) = (d.i_lag_table, &d.params.table_friction) {
            let tau = m.memory_lag_s.unwrap_or(1.0);
            y[k] = y0[k] * (-dt / tau).exp();
        }
        y
    }

    /// Per mass of a stuck chain at `y`: the holding force, the static maps' sliding force
    /// (0) and the capacities (+, −) ([`Drive::forces`] with mass 0 stuck, the others as
    /// they are: stuck).
    fn stuck_forces(&self, y: &SVector<f64, N>, inp: &Inputs) -> [[f64; 4]; MAX_MASSES] {
        let n = self.drive.n_state;
        let mut m = self.modes;
        m[0] = MassMode::Stuck;
        self.drive.forces(&y.as_slice()[..n], inp, &m, None)
    }

    /// A stuck phase of the chain (every mass stuck) from `t0` to at most `t1`, solved in
    /// closed form. Returns the time of the first breakaway (the state is then the first one
    /// found past it, within the event tolerance, as the integrator's event location leaves
    /// it) or `None` when every mass stays stuck to `t1` (the state is then the state at
    /// `t1`). The event value is the smallest margin `cap − |f|` over the masses.
    ///
    /// Nothing moves, so the link forces are constant: the holding force of mass 0 is affine
    /// in the current (or, with a quasi-static current, in the amplifier's voltage), which is
    /// monotone in time, so its magnitude peaks at an end of any interval, and those of the
    /// other masses are constant; the capacities are constant or (dwell) rise with time. So
    /// `min(cap±(a)) − max(|f(a)|, |f(b)|)`, per mass, bounds the event value from below on
    /// `[a, b]`: intervals whose bound is ≥ 0 hold for sure, the others are halved (left
    /// first) until a negative event value is found or they are narrower than the event
    /// tolerance.
    fn stuck_closed_form(&mut self, inp: &Inputs, t0: f64, t1: f64) -> Option<f64> {
        let y0 = self.y;
        let tol = self.integrator.options.event_tol_s;
        let n_mass = self.drive.n_mass;
        // (state, holding force and smaller capacity per mass, event value) at `dt`.
        let eval = |s: &Self, dt: f64| {
            let y = s.stuck_state(&y0, inp, dt);
            let forces = s.stuck_forces(&y, inp);
            let mut f = [0.0; MAX_MASSES];
            let mut capmin = [f64::INFINITY; MAX_MASSES];
            let mut g = f64::INFINITY;
            for (j, [fj, _, cp, cm]) in forces.into_iter().enumerate().take(n_mass) {
                let cap = if fj >= 0.0 { cp } else { cm };
                (f[j], capmin[j]) = (fj, cp.min(cm));
                g = g.min(cap - fj.abs());
            }
            (y, f, capmin, g)
        };
        // A bound on |f| over [a, b] from f at the ends: |f| peaks at an end where the force
        // is monotone; with both an amplifier and a current state the current lags the
        // voltage, which moves monotonically from v(a) to v(b), so the current stays
        // between i(a) and the ends' v/R (it relaxes toward v/R), and so does f, affine in it.
        let lagged = match (
            self.drive.i_amp,
            self.drive.i_current,
            &self.drive.params.actuator,
        ) {
            (Some(ka), Some(kc), Actuator::DcMotor { motor, .. }) => {
                Some((ka, kc, motor.resistance_ohm))
            }
            _ => None,
        };
        type PerMass = [f64; MAX_MASSES];
        let bound = |s: &Self, a: f64, b: f64, fa: &PerMass, capa: &PerMass, fb: &PerMass| {
            let mut peak0 = fa[0].abs().max(fb[0].abs());
            if let Some((ka, kc, r)) = lagged {
                let ya = s.stuck_state(&y0, inp, a);
                let v_b = s.stuck_state(&y0, inp, b)[ka];
                for i in [ya[ka] / r, v_b / r] {
                    let mut y = ya;
                    y[kc] = i;
                    peak0 = peak0.max(s.stuck_forces(&y, inp)[0][0].abs());
                }
            }
            let mut g = capa[0] - peak0;
            for j in 1..n_mass {
                g = g.min(capa[j] - fa[j].abs().max(fb[j].abs()));
            }
            g
        };
        let dt_end = t1 - t0;
        let (_, f_a0, capmin_a0, g0) = eval(self, 0.0);
        let (y_end, f_end, _, g_end) = eval(self, dt_end);
        // Find the first interval [a, b] with g(b) < 0 (or none).
        let mut bracket: Option<(f64, f64)> = None;
        if g0 < 0.0 {
            // Held although the force exceeds the capacity (the Zeno guard of `advance`):
            // as in the integrator, an event needs the value to go from ≥ 0 to < 0.
        } else if self.drive.i_clock.iter().all(Option::is_none) && lagged.is_none() {
            // Constant capacity: |f| peaks at an end, so g(end) ≥ 0 means no breakaway.
            if g_end < 0.0 {
                bracket = Some((0.0, dt_end));
            }
        } else {
            // (a, b, f(a), min cap(a), f(b)) per mass, left intervals on top.
            let mut stack: Vec<(f64, f64, PerMass, PerMass, PerMass)> =
                vec![(0.0, dt_end, f_a0, capmin_a0, f_end)];
            let mut evals = 0usize;
            while let Some((a, b, fa, capa, fb)) = stack.pop() {
                if bound(self, a, b, &fa, &capa, &fb) >= 0.0 {
                    continue;
                }
                let (_, _, _, gb) = eval(self, b);
                if gb < 0.0 {
                    bracket = Some((a, b));
                    break;
                }
                evals += 1;
                if b - a <= tol || evals > 400 {
                    continue;
                }
                let m = 0.5 * (a + b);
                let (_, fm, capm, _) = eval(self, m);
                stack.push((m, b, fm, capm, fb));
                stack.push((a, m, fa, capa, fm));
            }
        }
        let Some((mut a, mut b)) = bracket else {
            self.y = y_end;
            return None;
        };
        // Bisection on the event value: g(a) ≥ 0 > g(b).
        let mut yb = eval(self, b).0;
        for _ in 0..200 {
            if b - a <= tol {
                break;
            }
            let m = 0.5 * (a + b);
            let (ym, _, _, gm) = eval(self, m);
            if gm < 0.0 {
                b = m;
                yb = ym;
            } else {
                a = m;
            }
        }
        self.y = yb;
        Some(t0 + b)
    }

    /// Advance from `t0` to `t1` with the inputs held, handling stick/slip events.
    ///
    /// A stuck phase of the whole chain is solved in closed form
    /// (`stuck_closed_form`), as the rigid plant does. After a jump of the command
    /// voltage the first trial step is sized from the error seen after the last jump (as
    /// `model::Plant::advance`); error control itself is unchanged.
    ///
    /// The work of one call is bounded as in `model::Plant::advance`: at most `max_steps`
    /// integrator steps over all segments and `max_events` stick/slip transitions; a state
    /// that is not finite at the end is [`SimError::NonFinite`].
    pub fn advance(&mut self, inp: &Inputs, t0: f64, t1: f64) -> Result<(), SimError> {
        self.advance_polled(inp, t0, t1, &mut || false)
    }

    /// [`Self::advance`] asking `poll` every `POLL_EVERY_STEPS` integrator steps whether to
    /// stop (true: [`SimError::Interrupted`]).
    pub fn advance_polled(
        &mut self,
        inp: &Inputs,
        t0: f64,
        t1: f64,
        poll: &mut dyn FnMut() -> bool,
    ) -> Result<(), SimError> {
        hybrid::advance(self, inp, t0, t1, poll)
    }
}

impl<const N: usize> HybridPlant for DrivePlant<N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    type Input = Inputs;

    fn voltage(inp: &Inputs) -> f64 {
        inp.u_v
    }

    fn last_voltage(&mut self) -> &mut f64 {
        &mut self.u_last
    }

    fn options(&self) -> &IntegratorOptions {
        &self.integrator.options
    }

    fn state(&self) -> &[f64] {
        self.y.as_slice()
    }

    fn try_breakaway(&mut self, inp: &Inputs) {
        let n = self.drive.n_state;
        for j in 0..self.drive.n_mass {
            if self.modes[j] == MassMode::Stuck {
                let (f, cap) = self
                    .drive
                    .holding(&self.y.as_slice()[..n], inp, &self.modes, j);
                if f.abs() > cap {
                    self.modes[j] = MassMode::Slip(if f >= 0.0 { 1.0 } else { -1.0 });
                }
            }
        }
    }

    fn stuck_phase(&mut self, inp: &Inputs, t: f64, t1: f64) -> StuckPhase {
        let all_stuck = self.modes[..self.drive.n_mass]
            .iter()
            .all(|m| *m == MassMode::Stuck);
        if !(self.drive.closed_form_stuck && all_stuck) {
            return StuckPhase::Integrate;
        }
        match self.stuck_closed_form(inp, t, t1) {
            None => StuckPhase::HeldToEnd,
            Some(t_s) => StuckPhase::BreakawayAt(t_s),
        }
    }

    fn start_slip(&mut self, inp: &Inputs) {
        let j = self.event_mass(inp);
        let (f, _) = self.drive.holding(
            &self.y.as_slice()[..self.drive.n_state],
            inp,
            &self.modes,
            j,
        );
        self.modes[j] = MassMode::Slip(if f >= 0.0 { 1.0 } else { -1.0 });
    }

    fn integrate_segment(
        &mut self,
        inp: &Inputs,
        t: f64,
        t1: f64,
        after_jump: Option<f64>,
        steps: &mut usize,
        poll: &mut dyn FnMut() -> bool,
    ) -> Result<SegmentEnd, SimError> {
        let seg = Segment {
            drive: &self.drive,
            inp: *inp,
            modes: self.modes,
        };
        self.integrator.integrate_after_jump(
            &seg,
            t,
            t1,
            &mut self.y,
            &self.atol,
            after_jump,
            &mut self.jump_error_rate,
            steps,
            poll,
        )
    }

    fn resolve_event(&mut self, inp: &Inputs, force_stuck: bool) {
        let n = self.drive.n_state;
        let j = self.event_mass(inp);
        match self.modes[j] {
            MassMode::Free => {}
            MassMode::Slip(d) => {
                self.y[2 * j + 1] = 0.0;
                let (f, cap) = self
                    .drive
                    .holding(&self.y.as_slice()[..n], inp, &self.modes, j);
                self.modes[j] = if f.abs() <= cap || force_stuck {
                    // The breakaway-only clock restarts; the contact age runs on.
                    if let (Some(k), Some(m)) = (self.drive.i_clock[j], self.drive.clock_map(j)) {
                        if m.ageing().is_none() {
                            self.y[k] = 0.0;
                        }
                    }
                    MassMode::Stuck
                } else if f.signum() == d {
                    MassMode::Slip(d)
                } else {
                    MassMode::Slip(-d)
                };
            }
            MassMode::Stuck => {
                let (f, _) = self
                    .drive
                    .holding(&self.y.as_slice()[..n], inp, &self.modes, j);
                self.modes[j] = MassMode::Slip(if f >= 0.0 { 1.0 } else { -1.0 });
            }
        }
    }
}

/// A component plant of any size (the state is padded to the next supported size).
#[derive(Debug, Clone)]
pub enum AnyDrivePlant {
    /// Up to 4 states.
    N4(Box<DrivePlant<4>>),
    /// Up to 6 states.
    N6(Box<DrivePlant<6>>),
    /// Up to 8 states.
    N8(Box<DrivePlant<8>>),
    /// Up to 12 states.
    N12(Box<DrivePlant<12>>),
    /// Up to 16 states.
    N16(Box<DrivePlant<16>>),
    /// Up to 24 states.
    N24(Box<DrivePlant<24>>),
}

macro_rules! each {
    ($s:expr, $p:ident => $body:expr) => {
        match $s {
            AnyDrivePlant::N4($p) => $body,
            AnyDrivePlant::N6($p) => $body,
            AnyDrivePlant::N8($p) => $body,
            AnyDrivePlant::N12($p) => $body,
            AnyDrivePlant::N16($p) => $body,
            AnyDrivePlant::N24($p) => $body,
        }
    };
}

impl AnyDrivePlant {
    /// Validate, lay out and build a plant at rest at x = 0.
    pub fn new(params: DriveParams, options: IntegratorOptions) -> Result<Self, ConfigError> {
        let drive = Drive::new(params)?;
        Ok(match drive.n_state {
            0..=4 => Self::N4(Box::new(DrivePlant::new(drive, options)?)),
            5..=6 => Self::N6(Box::new(DrivePlant::new(drive, options)?)),
            7..=8 => Self::N8(Box::new(DrivePlant::new(drive, options)?)),
            9..=12 => Self::N12(Box::new(DrivePlant::new(drive, options)?)),
            13..=16 => Self::N16(Box::new(DrivePlant::new(drive, options)?)),
            _ => Self::N24(Box::new(DrivePlant::new(drive, options)?)),
        })
    }

    /// Advance with the inputs held.
    pub fn advance(&mut self, inp: &Inputs, t0: f64, t1: f64) -> Result<(), SimError> {
        each!(self, p => p.advance(inp, t0, t1))
    }

    /// Advance with the inputs held, asking `poll` whether to stop (see
    /// [`DrivePlant::advance_polled`]).
    pub fn advance_polled(
        &mut self,
        inp: &Inputs,
        t0: f64,
        t1: f64,
        poll: &mut dyn FnMut() -> bool,
    ) -> Result<(), SimError> {
        each!(self, p => p.advance_polled(inp, t0, t1, poll))
    }

    /// The model.
    pub fn drive(&self) -> &Drive {
        each!(self, p => &p.drive)
    }

    /// The used part of the state.
    pub fn state(&self) -> &[f64] {
        each!(self, p => &p.y.as_slice()[..p.drive.n_state])
    }

    /// Modes.
    pub fn modes(&self) -> [MassMode; MAX_MASSES] {
        each!(self, p => p.modes)
    }

    /// Place every mass at `x_m`, links relaxed; the drive side of a link with a dead band
    /// rests at `flank` × half its width from the driven side (±1: against the flank that
    /// pushes the driven side toward ±x, touching without force; 0: the centre), and every
    /// mass on the drive side of it moves with it.
    pub fn set_position(&mut self, x_m: f64, flank: f64) {
        each!(self, p => {
            let n_links = p.drive.n_mass - 1;
            for j in 0..p.drive.n_mass {
                // Mass j lies on the drive side of links j..n_links.
                let offset: f64 = p.drive.params.links[j.min(n_links)..n_links]
                    .iter()
                    .map(|l| 0.5 * flank * l.backlash_m)
                    .sum();
                p.y[2 * j] = x_m + offset;
            }
        })
    }

    /// Integrator work counters.
    pub fn stats(&self) -> Stats {
        each!(self, p => p.integrator.stats)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{Amplifier, DwellStatic, Gms, Link, LuGre, StaticMap, TableDahl};
    use crate::presets::seed_axis;

    fn configs() -> Vec<DriveParams> {
        let base = DriveParams::from_axis(&seed_axis());
        let fc = 30.4;
        let map = StaticMap {
            static_force_n: 1.4 * fc,
            coulomb_force_n: fc,
            viscous_n_s_per_m: 300.0,
            stribeck_velocity_m_per_s: 2e-3,
            stribeck_exponent: 1.5,
            asymmetry: 0.2,
            viscous_asymmetry: -0.1,
            dwell: Some(DwellStatic {
                rise_n: 5.0,
                time_constant_s: 0.1,
                slip_distance_m: None,
            }),
            memory_lag_s: Some(3e-3),
        };
        let mut modulation = Modulation {
            n_terms: 2,
            ..Modulation::default()
        };
        modulation.amplitude[..2].copy_from_slice(&[0.1, 0.05]);
        modulation.wavenumber_rad_per_m[..2].copy_from_slice(&[6e3, 2e4]);
        modulation.phase_rad[..2].copy_from_slice(&[0.3, -1.0]);
        let lugre = TableFriction::LuGre(LuGre {
            stiffness_n_per_m: 1e7,
            damping_n_s_per_m: 50.0,
            viscous_n_s_per_m: 20.0,
            coulomb_force_n: fc,
            static_force_n: 1.3 * fc,
            stribeck_velocity_m_per_s: 5e-4,
            asymmetry: 0.3,
        });
        let gms = TableFriction::Gms(Gms {
            n_elements: 3,
            stiffness_n_per_m: [3e7, 1e7, 3e6, 1.0, 1.0, 1.0, 1.0, 1.0],
            weights: [0.3, 0.3, 0.4, 0.0, 0.0, 0.0, 0.0, 0.0],
            coulomb_force_n: fc,
            static_force_n: 1.2 * fc,
            stribeck_velocity_m_per_s: 1e-3,
            viscous_n_s_per_m: 10.0,
            asymmetry: -0.25,
        });
        let dahl = TableFriction::Dahl(TableDahl {
            law: seed_axis().dahl,
            asymmetry: 0.4,
        });
        let link = Link {
            stiffness_n_per_m: 4.9e7,
            damping_n_s_per_m: 2e3,
            backlash_m: 0.0,
        };
        let mut out = vec![base];
        let mut c = base;
        if let Some(m) = c.motor_friction.as_mut() {
            m.dwell = map.dwell;
            m.memory_lag_s = map.memory_lag_s;
            m.asymmetry = 0.1;
        }
        c.motor_modulation = modulation;
        out.push(c);
        // The contact-ageing law on the motor map, and on the table map behind a link.
        let ageing = DwellStatic {
            slip_distance_m: Some(2e-6),
            ..map.dwell.expect("the test map has a dwell law")
        };
        if let Some(m) = c.motor_friction.as_mut() {
            m.dwell = Some(ageing);
        }
        out.push(c);
        let mut c = base;
        c.table_friction = TableFriction::Static(StaticMap {
            dwell: Some(ageing),
            ..map
        });
        c.n_links = 1;
        c.links[0] = link;
        out.push(c);
        for tf in [
            TableFriction::Static(map),
            lugre,
            gms,
            base.table_friction,
            dahl,
        ] {
            let mut c = base;
            c.table_friction = tf;
            out.push(c);
            c.table_modulation = modulation;
            out.push(c);
            c.n_links = 1;
            c.links[0] = link;
            out.push(c);
            c.links[0].backlash_m = 20e-6;
            out.push(c);
            c.n_links = 2;
            c.links[1] = link;
            c.amplifier = Some(Amplifier {
                bandwidth_hz: 300.0,
                slew_v_per_s: 1e9,
            });
            out.push(c);
        }
        let mut c = base;
        c.amplifier = Some(Amplifier {
            bandwidth_hz: 300.0,
            slew_v_per_s: 1e9,
        });
        if let Actuator::DcMotor { motor, .. } = &mut c.actuator {
            motor.quasi_static_current = true;
        }
        out.push(c);
        let mut c = base;
        c.actuator = Actuator::ForceDrive {
            gain_n_per_v: 20.0,
            drive_mass_kg: 0.5,
        };
        c.motor_friction = None;
        c.table_friction = lugre;
        c.n_links = 1;
        c.links[0] = link;
        c.amplifier = Some(Amplifier {
            bandwidth_hz: 1e3,
            slew_v_per_s: 1e9,
        });
        out.push(c);
        out
    }

    /// A resistance made invalid after validation: the stalled current u/R overflows while the
    /// mass is stuck (solved in closed form, no integrator step would notice); the state that
    /// is not finite is an error, not a result.
    #[test]
    fn a_state_that_is_not_finite_is_an_error_not_a_result() {
        let options = IntegratorOptions::default();
        let mut p = DrivePlant::<4>::new(
            Drive::new(DriveParams::from_axis(&seed_axis())).unwrap_or_else(|e| panic!("{e}")),
            options,
        )
        .unwrap_or_else(|e| panic!("{e}"));
        if let Actuator::DcMotor { motor, .. } = &mut p.drive.params.actuator {
            motor.resistance_ohm = 5e-324;
        }
        match p.advance(&Inputs::voltage(0.5), 0.0, 1e-3) {
            Err(SimError::NonFinite { t_s, .. }) => assert_eq!(t_s, 1e-3),
            other => panic!("expected NonFinite, got {other:?}"),
        }
    }

    /// A plant placed with its drive side at a flank of the dead band touches that flank
    /// without force: the link is at ±half the band, the contact force zero; every mass on
    /// the driven side of the band is at the given position.
    #[test]
    fn a_plant_placed_at_a_flank_rests_on_it_without_force() {
        let width = 12e-6;
        let mut params = DriveParams::from_axis(&seed_axis());
        params.n_links = 1;
        params.links[0] = Link {
            stiffness_n_per_m: 4e7,
            damping_n_s_per_m: 2e3,
            backlash_m: width,
        };
        for flank in [1.0, 0.0, -1.0, 0.25] {
            let mut p = AnyDrivePlant::new(params, IntegratorOptions::default())
                .unwrap_or_else(|e| panic!("{e}"));
            p.set_position(2e-3, flank);
            each!(&p, q => {
                let y = q.y.as_slice();
                assert_eq!(y[2], 2e-3);
                assert!((y[0] - y[2] - 0.5 * flank * width).abs() < 1e-18);
                assert!(q.drive.link_force(0, y).abs() < 1e-9);
            });
        }
    }

    #[test]
    fn analytic_jacobian_matches_forward_differences() {
        let mut seed = 0x9e37_79b9_7f4a_7c15_u64;
        let mut next = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        let mut checked = 0;
        for params in configs() {
            let drive = Drive::new(params).expect("valid");
            let n = drive.n_state;
            for trial in 0..200 {
                let mut y = SVector::<f64, 24>::zeros();
                for j in 0..drive.n_mass {
                    y[2 * j] = 1e-4 * next();
                    y[2 * j + 1] = 10f64.powf(-2.0 - 3.0 * next().abs()) * next().signum();
                }
                for k in 2 * drive.n_mass..drive.i_fric {
                    y[k] = next() * drive.scales[k];
                }
                for k in drive.i_clock.iter().flatten() {
                    y[*k] = 0.2 * next().abs();
                }
                for k in drive.i_fric..n {
                    y[k] = 1.3 * next() * drive.scales[k];
                }
                let mut modes = drive.initial_modes();
                for (j, m) in modes.iter_mut().enumerate().take(drive.n_mass) {
                    if *m == MassMode::Stuck && trial % 4 != 0 {
                        *m = MassMode::Slip(y[2 * j + 1].signum());
                    }
                }
                let inp = Inputs {
                    u_v: 3.0 * next(),
                    force_n: 2.0 * next(),
                    friction_scale: 1.0 + 0.2 * next(),
                };
                let seg = Segment {
                    drive: &drive,
                    inp,
                    modes,
                };
                let mut f0 = SVector::<f64, 24>::zeros();
                OdeSystem::<24>::rhs(&seg, &y, &mut f0);
                let mut fd = SMatrix::<f64, 24, 24>::zeros();
                seg.difference_jacobian(&y, &f0, &mut fd);
                let mut an = SMatrix::<f64, 24, 24>::zeros();
                OdeSystem::<24>::jacobian(&seg, &y, &mut an);
                for r in 0..n {
                    // Scale of the row: its largest entry times the column's state scale.
                    let row_scale = (0..n)
                        .map(|c| (fd[(r, c)] * drive.scales[c]).abs())
                        .fold(0.0, f64::max);
                    for c in 0..n {
                        let err = (an[(r, c)] - fd[(r, c)]).abs() * drive.scales[c];
                        assert!(
                            err <= 1e-4 * row_scale + 1e-3 * (fd[(r, c)] * drive.scales[c]).abs(),
                            "{params:?}\nrow {r} col {c}: analytic {} fd {} (row scale {row_scale})\ny {:?} modes {modes:?}",
                            an[(r, c)],
                            fd[(r, c)],
                            &y.as_slice()[..n]
                        );
                        if drive.arrowhead && r != c && r != 1 && c != 1 {
                            assert_eq!(an[(r, c)], 0.0, "not an arrowhead: row {r} col {c}");
                        }
                    }
                }
                checked += 1;
            }
        }
        assert!(checked > 1000);
    }

    /// The amplifier's voltage and the motor current of a stuck phase, in closed form, equal
    /// a fine classical Runge–Kutta integration of `dv/dt = clamp(ω(u − v), ±S)`,
    /// `di/dt = (v − R·i)/L`: with the amplifier's rate far from, equal to (the `t·e^{−at}`
    /// limit) and within 1e-9 of the current's rate, and slewing first, either way.
    #[test]
    fn the_stuck_amplifier_and_current_solve_their_equations() {
        let motor = seed_axis().motor;
        let rate = motor.resistance_ohm / motor.inductance_h;
        let two_pi = 2.0 * std::f64::consts::PI;
        let cases = [
            // (bandwidth, slew, v0, i0, u)
            (300.0, 1e9, 0.2, -0.1, 1.5),
            (rate / two_pi, 1e9, 1.0, 0.5, -2.0),
            (rate / two_pi * (1.0 + 1e-9), 1e9, -0.3, 0.0, 0.7),
            (5e3, 2e4, 0.0, 0.1, 3.0),
            (2e3, 5e3, 2.0, 0.6, -1.0),
        ];
        for (bw, slew, v0, i0, u) in cases {
            let a = Amplifier {
                bandwidth_hz: bw,
                slew_v_per_s: slew,
            };
            let f = |v: f64, i: f64| {
                (
                    (two_pi * bw * (u - v)).clamp(-slew, slew),
                    (v - motor.resistance_ohm * i) / motor.inductance_h,
                )
            };
            let (mut v, mut i, n, t_end) = (v0, i0, 400_000, 4e-4);
            let h = t_end / n as f64;
            for k in 1..=n {
                let (a1, b1) = f(v, i);
                let (a2, b2) = f(v + 0.5 * h * a1, i + 0.5 * h * b1);
                let (a3, b3) = f(v + 0.5 * h * a2, i + 0.5 * h * b2);
                let (a4, b4) = f(v + h * a3, i + h * b3);
                v += h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4);
                i += h / 6.0 * (b1 + 2.0 * b2 + 2.0 * b3 + b4);
                if k % 20_000 == 0 {
                    let t = k as f64 * h;
                    let (vc, ic) = amplifier_and_current(v0, i0, u, &a, &motor, t);
                    assert!(
                        (vc - v).abs() < 1e-9,
                        "bw {bw} slew {slew} t {t}: v {vc} vs {v}"
                    );
                    assert!(
                        (ic - i).abs() < 1e-9,
                        "bw {bw} slew {slew} t {t}: i {ic} vs {i}"
                    );
                    assert_eq!(vc, amplifier_voltage(v0, u, &a, t));
                }
            }
        }
    }

    /// A stuck phase solved in closed form agrees with the same plant integrated step by
    /// step (the closed form switched off): a command rising tick by tick through breakaway
    /// and back gives the same states at every tick (within the integrator's tolerances)
    /// and the same modes; one mass with an amplifier (with the current state and with a
    /// quasi-static current, slewing or not), and two masses joined by a spring with and
    /// without a dead band, with and without an amplifier and a dwell clock on the table.
    #[test]
    fn a_stuck_phase_in_closed_form_matches_integration() {
        let base = DriveParams::from_axis(&seed_axis());
        let mut checked = 0;
        let cases = [
            // (quasi-static current, bandwidth (0: no amplifier), slew, links, dead band)
            (false, 300.0, 1e9, 0, 0.0),
            (false, 3e3, 2e3, 0, 0.0),
            (true, 300.0, 1e9, 0, 0.0),
            (true, 3e3, 2e3, 0, 0.0),
            (false, 0.0, 0.0, 1, 0.0),
            (false, 0.0, 0.0, 1, 20e-6),
            (false, 300.0, 1e9, 1, 20e-6),
            (true, 300.0, 1e9, 1, 0.0),
        ];
        for (k_case, (quasi_static, bw, slew, links, band)) in cases.into_iter().enumerate() {
            let mut params = base;
            if bw > 0.0 {
                params.amplifier = Some(Amplifier {
                    bandwidth_hz: bw,
                    slew_v_per_s: slew,
                });
            }
            if let Actuator::DcMotor { motor, .. } = &mut params.actuator {
                motor.quasi_static_current = quasi_static;
            }
            params.n_links = links;
            params.links[0] = Link {
                stiffness_n_per_m: 4.9e7,
                damping_n_s_per_m: 2e3,
                backlash_m: band,
            };
            if links > 0 {
                // A table that can stick (a static map, not the seed axis's Dahl law); a
                // dwell clock on it in the last case.
                let fc = 30.4;
                params.table_friction = TableFriction::Static(StaticMap {
                    static_force_n: 1.4 * fc,
                    coulomb_force_n: fc,
                    viscous_n_s_per_m: 300.0,
                    stribeck_velocity_m_per_s: 2e-3,
                    stribeck_exponent: 1.5,
                    asymmetry: 0.0,
                    viscous_asymmetry: 0.0,
                    dwell: (k_case == 7).then_some(DwellStatic {
                        rise_n: 5.0,
                        time_constant_s: 0.01,
                        slip_distance_m: None,
                    }),
                    memory_lag_s: None,
                });
            }
            let drive = Drive::new(params).unwrap_or_else(|e| panic!("{e}"));
            assert!(drive.closed_form_stuck);
            let mut integrated = drive.clone();
            integrated.closed_form_stuck = false;
            let options = IntegratorOptions::default();
            let mut p = DrivePlant::<8>::new(drive, options).unwrap_or_else(|e| panic!("{e}"));
            let mut q = DrivePlant::<8>::new(integrated, options).unwrap_or_else(|e| panic!("{e}"));
            let (dt, n) = (1e-4, 600);
            let m = seed_axis().motor;
            let u_stall = seed_axis().motor_friction.static_torque_nm / m.torque_constant_nm_per_a
                * m.resistance_ohm;
            let (mut moved, mut all_stuck) = (0, 0);
            for k in 0..n {
                // Up to 1.3 times the stall voltage of the static friction and back, then a
                // reversal: stuck, breakaway, slip, sticking again.
                let phase = k as f64 / n as f64;
                let u = 1.3 * u_stall * (std::f64::consts::PI * 2.0 * phase).sin();
                let inp = Inputs::voltage(u);
                let (t0, t1) = (k as f64 * dt, (k + 1) as f64 * dt);
                p.advance(&inp, t0, t1).unwrap_or_else(|e| panic!("{e}"));
                q.advance(&inp, t0, t1).unwrap_or_else(|e| panic!("{e}"));
                let n_state = p.drive.n_state;
                for j in 0..n_state {
                    let tol = 20.0 * p.atol[j] + 1e-6 * q.y[j].abs();
                    assert!(
                        (p.y[j] - q.y[j]).abs() <= tol,
                        "bw {bw} slew {slew} quasi-static {quasi_static} tick {k} state {j}: \
                         {} vs {}",
                        p.y[j],
                        q.y[j]
                    );
                }
                assert_eq!(p.modes, q.modes, "case {k_case} tick {k}");
                if p.modes[..p.drive.n_mass]
                    .iter()
                    .all(|m| *m == MassMode::Stuck)
                {
                    all_stuck += 1;
                } else {
                    moved += 1;
                }
                checked += 1;
            }
            assert!(
                moved > 50 && all_stuck > 50,
                "case {k_case}: moved {moved}, all stuck {all_stuck} of {n} ticks"
            );
        }
        assert_eq!(checked, 4800);
    }
}
