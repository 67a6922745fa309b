//! Every friction law of the plants, as formulas with their partial derivatives: the rigid
//! plant's motor-side Stribeck torque and Dahl presliding force, and the component plant's
//! static maps (Stribeck, asymmetry, dwell-dependent breakaway), the table's Dahl, LuGre and
//! GMS laws (each with a direction asymmetry of its levels) and the position modulation of
//! friction levels. The direction `d` (±1) of the current slip segment replaces
//! `sgn v`, so each law is smooth inside a segment; the stick/slip logic of the plants
//! (`rigid.rs`, `component.rs`) handles v = 0.
use super::component_params::{
    DwellStatic, Gms, LuGre, Modulation, StaticMap, TableDahl, TableFriction,
};
use super::params::{DahlFriction, StribeckFriction};

impl StribeckFriction {
    /// Torque at motor speed `w` (rad/s) in a segment of direction `d`, and ∂T/∂w.
    #[inline]
    pub fn torque(&self, w: f64, d: f64) -> (f64, f64) {
        let ws = self.stribeck_velocity_rad_per_s;
        let delta = self.stribeck_exponent;
        let span = self.static_torque_nm - self.coulomb_torque_nm;
        // |w/ws| floored so that the derivative stays finite for δ < 1 at w = 0.
        let q = (w.abs() / ws).max(1e-12);
        let (e, de_dw) = if span == 0.0 {
            (0.0, 0.0)
        } else if delta == 2.0 {
            // exp(x) is exactly 0 in f64 for x < −745.2 (below half the smallest subnormal):
            // skip the call (the common case while slewing, |w| ≫ ws).
            let e = if q * q > 746.0 { 0.0 } else { (-q * q).exp() };
            (e, -e * 2.0 * q * w.signum() / ws)
        } else {
            let qd = q.powf(delta);
            let e = if qd > 746.0 { 0.0 } else { (-qd).exp() };
            (e, -e * delta * qd / q * w.signum() / ws)
        };
        let t = d * (self.coulomb_torque_nm + span * e) + self.viscous_nm_s_per_rad * w;
        let dt = d * span * de_dw + self.viscous_nm_s_per_rad;
        (t, dt)
    }
}

impl StribeckFriction {
    /// The exponent `q^δ` (q = |w|/ωs) above which `(T_s − T_c)·exp(−q^δ)` is below a
    /// quarter of the last bit of `T_c` (with a factor e of margin for the rounding of the
    /// exponent, the exponential and this threshold), so that `T_c + (T_s − T_c)·e` rounds to
    /// `T_c` exactly: [`Self::torque_value`] then skips the exponential and returns the same
    /// torque as [`Self::torque`], bit for bit. `+∞` (never skip) when `T_c = 0`.
    pub fn negligible_exponent(&self) -> f64 {
        let span = self.static_torque_nm - self.coulomb_torque_nm;
        if self.coulomb_torque_nm > 0.0 {
            (span / self.coulomb_torque_nm).ln() + 55.0 * std::f64::consts::LN_2 + 1.0
        } else {
            f64::INFINITY
        }
    }

    /// The torque of [`Self::torque`] alone (bit for bit the same value), without the
    /// exponential when its exponent exceeds `negligible` (from
    /// [`Self::negligible_exponent`]): the right-hand side needs the torque, not ∂T/∂w.
    #[inline]
    pub fn torque_value(&self, w: f64, d: f64, negligible: f64) -> f64 {
        let ws = self.stribeck_velocity_rad_per_s;
        let delta = self.stribeck_exponent;
        let span = self.static_torque_nm - self.coulomb_torque_nm;
        let q = (w.abs() / ws).max(1e-12);
        let e = if span == 0.0 {
            0.0
        } else if delta == 2.0 {
            let q2 = q * q;
            if q2 > 746.0 || q2 > negligible {
                0.0
            } else {
                (-q * q).exp()
            }
        } else {
            let qd = q.powf(delta);
            if qd > 746.0 || qd > negligible {
                0.0
            } else {
                (-qd).exp()
            }
        };
        d * (self.coulomb_torque_nm + span * e) + self.viscous_nm_s_per_rad * w
    }
}

impl DahlFriction {
    /// Rate dF/dt at velocity `v` and force `z` in a segment of direction `d`, with ∂/∂v and ∂/∂z.
    #[inline]
    pub fn rate(&self, v: f64, z: f64, d: f64) -> (f64, f64, f64) {
        let sigma = self.stiffness_n_per_m;
        let fc = self.coulomb_force_n;
        let q = 1.0 - z * d / fc;
        if self.exponent == 1.0 {
            (sigma * v * q, sigma * q, -sigma * v * d / fc)
        } else {
            let n = self.exponent;
            let aq = q.abs().max(1e-300);
            let g = aq.powf(n) * q.signum();
            let dg_dq = n * aq.powf(n - 1.0);
            (sigma * v * g, sigma * g, -sigma * v * dg_dq * d / fc)
        }
    }
}

/// β of the GMS elements: an element follows the motion exactly below β of its slip force.
pub const GMS_ELASTIC_FRACTION: f64 = 0.9;

pub(crate) fn modulation(m: &Modulation, x: f64) -> (f64, f64) {
    let mut f = 1.0;
    let mut df = 0.0;
    for k in 0..m.n_terms {
        let arg = m.wavenumber_rad_per_m[k] * x + m.phase_rad[k];
        f += m.amplitude[k] * arg.cos();
        df -= m.amplitude[k] * m.wavenumber_rad_per_m[k] * arg.sin();
    }
    (f, df)
}

pub(crate) fn smoothstep(s: f64) -> f64 {
    let s = s.clamp(0.0, 1.0);
    s * s * (3.0 - 2.0 * s)
}

impl StaticMap {
    /// Direction factor of the asymmetry for direction `d`.
    #[inline]
    pub(crate) fn dir(&self, d: f64) -> f64 {
        1.0 + self.asymmetry * d
    }

    /// Sliding force in direction `d` at velocity `v` with lagged velocity `w` and level
    /// scale `s` (modulation × stochastic factor).
    #[inline]
    pub fn sliding_force(&self, v: f64, w: f64, d: f64, s: f64) -> f64 {
        self.sliding_force_with(v, w, d, s, 0.0, f64::INFINITY)
    }

    /// The dwell law and its slip distance `D_c` when the dwell law is the contact-ageing
    /// law (None without a dwell law or with its breakaway-only form).
    #[inline]
    pub(crate) fn ageing(&self) -> Option<(&DwellStatic, f64)> {
        self.dwell
            .as_ref()
            .and_then(|dw| dw.slip_distance_m.map(|dc| (dw, dc)))
    }

    /// The contact-ageing law's rise of the static level at age `age_s`,
    /// `ΔFs·θ/(θ + γ)` (0 without the dwell law or with its breakaway-only form, where the
    /// rise enters the capacity alone).
    #[inline]
    pub fn sliding_rise(&self, age_s: f64) -> f64 {
        match self.ageing() {
            Some((dw, _)) => dw.rise_n * age_s / (age_s + dw.time_constant_s),
            None => 0.0,
        }
    }

    /// `∂/∂θ` of [`Self::sliding_rise`].
    #[inline]
    pub(crate) fn sliding_rise_slope(&self, age_s: f64) -> f64 {
        match self.ageing() {
            Some((dw, _)) => {
                let g = dw.time_constant_s;
                dw.rise_n * g / ((age_s + g) * (age_s + g))
            }
            None => 0.0,
        }
    }

    /// Rate of the dwell clock (the contact age θ) while the side moves at `v`: 0 for the
    /// breakaway-only law (the clock runs only while stuck), `1 − |v|·θ/D_c` for the
    /// contact-ageing law (Ruina's ageing law: θ grows at rest and relaxes to `D_c/|v|` over
    /// a slip of about `D_c`), and its partials (∂/∂θ, ∂/∂v).
    #[inline]
    pub(crate) fn clock_rate(&self, v: f64, age_s: f64) -> (f64, f64, f64) {
        match self.ageing() {
            Some((_, dc)) => (
                1.0 - v.abs() * age_s / dc,
                -v.abs() / dc,
                -v.signum() * age_s / dc,
            ),
            None => (0.0, 0.0, 0.0),
        }
    }

    /// Stribeck exponent above which the exponential term cannot change the sliding force
    /// (`e·(Fs − Fc)` below half an ulp of `Fc`; as `StribeckFriction::negligible_exponent`).
    /// `+∞` (never skip) when `Fc = 0`.
    pub fn negligible_exponent(&self) -> f64 {
        // The contact-ageing law raises the level by at most ΔFs.
        let most_rise = self.ageing().map_or(0.0, |(dw, _)| dw.rise_n);
        let span = self.static_force_n + most_rise - self.coulomb_force_n;
        if self.coulomb_force_n > 0.0 && span > 0.0 {
            (span / self.coulomb_force_n).ln() + 55.0 * std::f64::consts::LN_2 + 1.0
        } else {
            f64::INFINITY
        }
    }

    /// [`Self::sliding_force`] with the static level raised by `rise_n` (the contact-ageing
    /// law's [`Self::sliding_rise`]; 0 otherwise), without the exponential where its
    /// exponent exceeds `negligible` (from [`Self::negligible_exponent`]) or 746 (where it
    /// underflows to 0): the same force, bit for bit. The exponent `|w/vs|^δ` is a product
    /// for δ = 2.
    #[inline]
    pub fn sliding_force_with(
        &self,
        v: f64,
        w: f64,
        d: f64,
        s: f64,
        rise_n: f64,
        negligible: f64,
    ) -> f64 {
        let q = (w.abs() / self.stribeck_velocity_m_per_s).max(1e-300);
        let fs = self.static_force_n + rise_n;
        let e = if fs == self.coulomb_force_n {
            0.0
        } else {
            let qd = if self.stribeck_exponent == 2.0 {
                q * q
            } else {
                q.powf(self.stribeck_exponent)
            };
            if qd > 746.0 || qd > negligible {
                0.0
            } else {
                (-qd).exp()
            }
        };
        self.dir(d) * s * (self.coulomb_force_n + (fs - self.coulomb_force_n) * e) * d
            + (1.0 + self.viscous_asymmetry * d) * self.viscous_n_s_per_m * v
    }

    /// Largest force the map holds at rest, pushing in direction `d`, after a dwell `t_d`.
    #[inline]
    pub fn capacity(&self, d: f64, s: f64, dwell_s: f64) -> f64 {
        let rise = match &self.dwell {
            Some(dw) => dw.rise_n * dwell_s / (dwell_s + dw.time_constant_s),
            None => 0.0,
        };
        self.dir(d) * s * (self.static_force_n + rise)
    }

    /// Partial derivatives of the sliding force of a static map (as
    /// [`StaticMap::sliding_force`]) at velocity `v`, lagged velocity `w`, direction `d` and
    /// level `s`, the static level raised by `rise_n`: (∂/∂v, ∂/∂w, ∂/∂s, ∂/∂rise).
    pub(crate) fn sliding_partials(
        &self,
        w: f64,
        d: f64,
        s: f64,
        rise_n: f64,
    ) -> (f64, f64, f64, f64) {
        let dv = (1.0 + self.viscous_asymmetry * d) * self.viscous_n_s_per_m;
        let span = self.static_force_n + rise_n - self.coulomb_force_n;
        let q = (w.abs() / self.stribeck_velocity_m_per_s).max(1e-300);
        let (e, de_dw) = if span == 0.0 && self.sliding_rise(1.0) == 0.0 {
            (0.0, 0.0)
        } else {
            let delta = self.stribeck_exponent;
            let qd = q.powf(delta);
            let e = (-qd).exp();
            let dq_dw = if w.abs() / self.stribeck_velocity_m_per_s > 1e-300 {
                w.signum() / self.stribeck_velocity_m_per_s
            } else {
                0.0
            };
            (e, -e * delta * qd / q * dq_dw)
        };
        let dir = self.dir(d);
        (
            dv,
            dir * s * span * de_dw * d,
            dir * (self.coulomb_force_n + span * e) * d,
            dir * s * e * d,
        )
    }
}

/// The direction of sliding of the LuGre and GMS laws: the slip segment's direction `d`, or
/// `sgn v` where `d` is 0 (at rest or unknown; +1 at v = 0, where their rates vanish and the
/// level does not matter). (The Dahl law keeps its `d`, or 1 where `d` is 0: the plants
/// pass `d = 0` only at rest.)
#[inline]
pub(crate) fn sliding_direction(v: f64, d: f64) -> f64 {
    if d != 0.0 {
        d
    } else if v < 0.0 {
        -1.0
    } else {
        1.0
    }
}

/// The level factor `1 + a·d` of a direction asymmetry `a` in direction `d` (exactly 1 for
/// a = 0).
#[inline]
pub(crate) fn direction_factor(asymmetry: f64, d: f64) -> f64 {
    1.0 + asymmetry * d
}

impl TableDahl {
    /// The Dahl law in direction `d` at level scale `s`: Coulomb force `Fc·s·(1 + a·d)`
    /// (exactly `Fc·s` for a = 0).
    #[inline]
    pub(crate) fn scaled(&self, s: f64, d: f64) -> DahlFriction {
        DahlFriction {
            coulomb_force_n: self.law.coulomb_force_n * s * direction_factor(self.asymmetry, d),
            ..self.law
        }
    }
}

impl LuGre {
    /// `g(v)` at level scale `s` (the caller includes the direction factor in `s`).
    pub(crate) fn g(&self, v: f64, s: f64) -> f64 {
        let q = v / self.stribeck_velocity_m_per_s;
        s * (self.coulomb_force_n + (self.static_force_n - self.coulomb_force_n) * (-q * q).exp())
    }
}

impl Gms {
    /// `s(v)` at level scale `s` (the caller includes the direction factor in `s`).
    pub(crate) fn slip_force(&self, v: f64, s: f64) -> f64 {
        let q = v / self.stribeck_velocity_m_per_s;
        s * (self.coulomb_force_n + (self.static_force_n - self.coulomb_force_n) * (-q * q).exp())
    }
}

/// Element rate of a GMS element with deflection `z`, limit `z_max`, velocity `v`.
#[inline]
pub(crate) fn gms_rate(z: f64, z_max: f64, v: f64) -> f64 {
    if v == 0.0 {
        return 0.0;
    }
    let w = v.signum() * z / z_max;
    let beta = GMS_ELASTIC_FRACTION;
    let alpha = if w <= beta {
        0.0
    } else if w <= 1.0 {
        smoothstep((w - beta) / (1.0 - beta))
    } else {
        w
    };
    v * (1.0 - alpha)
}

impl TableFriction {
    /// Number of internal states (Dahl, LuGre: 1; GMS: one per element; static maps: 0).
    pub fn n_states(&self) -> usize {
        match self {
            Self::Dahl(_) | Self::LuGre(_) => 1,
            Self::Gms(g) => g.n_elements,
            Self::None | Self::Static(_) => 0,
        }
    }

    /// Force of the dynamic part (Dahl, LuGre, GMS; 0 for static maps and none) at states
    /// `z`, velocity `v`, slip direction `d` (0: at rest or unknown) and level scale `s`;
    /// writes the state rates to `dfric` when given. The direction asymmetry of each law
    /// scales its levels by `1 + a·d`: Dahl with the `d` it uses for `sgn v` (1 where `d` is
    /// 0, at rest), LuGre and GMS with `d`, or `sgn v` where `d` is 0.
    pub fn dynamic(&self, z: &[f64], v: f64, d: f64, s: f64, dfric: Option<&mut [f64]>) -> f64 {
        match self {
            Self::Dahl(p) => {
                if let Some(dz) = dfric {
                    // The direction d of the slip segment replaces sgn v (1 at rest, where
                    // the rate σ·v·(…) is 0 whatever the direction).
                    let dd = if d == 0.0 { 1.0 } else { d };
                    dz[0] = p.scaled(s, dd).rate(v, z[0], dd).0;
                }
                z[0]
            }
            Self::LuGre(p) => {
                let g = p.g(
                    v,
                    s * direction_factor(p.asymmetry, sliding_direction(v, d)),
                );
                let zdot = v - p.stiffness_n_per_m * v.abs() * z[0] / g;
                if let Some(dz) = dfric {
                    dz[0] = zdot;
                }
                p.stiffness_n_per_m * z[0] + p.damping_n_s_per_m * zdot + p.viscous_n_s_per_m * v
            }
            Self::Gms(p) => {
                let sv = p.slip_force(
                    v,
                    s * direction_factor(p.asymmetry, sliding_direction(v, d)),
                );
                let mut f = p.viscous_n_s_per_m * v;
                let mut rates = dfric;
                for i in 0..p.n_elements {
                    let z_max = p.weights[i] * sv / p.stiffness_n_per_m[i];
                    if let Some(dz) = rates.as_deref_mut() {
                        dz[i] = gms_rate(z[i], z_max, v);
                    }
                    f += p.stiffness_n_per_m[i] * z[i];
                }
                f
            }
            Self::None | Self::Static(_) => 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::StribeckFriction;

    #[test]
    fn torque_value_is_the_torque_bit_for_bit() {
        let mut n_skipped = 0;
        for (tc, ts, b, ws, delta) in [
            (0.10e-3, 0.12e-3, 2.0e-8, 10.0, 2.0),
            (0.10e-3, 0.12e-3, 0.0, 10.0, 2.0),
            (1e-300, 5.0, 0.0, 1.0, 2.0),
            (1.0, 1.0 + 1e-9, 0.0, 0.3, 2.0),
            (0.0, 0.1, 1e-6, 2.0, 2.0),
            (2.0, 9.0, 1e-3, 50.0, 0.5),
            (2.0, 9.0, 0.0, 50.0, 1.3),
            (3.0, 3.0, 1e-3, 5.0, 4.0),
        ] {
            let f = StribeckFriction {
                static_torque_nm: ts,
                coulomb_torque_nm: tc,
                viscous_nm_s_per_rad: b,
                stribeck_velocity_rad_per_s: ws,
                stribeck_exponent: delta,
            };
            let neg = f.negligible_exponent();
            for k in 0..20_000 {
                // Speeds from 0 to 40 ωs, finely around the threshold.
                let w = ws * 40.0 * (k as f64 / 20_000.0).powi(2);
                for d in [1.0, -1.0] {
                    for w in [w, -w] {
                        let (t, _) = f.torque(w, d);
                        let v = f.torque_value(w, d, neg);
                        assert_eq!(t.to_bits(), v.to_bits(), "{f:?} w {w} d {d}");
                        let q = (w.abs() / ws).max(1e-12);
                        if q.powf(delta) > neg && q.powf(delta) <= 746.0 {
                            n_skipped += 1;
                        }
                    }
                }
            }
        }
        assert!(n_skipped > 10_000, "{n_skipped}");
    }
}

/// The direction asymmetry of the table laws (Dahl, LuGre, GMS): exactly the symmetric law
/// at a = 0, the levels `Fc·(1 ± a)` in steady sliding, and passivity for a ≠ 0.
#[cfg(test)]
mod asymmetry_tests {
    use super::{sliding_direction, DahlFriction};
    use crate::integrate::IntegratorOptions;
    use crate::model::component_params::{
        Gms, LuGre, Modulation, TableDahl, TableFriction, MAX_GMS_ELEMENTS,
    };
    use crate::model::friction_response;

    const FC: f64 = 30.4;

    fn dahl(a: f64, exponent: f64) -> TableFriction {
        TableFriction::Dahl(TableDahl {
            law: DahlFriction {
                coulomb_force_n: FC,
                stiffness_n_per_m: 7.5e7,
                exponent,
            },
            asymmetry: a,
        })
    }

    /// LuGre without bristle damping (σ1 = 0: the force is then passive for any positive
    /// g, which the asymmetry keeps positive).
    fn lugre(a: f64) -> TableFriction {
        TableFriction::LuGre(LuGre {
            stiffness_n_per_m: 1e7,
            damping_n_s_per_m: 0.0,
            viscous_n_s_per_m: 20.0,
            coulomb_force_n: FC,
            static_force_n: 1.3 * FC,
            stribeck_velocity_m_per_s: 5e-4,
            asymmetry: a,
        })
    }

    fn gms(a: f64) -> TableFriction {
        let mut k = [1.0; MAX_GMS_ELEMENTS];
        let mut w = [0.0; MAX_GMS_ELEMENTS];
        k[..3].copy_from_slice(&[3e7, 1e7, 3e6]);
        w[..3].copy_from_slice(&[0.3, 0.3, 0.4]);
        TableFriction::Gms(Gms {
            n_elements: 3,
            stiffness_n_per_m: k,
            weights: w,
            coulomb_force_n: FC,
            static_force_n: 1.2 * FC,
            stribeck_velocity_m_per_s: 1e-3,
            viscous_n_s_per_m: 10.0,
            asymmetry: a,
        })
    }

    fn laws(a: f64) -> [TableFriction; 4] {
        [dahl(a, 1.0), dahl(a, 2.5), lugre(a), gms(a)]
    }

    /// Saturation deflection of each state (Dahl: a force; LuGre, GMS: lengths).
    fn state_scale(tf: &TableFriction, i: usize) -> f64 {
        match tf {
            TableFriction::Dahl(_) => FC,
            TableFriction::LuGre(l) => FC / l.stiffness_n_per_m,
            TableFriction::Gms(g) => g.weights[i] * FC / g.stiffness_n_per_m[i],
            _ => 1.0,
        }
    }

    /// Stored (spring) energy of the states, J.
    fn storage(tf: &TableFriction, z: &[f64]) -> f64 {
        match tf {
            TableFriction::Dahl(d) => z[0] * z[0] / (2.0 * d.law.stiffness_n_per_m),
            TableFriction::LuGre(l) => 0.5 * l.stiffness_n_per_m * z[0] * z[0],
            TableFriction::Gms(g) => (0..g.n_elements)
                .map(|i| 0.5 * g.stiffness_n_per_m[i] * z[i] * z[i])
                .sum(),
            _ => 0.0,
        }
    }

    fn xorshift(seed: &mut u64) -> f64 {
        *seed ^= *seed << 13;
        *seed ^= *seed >> 7;
        *seed ^= *seed << 17;
        (*seed >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }

    /// a = 0 is today's law bit for bit: the force and rates of each law written out as
    /// before the asymmetry existed, at random states, velocities, directions and levels.
    #[test]
    fn zero_asymmetry_is_the_symmetric_law_bit_for_bit() {
        let mut seed = 0x2545_f491_4f6c_dd1d_u64;
        for tf in laws(0.0) {
            for _ in 0..20_000 {
                let n = tf.n_states();
                let mut z = [0.0; MAX_GMS_ELEMENTS];
                for (i, zi) in z.iter_mut().enumerate().take(n) {
                    *zi = 1.5 * xorshift(&mut seed) * state_scale(&tf, i);
                }
                let v = 10f64.powf(-6.0 + 5.0 * xorshift(&mut seed).abs())
                    * xorshift(&mut seed).signum();
                let d = [0.0, 1.0, -1.0][(xorshift(&mut seed).abs() * 3.0) as usize % 3];
                let s = 1.0 + 0.3 * xorshift(&mut seed);
                let mut rates = [0.0; MAX_GMS_ELEMENTS];
                let f = tf.dynamic(&z[..n], v, d, s, Some(&mut rates[..n]));
                let mut old_rates = [0.0; MAX_GMS_ELEMENTS];
                let old_f = match &tf {
                    TableFriction::Dahl(p) => {
                        let scaled = DahlFriction {
                            coulomb_force_n: p.law.coulomb_force_n * s,
                            ..p.law
                        };
                        let dd = if d == 0.0 { 1.0 } else { d };
                        old_rates[0] = scaled.rate(v, z[0], dd).0;
                        z[0]
                    }
                    TableFriction::LuGre(p) => {
                        let g = p.g(v, s);
                        let zdot = v - p.stiffness_n_per_m * v.abs() * z[0] / g;
                        old_rates[0] = zdot;
                        p.stiffness_n_per_m * z[0]
                            + p.damping_n_s_per_m * zdot
                            + p.viscous_n_s_per_m * v
                    }
                    TableFriction::Gms(p) => {
                        let sv = p.slip_force(v, s);
                        let mut f = p.viscous_n_s_per_m * v;
                        for i in 0..p.n_elements {
                            let z_max = p.weights[i] * sv / p.stiffness_n_per_m[i];
                            old_rates[i] = super::gms_rate(z[i], z_max, v);
                            f += p.stiffness_n_per_m[i] * z[i];
                        }
                        f
                    }
                    _ => unreachable!(),
                };
                assert_eq!(f.to_bits(), old_f.to_bits(), "{tf:?} v {v} d {d}");
                for i in 0..n {
                    assert_eq!(rates[i].to_bits(), old_rates[i].to_bits(), "{tf:?} v {v}");
                }
            }
        }
    }

    /// The power absorbed by each law, `F·v − V̇` with V the spring energy of its states, is
    /// never negative, for asymmetries up to the bounds, at random states (inside and beyond
    /// saturation), velocities and level scales.
    #[test]
    fn asymmetric_laws_absorb_power_at_every_state() {
        let mut seed = 0x9e37_79b9_7f4a_7c15_u64;
        let mut checked = 0;
        for a in [0.9, 0.5, -0.3, -0.9] {
            for tf in laws(a) {
                for _ in 0..20_000 {
                    let n = tf.n_states();
                    let mut z = [0.0; MAX_GMS_ELEMENTS];
                    for (i, zi) in z.iter_mut().enumerate().take(n) {
                        *zi = 2.5 * xorshift(&mut seed) * state_scale(&tf, i);
                    }
                    let v = 10f64.powf(-6.0 + 5.0 * xorshift(&mut seed).abs())
                        * xorshift(&mut seed).signum();
                    let d = sliding_direction(v, 0.0);
                    let s = 1.0 + 0.3 * xorshift(&mut seed);
                    let mut rates = [0.0; MAX_GMS_ELEMENTS];
                    let f = tf.dynamic(&z[..n], v, d, s, Some(&mut rates[..n]));
                    let v_dot = match &tf {
                        TableFriction::Dahl(p) => z[0] * rates[0] / p.law.stiffness_n_per_m,
                        TableFriction::LuGre(p) => p.stiffness_n_per_m * z[0] * rates[0],
                        TableFriction::Gms(p) => (0..n)
                            .map(|i| p.stiffness_n_per_m[i] * z[i] * rates[i])
                            .sum(),
                        _ => unreachable!(),
                    };
                    let absorbed = f * v - v_dot;
                    assert!(
                        absorbed >= -1e-12 * (f * v).abs().max(v_dot.abs()),
                        "{tf:?}: F·v − V̇ = {absorbed} at z {:?} v {v}",
                        &z[..n]
                    );
                    checked += 1;
                }
            }
        }
        assert_eq!(checked, 4 * 4 * 20_000);
    }

    fn trapezoid_work(f: &[f64], x: &[f64]) -> f64 {
        (1..f.len())
            .map(|k| 0.5 * (f[k] + f[k - 1]) * (x[k] - x[k - 1]))
            .sum()
    }

    /// Presliding rest stiffness of a law (its force per displacement at rest), N/m.
    fn rest_stiffness(tf: &TableFriction) -> f64 {
        match tf {
            TableFriction::Dahl(d) => d.law.stiffness_n_per_m,
            TableFriction::LuGre(l) => l.stiffness_n_per_m,
            TableFriction::Gms(g) => g.stiffness_n_per_m[..g.n_elements].iter().sum(),
            _ => unreachable!(),
        }
    }

    /// The law driven along `x = A·sin(ωt)` for `periods` periods from relaxed states, by a
    /// classical fourth-order Runge–Kutta method of `steps` fixed steps per period (not the
    /// crate's integrator), with the work `∫F·v dt` done on it as an extra state. Returns
    /// (work, J; the states at the end).
    fn cycle_rk4(
        tf: &TableFriction,
        amp: f64,
        w: f64,
        periods: usize,
        steps: usize,
    ) -> (f64, [f64; 9]) {
        let n = tf.n_states();
        let rhs = |t: f64, y: &[f64; 9]| -> [f64; 9] {
            let v = amp * w * (w * t).cos();
            let mut rates = [0.0; MAX_GMS_ELEMENTS];
            let f = tf.dynamic(
                &y[..n],
                v,
                sliding_direction(v, 0.0),
                1.0,
                Some(&mut rates[..n]),
            );
            let mut dy = [0.0; 9];
            dy[..n].copy_from_slice(&rates[..n]);
            dy[8] = f * v;
            dy
        };
        let h = 2.0 * std::f64::consts::PI / w / steps as f64;
        let mut y = [0.0; 9];
        for k in 0..periods * steps {
            let t = k as f64 * h;
            let add = |y: &[f64; 9], d: &[f64; 9], c: f64| {
                let mut o = *y;
                for i in 0..9 {
                    o[i] += c * d[i];
                }
                o
            };
            let k1 = rhs(t, &y);
            let k2 = rhs(t + 0.5 * h, &add(&y, &k1, 0.5 * h));
            let k3 = rhs(t + 0.5 * h, &add(&y, &k2, 0.5 * h));
            let k4 = rhs(t + h, &add(&y, &k3, h));
            for i in 0..9 {
                y[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
            }
        }
        let mut z = [0.0; 9];
        z[..n].copy_from_slice(&y[..n]);
        (y[8], z)
    }

    /// Closed displacement cycles (sinusoids of 5 periods from relaxed states, integrated by
    /// a fixed-step RK4 of their own): the work done on the friction exceeds the energy left
    /// in its springs, for presliding amplitudes (a tenth of the saturation deflection) and
    /// sliding ones (50 times), for asymmetries of either sign and the symmetric law.
    #[test]
    fn closed_cycles_dissipate_energy() {
        let w = 2.0 * std::f64::consts::PI * 2.0;
        for a in [0.6, 0.0, -0.8] {
            for tf in laws(a) {
                for amp_rel in [0.1, 50.0] {
                    let amp = amp_rel * FC / rest_stiffness(&tf);
                    let (work, z) = cycle_rk4(&tf, amp, w, 5, 20_000);
                    let left = storage(&tf, &z[..tf.n_states()]);
                    let dissipated = work - left;
                    // RK4's error on the work: far below the energy turned over, k·A².
                    let turnover = rest_stiffness(&tf) * amp * amp;
                    assert!(
                        dissipated >= -1e-9 * turnover,
                        "{tf:?} amplitude {amp} m: work {work} J, energy left {left} J"
                    );
                    if amp_rel > 1.0 {
                        // Sliding: most of the 5 loops' Coulomb work 5·4·A·Fc is dissipated.
                        assert!(dissipated > 0.5 * 20.0 * amp * FC, "{tf:?}: {dissipated} J");
                    }
                }
            }
        }
    }

    /// The sliding loop of the crate's integrator (`friction_response`): over the last of 5
    /// periods of `x = A·sin(ωt)` with A = 500 saturation deflections, the loop's area less
    /// the viscous work `π·ω·A²·σ2` is `2A·(Fc(1 + a) + Fc(1 − a)) = 4·A·Fc` less the
    /// presliding rounding at the reversals (the Dahl law of exponent n > 1 and the GMS
    /// yield approach their levels as a power of the displacement, hence the large A).
    #[test]
    fn sliding_loop_area_is_the_coulomb_work() {
        let opts = IntegratorOptions {
            rtol: 1e-9,
            atol_position_m: 1e-14,
            ..IntegratorOptions::default()
        };
        let m = Modulation::default();
        for a in [0.6, -0.8] {
            for tf in laws(a) {
                let amp = 500.0 * FC / rest_stiffness(&tf);
                let (freq, periods, per_period) = (2.0, 5usize, 4000usize);
                let n = periods * per_period + 1;
                let w = 2.0 * std::f64::consts::PI * freq;
                let t: Vec<f64> = (0..n)
                    .map(|k| k as f64 / (freq * per_period as f64))
                    .collect();
                let x: Vec<f64> = t.iter().map(|t| amp * (w * t).sin()).collect();
                let v: Vec<f64> = t.iter().map(|t| amp * w * (w * t).cos()).collect();
                let f = friction_response(&tf, &m, &t, &x, &v, &opts)
                    .unwrap_or_else(|e| panic!("{tf:?}: {e}"));
                let s = (periods - 1) * per_period;
                let viscous = match &tf {
                    TableFriction::LuGre(l) => l.viscous_n_s_per_m,
                    TableFriction::Gms(g) => g.viscous_n_s_per_m,
                    _ => 0.0,
                };
                let loop_work = trapezoid_work(&f[s..], &x[s..])
                    - viscous * std::f64::consts::PI * w * amp * amp;
                let coulomb_loop = 4.0 * amp * FC;
                assert!(
                    loop_work > 0.95 * coulomb_loop && loop_work < 1.01 * coulomb_loop,
                    "{tf:?}: loop {loop_work} J, 4·A·Fc = {coulomb_loop} J"
                );
            }
        }
    }

    /// Sliding at constant velocity, well above the Stribeck velocity (its exponential is
    /// exactly 0): the force settles at `Fc·(1 + a)` in + and `−Fc·(1 − a)` in − (plus the
    /// viscous term), and that force is the law's fixed point (Dahl: exactly; LuGre, GMS: to
    /// the rounding of `σ·(F/σ)`).
    #[test]
    fn steady_sliding_force_is_the_asymmetric_level() {
        let opts = IntegratorOptions {
            rtol: 1e-10,
            ..IntegratorOptions::default()
        };
        let m = Modulation::default();
        for a in [0.35, -0.6, 0.9] {
            for tf in laws(a) {
                // Exponent n > 1 approaches the level as a power of the displacement (not
                // within a run of 10 ms): its fixed point is checked below alone.
                let settles = !matches!(&tf, TableFriction::Dahl(p) if p.law.exponent != 1.0);
                for d in [1.0, -1.0] {
                    let v = 0.05 * d;
                    let level = FC * (1.0 + a * d);
                    let viscous = match &tf {
                        TableFriction::LuGre(l) => l.viscous_n_s_per_m,
                        TableFriction::Gms(g) => g.viscous_n_s_per_m,
                        _ => 0.0,
                    };
                    let expected = d * level + viscous * v;
                    let n = 201;
                    let t: Vec<f64> = (0..n).map(|k| k as f64 * 1e-4).collect();
                    let x: Vec<f64> = t.iter().map(|t| v * t).collect();
                    let vv = vec![v; n];
                    let f = friction_response(&tf, &m, &t, &x, &vv, &opts)
                        .unwrap_or_else(|e| panic!("{tf:?}: {e}"));
                    let end = f[n - 1];
                    // The GMS yield approaches the slip force as a power of the displacement.
                    let tol = if matches!(tf, TableFriction::Gms(_)) {
                        1e-4
                    } else {
                        1e-9
                    };
                    assert!(
                        !settles || (end - expected).abs() <= tol * FC,
                        "{tf:?} v {v}: {end} N, expected {expected} N"
                    );
                    // The fixed point itself.
                    let nz = tf.n_states();
                    let mut z = [0.0; MAX_GMS_ELEMENTS];
                    match &tf {
                        TableFriction::Dahl(_) => z[0] = d * level,
                        TableFriction::LuGre(l) => z[0] = d * level / l.stiffness_n_per_m,
                        TableFriction::Gms(g) => {
                            for (i, zi) in z.iter_mut().enumerate().take(g.n_elements) {
                                *zi = d * g.weights[i] * level / g.stiffness_n_per_m[i];
                            }
                        }
                        _ => unreachable!(),
                    }
                    let mut rates = [0.0; MAX_GMS_ELEMENTS];
                    let f = tf.dynamic(&z[..nz], v, d, 1.0, Some(&mut rates[..nz]));
                    assert!(
                        (f - expected).abs() <= 1e-12 * FC,
                        "{tf:?}: {f} vs {expected}"
                    );
                    for (i, r) in rates[..nz].iter().enumerate() {
                        let tol = match &tf {
                            TableFriction::Dahl(_) => 0.0,
                            _ => 4.0 * f64::EPSILON * v.abs(),
                        };
                        assert!(r.abs() <= tol, "{tf:?}: rate[{i}] = {r} at the fixed point");
                    }
                }
            }
        }
    }

    #[test]
    fn asymmetry_out_of_range_is_named() {
        for tf in [dahl(0.95, 1.0), lugre(-1.0), gms(f64::NAN)] {
            let e = tf.validate().expect_err("out of range").to_string();
            assert!(e.starts_with("asymmetry = "), "{e}");
            assert!(e.contains("in [-9e-1, 9e-1]"), "{e}");
        }
        for tf in laws(0.9).into_iter().chain(laws(-0.9)) {
            tf.validate().unwrap_or_else(|e| panic!("{e}"));
        }
    }
}
