//! Solve with the iteration matrix `W = c·I − J` of a system whose Jacobian is an
//! *arrowhead*: every nonzero off-diagonal entry lies in one row `k` or one column `k` (the
//! hub). The rigid axis is one (hub: the velocity; position, Dahl force and current each
//! couple only to it), and so is every diagonal Jacobian.
//!
//! Elimination of the leaves (every index but the hub) into the hub row leaves one scalar
//! equation: with `d_j = c − J_jj`,
//! `s = (c − J_kk) − Σ_j J_kj·J_jk / d_j`,
//! `x_k = (b_k + Σ_j J_kj·b_j / d_j) / s`,  `x_j = (b_j + J_jk·x_k) / d_j`.
//! That is Gaussian elimination in the order leaves-then-hub, without pivoting; it is used
//! only when every leaf pivot is at least `c/2` (a leaf's own decay `J_jj` is at most `c/2`),
//! so no multiplier exceeds `2·|J_kj|/c` and the factorisation is as stable as the hub's pivot
//! `s` itself (a small `s` means `W` is nearly singular, for any pivoting). Otherwise
//! [`Arrow::new`] declines and the integrator uses the dense [`super::Lu`]. It costs about a
//! fifth of the dense LU's instructions on the 4×4 iteration matrix (factorisation and six
//! solves per step).
use nalgebra::{SMatrix, SVector};

/// The factorised arrowhead `c·I − J` (see the module documentation).
#[derive(Debug, Clone, Copy)]
pub struct Arrow<const N: usize> {
    hub: usize,
    /// `1/d_j` for each leaf (unused at the hub).
    inv_d: [f64; N],
    /// `J_kj / d_j` for each leaf (0 at the hub).
    row: [f64; N],
    /// `J_jk` for each leaf (0 at the hub).
    col: [f64; N],
    /// `1/s`.
    inv_s: f64,
}

impl<const N: usize> Arrow<N> {
    /// Factorise `c·I − jac` with hub `hub`. `None` when a leaf pivot is below `c/2`, the hub
    /// pivot is zero or not finite, or `hub` is out of range (the caller then factorises
    /// densely). The entries of `jac` off the hub's row and column and off the diagonal are
    /// taken as zero (the system declares it; checked in debug builds).
    #[inline(always)]
    pub fn new(c: f64, jac: &SMatrix<f64, N, N>, hub: usize) -> Option<Self> {
        if hub >= N {
            return None;
        }
        debug_assert!(
            (0..N).all(|i| (0..N).all(|j| i == j || i == hub || j == hub || jac[(i, j)] == 0.0)),
            "Jacobian is not an arrowhead with hub {hub}: {jac}"
        );
        let half = 0.5 * c;
        let mut inv_d = [0.0; N];
        let mut row = [0.0; N];
        let mut col = [0.0; N];
        let mut s = c - jac[(hub, hub)];
        for j in 0..N {
            if j == hub {
                continue;
            }
            let d = c - jac[(j, j)];
            // Also declines a NaN.
            if d < half || d.is_nan() {
                return None;
            }
            let inv = 1.0 / d;
            inv_d[j] = inv;
            row[j] = jac[(hub, j)] * inv;
            col[j] = jac[(j, hub)];
            s -= row[j] * col[j];
        }
        if s == 0.0 || !s.is_finite() {
            return None;
        }
        Some(Self {
            hub,
            inv_d,
            row,
            col,
            inv_s: 1.0 / s,
        })
    }

    /// Solve `(c·I − J)·x = b`.
    #[inline(always)]
    pub fn solve(&self, b: &SVector<f64, N>) -> SVector<f64, N> {
        let k = self.hub;
        let mut acc = b[k];
        for j in 0..N {
            if j != k {
                acc += self.row[j] * b[j];
            }
        }
        let xk = acc * self.inv_s;
        let mut x = SVector::<f64, N>::zeros();
        for j in 0..N {
            x[j] = if j == k {
                xk
            } else {
                (b[j] + self.col[j] * xk) * self.inv_d[j]
            };
        }
        x
    }
}

#[cfg(test)]
mod tests {
    use super::Arrow;
    use nalgebra::{SMatrix, SVector};

    #[test]
    fn solves_arrowhead_systems_like_dense_lu() {
        let mut s = 0x9e37_79b9_7f4a_7c15_u64;
        let mut next = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        let mut used = 0;
        for _ in 0..2000 {
            let hub = ((next() + 1.0) * 2.0).floor().clamp(0.0, 3.0) as usize;
            let c = 10f64.powf(2.0 + 3.0 * next());
            let jac = SMatrix::<f64, 4, 4>::from_fn(|i, j| {
                if i == j {
                    // Mostly decaying leaves, sometimes a growing one (declined).
                    -c * 10f64.powf(2.0 * next()) * (next() + 0.8)
                } else if i == hub || j == hub {
                    next() * 10f64.powf(4.0 * next())
                } else {
                    0.0
                }
            });
            let b = SVector::<f64, 4>::from_fn(|_, _| next());
            let w = SMatrix::<f64, 4, 4>::identity() * c - jac;
            let dense = w.lu().solve(&b);
            match Arrow::new(c, &jac, hub) {
                Some(f) => {
                    used += 1;
                    let x = f.solve(&b);
                    assert!(dense.is_some(), "{w}");
                    // Backward stable: the residual is at rounding level.
                    let r = w * x - b;
                    let wn = w.abs().row_sum().amax();
                    assert!(r.amax() <= 1e-13 * (wn * x.amax() + b.amax()), "{r}");
                }
                None => {
                    let declined = (0..4).any(|j| j != hub && c - jac[(j, j)] < 0.5 * c);
                    assert!(declined || dense.is_none(), "{w}");
                }
            }
        }
        assert!(used > 1000, "{used}");
        assert!(Arrow::new(1.0, &SMatrix::<f64, 4, 4>::zeros(), 4).is_none());
    }
}
