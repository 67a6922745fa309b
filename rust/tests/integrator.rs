//! RODAS4 on problems with exact solutions: convergence order, stiff stability, events.
use nalgebra::{SMatrix, SVector};
use nanostage::integrate::{IntegratorOptions, OdeSystem, Rodas4, SegmentEnd};

/// Damped oscillator x'' + 2ζω x' + ω² x = 0.
struct Oscillator {
    w: f64,
    zeta: f64,
}

impl OdeSystem<2> for Oscillator {
    fn rhs(&self, y: &SVector<f64, 2>, dy: &mut SVector<f64, 2>) {
        dy[0] = y[1];
        dy[1] = -self.w * self.w * y[0] - 2.0 * self.zeta * self.w * y[1];
    }
    fn jacobian(&self, _y: &SVector<f64, 2>, j: &mut SMatrix<f64, 2, 2>) {
        *j = SMatrix::<f64, 2, 2>::new(0.0, 1.0, -self.w * self.w, -2.0 * self.zeta * self.w);
    }
}

impl Oscillator {
    /// Exact solution from x(0) = 1, v(0) = 0 (underdamped).
    fn exact(&self, t: f64) -> f64 {
        let wd = self.w * (1.0 - self.zeta * self.zeta).sqrt();
        let a = self.zeta * self.w;
        (-a * t).exp() * ((wd * t).cos() + a / wd * (wd * t).sin())
    }
}

#[test]
fn fixed_step_convergence_order_is_four() {
    let sys = Oscillator { w: 3.0, zeta: 0.1 };
    let t_end = 1.0;
    let atol = SVector::<f64, 2>::repeat(1e-12);
    let mut errs = Vec::new();
    let mut hs = Vec::new();
    for k in 3..8 {
        let n = 1usize << k;
        let h = t_end / n as f64;
        let mut integ = Rodas4::<2>::new(IntegratorOptions::default()).unwrap();
        let mut y = SVector::<f64, 2>::new(1.0, 0.0);
        for _ in 0..n {
            integ.fixed_step(&sys, &mut y, h, &atol).unwrap();
        }
        errs.push((y[0] - sys.exact(t_end)).abs());
        hs.push(h);
    }
    // Least-squares slope of log(err) against log(h).
    let lx: Vec<f64> = hs.iter().map(|h| h.ln()).collect();
    let ly: Vec<f64> = errs.iter().map(|e| e.ln()).collect();
    let mx = lx.iter().sum::<f64>() / lx.len() as f64;
    let my = ly.iter().sum::<f64>() / ly.len() as f64;
    let num: f64 = lx.iter().zip(&ly).map(|(x, y)| (x - mx) * (y - my)).sum();
    let den: f64 = lx.iter().map(|x| (x - mx) * (x - mx)).sum();
    let slope = num / den;
    assert!((slope - 4.0).abs() < 0.3, "order {slope}, errors {errs:?}");
}

/// y1' = −y1, y2' = −λ(y2 − y1) − y1: y2 = y1 + (y2(0) − y1(0))·e^(−λt), λ = 1e6.
struct Stiff {
    lambda: f64,
}

impl OdeSystem<2> for Stiff {
    fn rhs(&self, y: &SVector<f64, 2>, dy: &mut SVector<f64, 2>) {
        dy[0] = -y[0];
        dy[1] = -self.lambda * (y[1] - y[0]) - y[0];
    }
    fn jacobian(&self, _y: &SVector<f64, 2>, j: &mut SMatrix<f64, 2, 2>) {
        *j = SMatrix::<f64, 2, 2>::new(-1.0, 0.0, self.lambda - 1.0, -self.lambda);
    }
}

#[test]
fn stiff_problem_is_accurate_with_few_steps() {
    let sys = Stiff { lambda: 1e6 };
    let opts = IntegratorOptions {
        rtol: 1e-8,
        h_max_s: 1.0,
        ..IntegratorOptions::default()
    };
    let mut integ = Rodas4::<2>::new(opts).unwrap();
    let mut y = SVector::<f64, 2>::new(1.0, 2.0);
    let atol = SVector::<f64, 2>::repeat(1e-10);
    let end = integ.integrate(&sys, 0.0, 2.0, &mut y, &atol).unwrap();
    assert_eq!(end, SegmentEnd::Reached);
    let exact = (-2.0f64).exp();
    assert!((y[0] - exact).abs() < 1e-7, "y1 {} vs {exact}", y[0]);
    assert!((y[1] - exact).abs() < 1e-7, "y2 {} vs {exact}", y[1]);
    // An explicit method would need ~1e6 steps for stability; L-stability needs far fewer.
    assert!(integ.stats.n_accepted < 400, "{:?}", integ.stats);
}

/// Free fall with an event at x = 0.
struct Fall;

impl OdeSystem<2> for Fall {
    fn rhs(&self, y: &SVector<f64, 2>, dy: &mut SVector<f64, 2>) {
        dy[0] = y[1];
        dy[1] = -9.81;
    }
    fn jacobian(&self, _y: &SVector<f64, 2>, j: &mut SMatrix<f64, 2, 2>) {
        *j = SMatrix::<f64, 2, 2>::new(0.0, 1.0, 0.0, 0.0);
    }
    fn event(&self, y: &SVector<f64, 2>) -> Option<f64> {
        Some(y[0])
    }
}

#[test]
fn event_is_located_at_the_exact_time() {
    let mut integ = Rodas4::<2>::new(IntegratorOptions {
        h_max_s: 1.0,
        ..IntegratorOptions::default()
    })
    .unwrap();
    let mut y = SVector::<f64, 2>::new(1.0, 0.0);
    let atol = SVector::<f64, 2>::repeat(1e-12);
    let end = integ.integrate(&Fall, 0.0, 10.0, &mut y, &atol).unwrap();
    let exact = (2.0f64 / 9.81).sqrt();
    match end {
        SegmentEnd::Event { t_s } => assert!((t_s - exact).abs() < 1e-10, "{t_s} vs {exact}"),
        SegmentEnd::Reached => panic!("no event"),
    }
    assert!(y[0].abs() < 1e-9);
}

#[test]
fn invalid_options_name_the_field() {
    let bad = IntegratorOptions {
        rtol: 0.5,
        ..IntegratorOptions::default()
    };
    let err = Rodas4::<2>::new(bad).unwrap_err();
    assert_eq!(err.field, "rtol");
    assert!(err.to_string().contains("0.5"));
}
