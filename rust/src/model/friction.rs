//! Friction laws as formulas with their partial derivatives. The direction `d` (±1) of the
//! current slip segment replaces `sgn v`, so each law is smooth inside a segment; the hybrid
//! stick/slip logic in `axis.rs` handles v = 0.
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
