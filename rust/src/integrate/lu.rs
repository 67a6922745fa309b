//! LU factorisation with partial pivoting of a small fixed-size matrix, on the stack.
//!
//! The same algorithm and the same floating-point operations, in the same order, as
//! `nalgebra::LU` (pivot = first largest |entry| of the column; the column below the pivot is
//! scaled by the reciprocal of the pivot; rank-1 update of the trailing block; forward
//! substitution with a unit lower triangle, back substitution dividing by the pivots), so the
//! results are bit-identical; without nalgebra's generic storage machinery it costs about a
//! quarter of the instructions for the 4×4 iteration matrix of the integrator, which it
//! factorises once per step and solves six times.
// Index loops mirror the textbook algorithm (and nalgebra's operation order).
#![allow(clippy::needless_range_loop)]
use nalgebra::{SMatrix, SVector};

/// `P·A = L·U` of an `N×N` matrix: `L` (unit diagonal) below, `U` on and above the diagonal,
/// stored column-major like nalgebra, and the row swaps in the order they were made.
#[derive(Debug, Clone, Copy)]
pub struct Lu<const N: usize> {
    lu: [[f64; N]; N], // lu[column][row]
    swaps: [usize; N],
}

impl<const N: usize> Lu<N> {
    /// Factorise `a`. Returns `None` when a pivot is zero (singular matrix).
    #[inline(always)]
    pub fn new(a: &SMatrix<f64, N, N>) -> Option<Self> {
        let mut m = [[0.0; N]; N];
        for (j, col) in m.iter_mut().enumerate() {
            for (i, v) in col.iter_mut().enumerate() {
                *v = a[(i, j)];
            }
        }
        let mut swaps = [0usize; N];
        for i in 0..N {
            let mut piv = i;
            let mut best = m[i][i].abs();
            for r in i + 1..N {
                let v = m[i][r].abs();
                if v > best {
                    best = v;
                    piv = r;
                }
            }
            swaps[i] = piv;
            let diag = m[i][piv];
            if diag == 0.0 {
                return None;
            }
            if piv != i {
                for col in m.iter_mut() {
                    col.swap(i, piv);
                }
            }
            let inv_diag = 1.0 / diag;
            for r in i + 1..N {
                m[i][r] *= inv_diag;
            }
            let (head, tail) = m.split_at_mut(i + 1);
            let coeffs = &head[i];
            for col in tail.iter_mut() {
                let p = col[i];
                for r in i + 1..N {
                    col[r] += -p * coeffs[r];
                }
            }
        }
        Some(Self { lu: m, swaps })
    }

    /// Solve `A·x = b`.
    #[inline(always)]
    pub fn solve(&self, b: &SVector<f64, N>) -> SVector<f64, N> {
        let mut x = *b;
        for (i, &p) in self.swaps.iter().enumerate() {
            if p != i {
                x.swap_rows(i, p);
            }
        }
        for i in 0..N {
            let c = x[i];
            for r in i + 1..N {
                x[r] += -c * self.lu[i][r];
            }
        }
        for i in (0..N).rev() {
            let c = x[i] / self.lu[i][i];
            x[i] = c;
            for r in 0..i {
                x[r] += -c * self.lu[i][r];
            }
        }
        x
    }
}

#[cfg(test)]
mod tests {
    use super::Lu;
    use nalgebra::{SMatrix, SVector};

    #[test]
    fn bit_identical_to_nalgebra() {
        let mut s = 0x2545_f491_4f6c_dd1d_u64;
        let mut next = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        for _ in 0..2000 {
            let a = SMatrix::<f64, 4, 4>::from_fn(|_, _| next() * 10f64.powf(3.0 * next()));
            let b = SVector::<f64, 4>::from_fn(|_, _| next());
            let ours = Lu::new(&a).map(|lu| lu.solve(&b));
            let theirs = a.lu().solve(&b);
            match (ours, theirs) {
                (Some(x), Some(y)) => {
                    for i in 0..4 {
                        assert_eq!(x[i].to_bits(), y[i].to_bits(), "{a} {b}");
                    }
                }
                (o, t) => assert_eq!(o.is_some(), t.is_some()),
            }
        }
        let singular =
            SMatrix::<f64, 4, 4>::from_fn(|i, j| if j == 2 { 0.0 } else { (i + j) as f64 });
        assert!(Lu::new(&singular).is_none());
    }
}
