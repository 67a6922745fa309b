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
