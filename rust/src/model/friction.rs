//! Every friction law of the plants, as formulas with their partial derivatives: the rigid
//! plant's motor-side Stribeck torque and Dahl presliding force, and the component plant's
//! static maps (Stribeck, asymmetry, dwell-dependent breakaway), LuGre, GMS and the position
//! modulation of friction levels. The direction `d` (±1) of the current slip segment replaces
//! `sgn v`, so each law is smooth inside a segment; the stick/slip logic of the plants
//! (`rigid.rs`, `component.rs`) handles v = 0.
use super::component_params::{Gms, LuGre, Modulation, StaticMap, TableFriction};
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
        self.sliding_force_with(v, w, d, s, f64::INFINITY)
    }

    /// Stribeck exponent above which the exponential term cannot change the sliding force
    /// (`e·(Fs − Fc)` below half an ulp of `Fc`; as `StribeckFriction::negligible_exponent`).
    /// `+∞` (never skip) when `Fc = 0`.
    pub fn negligible_exponent(&self) -> f64 {
        let span = self.static_force_n - self.coulomb_force_n;
        if self.coulomb_force_n > 0.0 && span > 0.0 {
            (span / self.coulomb_force_n).ln() + 55.0 * std::f64::consts::LN_2 + 1.0
        } else {
            f64::INFINITY
        }
    }

    /// [`Self::sliding_force`] without the exponential where its exponent exceeds
    /// `negligible` (from [`Self::negligible_exponent`]) or 746 (where it underflows to 0):
    /// the same force, bit for bit. The exponent `|w/vs|^δ` is a product for δ = 2.
    #[inline]
    pub fn sliding_force_with(&self, v: f64, w: f64, d: f64, s: f64, negligible: f64) -> f64 {
        let q = (w.abs() / self.stribeck_velocity_m_per_s).max(1e-300);
        let e = if self.static_force_n == self.coulomb_force_n {
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
        self.dir(d)
            * s
            * (self.coulomb_force_n + (self.static_force_n - self.coulomb_force_n) * e)
            * d
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
    /// level `s`: (∂/∂v, ∂/∂w, ∂/∂s).
    pub(crate) fn sliding_partials(&self, w: f64, d: f64, s: f64) -> (f64, f64, f64) {
        let dv = (1.0 + self.viscous_asymmetry * d) * self.viscous_n_s_per_m;
        let span = self.static_force_n - self.coulomb_force_n;
        let q = (w.abs() / self.stribeck_velocity_m_per_s).max(1e-300);
        let (e, de_dw) = if span == 0.0 {
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
        )
    }
}

impl LuGre {
    pub(crate) fn g(&self, v: f64, s: f64) -> f64 {
        let q = v / self.stribeck_velocity_m_per_s;
        s * (self.coulomb_force_n + (self.static_force_n - self.coulomb_force_n) * (-q * q).exp())
    }
}

impl Gms {
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
    /// writes the state rates to `dfric` when given.
    pub fn dynamic(&self, z: &[f64], v: f64, d: f64, s: f64, dfric: Option<&mut [f64]>) -> f64 {
        match self {
            Self::Dahl(p) => {
                let scaled = DahlFriction {
                    coulomb_force_n: p.coulomb_force_n * s,
                    ..*p
                };
                if let Some(dz) = dfric {
                    // The direction d of the slip segment replaces sgn v (1 when free).
                    let dd = if d == 0.0 { 1.0 } else { d };
                    dz[0] = scaled.rate(v, z[0], dd).0;
                }
                z[0]
            }
            Self::LuGre(p) => {
                let g = p.g(v, s);
                let zdot = v - p.stiffness_n_per_m * v.abs() * z[0] / g;
                if let Some(dz) = dfric {
                    dz[0] = zdot;
                }
                p.stiffness_n_per_m * z[0] + p.damping_n_s_per_m * zdot + p.viscous_n_s_per_m * v
            }
            Self::Gms(p) => {
                let sv = p.slip_force(v, s);
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
