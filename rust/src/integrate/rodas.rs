//! RODAS4 with step-size control and event location.
use super::arrow::Arrow;
use super::lu::Lu;
use super::OdeSystem;
use crate::error::{check_positive, check_range, ConfigError, SimError};
use nalgebra::{Const, DimMin, SMatrix, SVector};

/// Options of the integrator. Defaults suit the seed axis (position error ≪ 1 nm).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IntegratorOptions {
    /// Relative tolerance, in [1e-14, 1e-2].
    pub rtol: f64,
    /// Absolute tolerance of the position state, m, in (0, 1e-3]; the system scales it to its
    /// other states (see `Axis::state_scales`).
    pub atol_position_m: f64,
    /// First trial step, s, in (0, 1].
    pub h_init_s: f64,
    /// Smallest step before the run fails, s, in (0, 1e-6].
    pub h_min_s: f64,
    /// Largest step, s, in (0, 1].
    pub h_max_s: f64,
    /// Most steps (accepted + rejected) in one control interval, in [10, 1e9]: one call of a
    /// plant's `advance` (the interval from a sample to the output update, or from there to
    /// the next sample), over all its segments between stick/slip events. A plain
    /// [`Rodas4::integrate`] call counts its own steps. Event location's trial steps are not
    /// counted (at most 200 per event, and events are limited by `max_events`).
    pub max_steps: usize,
    /// Most stick/slip events (mode changes) in one control interval (one call of a plant's
    /// `advance`), in [1, 1e9]. Together with `max_steps` this bounds the work of every
    /// control interval: a friction law that switches faster than the model can resolve
    /// (chattering between stick and slip at ever shorter intervals) ends the run with
    /// `SimError::TooManyEvents` instead of running on. The seed axis and the effect library
    /// take at most about ten events per interval.
    pub max_events: usize,
    /// Width of the time bracket at which an event is considered located, s, in (0, 1e-6].
    pub event_tol_s: f64,
}

impl Default for IntegratorOptions {
    fn default() -> Self {
        Self {
            rtol: 1e-6,
            atol_position_m: 1e-11,
            h_init_s: 1e-5,
            h_min_s: 1e-14,
            h_max_s: 1e-3,
            max_steps: 100_000,
            max_events: 10_000,
            event_tol_s: 1e-11,
        }
    }
}

impl IntegratorOptions {
    /// Check every field against its documented range.
    pub fn validate(&self) -> Result<(), ConfigError> {
        check_range("rtol", self.rtol, 1e-14, 1e-2)?;
        check_positive("atol_position_m", self.atol_position_m, 1e-3)?;
        check_positive("h_init_s", self.h_init_s, 1.0)?;
        check_positive("h_min_s", self.h_min_s, 1e-6)?;
        check_positive("h_max_s", self.h_max_s, 1.0)?;
        check_positive("event_tol_s", self.event_tol_s, 1e-6)?;
        if self.max_steps < 10 || self.max_steps > 1_000_000_000 {
            return Err(ConfigError::new(
                "max_steps",
                self.max_steps,
                "an integer in [10, 1e9]",
            ));
        }
        if self.max_events < 1 || self.max_events > 1_000_000_000 {
            return Err(ConfigError::new(
                "max_events",
                self.max_events,
                "an integer in [1, 1e9]",
            ));
        }
        if self.h_min_s > self.h_max_s {
            return Err(ConfigError::new(
                "h_min_s",
                self.h_min_s,
                format!("at most h_max_s = {}", self.h_max_s),
            ));
        }
        Ok(())
    }
}

/// Work counters, returned with every run.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Stats {
    /// Right-hand-side evaluations.
    pub n_rhs: u64,
    /// Jacobian evaluations.
    pub n_jac: u64,
    /// LU factorisations.
    pub n_lu: u64,
    /// Accepted steps.
    pub n_accepted: u64,
    /// Rejected steps (error too large).
    pub n_rejected: u64,
    /// Events located.
    pub n_events: u64,
}

impl std::ops::AddAssign for Stats {
    fn add_assign(&mut self, o: Self) {
        self.n_rhs += o.n_rhs;
        self.n_jac += o.n_jac;
        self.n_lu += o.n_lu;
        self.n_accepted += o.n_accepted;
        self.n_rejected += o.n_rejected;
        self.n_events += o.n_events;
    }
}

/// How a segment ended.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SegmentEnd {
    /// The end time was reached.
    Reached,
    /// An event was located at this time (the state is the state at the event).
    Event {
        /// Time of the event, s.
        t_s: f64,
    },
}

// RODAS4 coefficients (Hairer & Wanner, rodas.f, transformed form):
// (I/(hγ) − J) k_i = f(y0 + Σ a_ij k_j) + Σ (c_ij/h) k_j;  y1 = y0 + Σ b_j k_j;  err = k_6.
const GAMMA: f64 = 0.25;
const A21: f64 = 1.544;
const A31: f64 = 0.946_678_528_081_582_6;
const A32: f64 = 0.255_701_169_898_328_4;
const A41: f64 = 3.314_825_187_068_521;
const A42: f64 = 2.896_124_015_972_201;
const A43: f64 = 0.998_641_913_997_781_7;
const A51: f64 = 1.221_224_509_226_641;
const A52: f64 = 6.019_134_481_288_629;
const A53: f64 = 12.537_083_329_320_87;
const A54: f64 = -0.687_886_036_105_895;
const C21: f64 = -5.6688;
const C31: f64 = -2.430_093_356_833_875;
const C32: f64 = -0.206_359_915_709_191_5;
const C41: f64 = -0.107_352_905_815_137_5;
const C42: f64 = -9.594_562_251_023_355;
const C43: f64 = -20.470_286_148_096_16;
const C51: f64 = 7.496_443_313_967_647;
const C52: f64 = -10.246_804_314_643_52;
const C53: f64 = -33.999_903_528_199_05;
const C54: f64 = 11.708_908_932_061_6;
const C61: f64 = 8.083_246_795_921_522;
const C62: f64 = -7.981_132_988_064_893;
const C63: f64 = -31.521_594_328_743_71;
const C64: f64 = 16.319_305_431_231_36;
const C65: f64 = -6.058_818_238_834_054;

/// A factorised iteration matrix.
trait Factor<const N: usize> {
    fn solve(&self, b: &SVector<f64, N>) -> SVector<f64, N>;
}

impl<const N: usize> Factor<N> for Lu<N> {
    #[inline(always)]
    fn solve(&self, b: &SVector<f64, N>) -> SVector<f64, N> {
        Lu::solve(self, b)
    }
}

impl<const N: usize> Factor<N> for Arrow<N> {
    #[inline(always)]
    fn solve(&self, b: &SVector<f64, N>) -> SVector<f64, N> {
        Arrow::solve(self, b)
    }
}

/// Steps of a control interval between two polls of its stop request (see
/// [`Rodas4::integrate_after_jump`]). Counted in integrator steps, not in samples as
/// [`POLL_EVERY_SAMPLES`](super::POLL_EVERY_SAMPLES) is: a stiff interval of millions of
/// steps still answers a stop request after at most this many steps.
pub const POLL_EVERY_STEPS: usize = 4096;

/// Error norm the first trial step after an input jump aims at
/// ([`Rodas4::integrate_after_jump`]).
pub const JUMP_FIRST_STEP_ERROR: f64 = 0.8;

/// The RODAS4 integrator. Keeps the last step size as a warm start and its work counters.
#[derive(Debug, Clone)]
pub struct Rodas4<const N: usize> {
    /// Options (validated at construction).
    pub options: IntegratorOptions,
    /// Work counters since construction.
    pub stats: Stats,
    h: f64,
    first_accepted: Option<(f64, f64)>,
}

struct StepOut<const N: usize> {
    y1: SVector<f64, N>,
    err: f64,
}

impl<const N: usize> Rodas4<N>
where
    Const<N>: DimMin<Const<N>, Output = Const<N>>,
{
    /// A new integrator; fails on invalid options.
    pub fn new(options: IntegratorOptions) -> Result<Self, ConfigError> {
        options.validate()?;
        Ok(Self {
            options,
            stats: Stats::default(),
            h: options.h_init_s,
            first_accepted: None,
        })
    }

    /// The step size the next [`Self::integrate`] call will try first, s.
    pub fn next_step(&self) -> f64 {
        self.h
    }

    /// Let the next [`Self::integrate`] call try at most `h_s` first (a caller that knows the
    /// next segment starts with a transient the warm start does not foresee, e.g. after a jump
    /// of a held input). Only the first trial step changes: error control is as always.
    pub fn limit_next_step(&mut self, h_s: f64) {
        if h_s.is_finite() && h_s > 0.0 {
            self.h = self.h.min(h_s);
        }
    }

    /// Size and error norm of the first accepted step of the last [`Self::integrate`] call
    /// (`None` if it accepted none).
    pub fn first_accepted(&self) -> Option<(f64, f64)> {
        self.first_accepted
    }

    /// One RODAS4 step of size `h` from `y0`, given `f0 = f(y0)` and `jac = J(y0)`. The
    /// iteration matrix is factorised by [`Arrow`] when the system declares an arrowhead
    /// Jacobian (and the factorisation accepts it), by the dense [`Lu`] otherwise.
    fn step<S: OdeSystem<N>>(
        &mut self,
        sys: &S,
        y0: &SVector<f64, N>,
        f0: &SVector<f64, N>,
        jac: &SMatrix<f64, N, N>,
        h: f64,
        atol: &SVector<f64, N>,
    ) -> Option<StepOut<N>> {
        let c = 1.0 / (h * GAMMA);
        self.stats.n_lu += 1;
        if let Some(hub) = sys.arrowhead_hub() {
            if let Some(f) = Arrow::new(c, jac, hub) {
                return Some(self.stages(sys, y0, f0, h, atol, &f));
            }
        }
        let w = SMatrix::<f64, N, N>::identity() * c - jac;
        let lu = Lu::new(&w)?;
        Some(self.stages(sys, y0, f0, h, atol, &lu))
    }

    /// The six stages of a step with the factorised iteration matrix `lu`.
    #[inline(always)]
    fn stages<S: OdeSystem<N>, F: Factor<N>>(
        &mut self,
        sys: &S,
        y0: &SVector<f64, N>,
        f0: &SVector<f64, N>,
        h: f64,
        atol: &SVector<f64, N>,
        lu: &F,
    ) -> StepOut<N> {
        let mut f = SVector::<f64, N>::zeros();
        let k1 = lu.solve(f0);
        let y = y0 + k1 * A21;
        sys.rhs(&y, &mut f);
        let k2 = lu.solve(&(f + k1 * (C21 / h)));
        let y = y0 + k1 * A31 + k2 * A32;
        sys.rhs(&y, &mut f);
        let k3 = lu.solve(&(f + (k1 * C31 + k2 * C32) * (1.0 / h)));
        let y = y0 + k1 * A41 + k2 * A42 + k3 * A43;
        sys.rhs(&y, &mut f);
        let k4 = lu.solve(&(f + (k1 * C41 + k2 * C42 + k3 * C43) * (1.0 / h)));
        let y = y0 + k1 * A51 + k2 * A52 + k3 * A53 + k4 * A54;
        sys.rhs(&y, &mut f);
        let k5 = lu.solve(&(f + (k1 * C51 + k2 * C52 + k3 * C53 + k4 * C54) * (1.0 / h)));
        let y = y + k5;
        sys.rhs(&y, &mut f);
        let k6 =
            lu.solve(&(f + (k1 * C61 + k2 * C62 + k3 * C63 + k4 * C64 + k5 * C65) * (1.0 / h)));
        self.stats.n_rhs += 5;
        let y1 = y + k6;
        let rtol = self.options.rtol;
        let mut acc = 0.0;
        for i in 0..N {
            let sc = atol[i] + rtol * y0[i].abs().max(y1[i].abs());
            let r = k6[i] / sc;
            acc += r * r;
        }
        let err = (acc / N as f64).sqrt();
        if !y1.iter().all(|v| v.is_finite()) || !err.is_finite() {
            return StepOut {
                y1,
                err: f64::INFINITY,
            };
        }
        StepOut { y1, err }
    }

    /// Take exactly one step of size `h` without error control (for convergence tests).
    pub fn fixed_step<S: OdeSystem<N>>(
        &mut self,
        sys: &S,
        y: &mut SVector<f64, N>,
        h: f64,
        atol: &SVector<f64, N>,
    ) -> Result<(), SimError> {
        let mut f0 = SVector::<f64, N>::zeros();
        let mut jac = SMatrix::<f64, N, N>::zeros();
        sys.rhs_and_jacobian(y, &mut f0, &mut jac);
        self.stats.n_rhs += 1;
        self.stats.n_jac += 1;
        match self.step(sys, y, &f0, &jac, h, atol) {
            Some(out) => {
                *y = out.y1;
                Ok(())
            }
            None => Err(SimError::SingularMatrix {
                t_s: f64::NAN,
                state: y.iter().copied().collect(),
            }),
        }
    }

    /// [`Self::integrate`] for a plant whose held input may jump at `t0`. With `jump`
    /// (the size of the input jump, for the first segment after it), the first trial step is
    /// limited to the size whose error norm the rate learned after earlier jumps
    /// (`error_rate`, per unit of jump · s³) predicts to be [`JUMP_FIRST_STEP_ERROR`], and the
    /// rate is learned again from this call's first accepted step. Without `jump` it is
    /// [`Self::integrate`].
    ///
    /// `steps` counts the steps (accepted + rejected) of the control interval this segment
    /// belongs to: the call adds its own and fails with [`SimError::TooManySteps`] when the
    /// count would exceed `max_steps`. Every [`POLL_EVERY_STEPS`] steps of the interval it
    /// asks `poll` whether to stop (true: [`SimError::Interrupted`]), so that even an
    /// interval with a large budget answers Ctrl-C; the poll does not change the result.
    #[allow(clippy::too_many_arguments)]
    pub fn integrate_after_jump<S: OdeSystem<N>>(
        &mut self,
        sys: &S,
        t0: f64,
        t1: f64,
        y: &mut SVector<f64, N>,
        atol: &SVector<f64, N>,
        jump: Option<f64>,
        error_rate: &mut Option<f64>,
        steps: &mut usize,
        poll: &mut dyn FnMut() -> bool,
    ) -> Result<SegmentEnd, SimError> {
        if let (Some(jump), Some(rate)) = (jump, *error_rate) {
            self.limit_next_step((JUMP_FIRST_STEP_ERROR / (rate * jump)).cbrt());
        }
        let end = self.integrate_counted(sys, t0, t1, y, atol, steps, poll)?;
        if let (Some(jump), Some((h, err))) = (jump, self.first_accepted()) {
            let rate = err / (jump * h * h * h);
            if rate.is_finite() && rate > 0.0 {
                *error_rate = Some(rate);
            }
        }
        Ok(end)
    }

    /// Integrate from `t0` to `t1` (or to the first event), updating `y` in place.
    /// `atol` is the per-component absolute tolerance. At most `max_steps` steps.
    pub fn integrate<S: OdeSystem<N>>(
        &mut self,
        sys: &S,
        t0: f64,
        t1: f64,
        y: &mut SVector<f64, N>,
        atol: &SVector<f64, N>,
    ) -> Result<SegmentEnd, SimError> {
        let mut steps = 0;
        self.integrate_counted(sys, t0, t1, y, atol, &mut steps, &mut || false)
    }

    /// [`Self::integrate`] adding its steps to `steps` (the steps of the control interval
    /// so far), failing when the count would exceed `max_steps`, and asking `poll` every
    /// [`POLL_EVERY_STEPS`] steps of the interval whether to stop.
    #[allow(clippy::too_many_arguments)]
    fn integrate_counted<S: OdeSystem<N>>(
        &mut self,
        sys: &S,
        t0: f64,
        t1: f64,
        y: &mut SVector<f64, N>,
        atol: &SVector<f64, N>,
        steps: &mut usize,
        poll: &mut dyn FnMut() -> bool,
    ) -> Result<SegmentEnd, SimError> {
        let opts = self.options;
        let mut t = t0;
        let mut h = self.h.clamp(opts.h_min_s, opts.h_max_s);
        let mut f0 = SVector::<f64, N>::zeros();
        let mut jac = SMatrix::<f64, N, N>::zeros();
        // Relative floor below which the remaining interval counts as reached.
        let t_eps = 1e-15 * t1.abs().max(1e-9);
        let mut fresh = true;
        let mut last_reject = false;
        // Size and error norm (floored at 1e-2) of the previous accepted step of this segment,
        // if no step was rejected since (for the predictive controller).
        let mut prev_acc: Option<(f64, f64)> = None;
        self.first_accepted = None;
        while t1 - t > t_eps {
            if fresh {
                sys.rhs_and_jacobian(y, &mut f0, &mut jac);
                self.stats.n_rhs += 1;
                self.stats.n_jac += 1;
                fresh = false;
            }
            let remaining = t1 - t;
            let last = h >= remaining;
            let h_try = if last { remaining } else { h };
            *steps += 1;
            if *steps > opts.max_steps {
                return Err(SimError::TooManySteps {
                    t_s: t,
                    max_steps: opts.max_steps,
                    state: y.iter().copied().collect(),
                });
            }
            if *steps % POLL_EVERY_STEPS == 0 && poll() {
                return Err(SimError::Interrupted { t_s: t });
            }
            let Some(out) = self.step(sys, y, &f0, &jac, h_try, atol) else {
                return Err(SimError::SingularMatrix {
                    t_s: t,
                    state: y.iter().copied().collect(),
                });
            };
            let fac = if out.err == 0.0 {
                6.0
            } else {
                (0.9 / out.err.sqrt().sqrt()).clamp(0.2, 6.0)
            };
            if out.err > 1.0 {
                self.stats.n_rejected += 1;
                h = h_try * fac.min(if last_reject { 0.5 } else { 1.0 });
                last_reject = true;
                if h < opts.h_min_s {
                    return Err(if out.err.is_finite() {
                        SimError::StepSizeTooSmall {
                            t_s: t,
                            h_s: h,
                            state: y.iter().copied().collect(),
                        }
                    } else {
                        SimError::NonFinite {
                            t_s: t,
                            state: out.y1.iter().copied().collect(),
                        }
                    });
                }
                continue;
            }
            self.stats.n_accepted += 1;
            if self.first_accepted.is_none() {
                self.first_accepted = Some((h_try, out.err));
            }
            // Event check on the accepted step.
            if let (Some(g0), Some(g1)) = (sys.event(y), sys.event(&out.y1)) {
                if g0 >= 0.0 && g1 < 0.0 {
                    let (s, y_ev) = self.locate(sys, y, &f0, &jac, &out.y1, h_try, g0, g1, atol)?;
                    *y = y_ev;
                    self.stats.n_events += 1;
                    self.h = h_try.max(opts.h_min_s);
                    return Ok(SegmentEnd::Event { t_s: t + s });
                }
            }
            *y = out.y1;
            t = if last { t1 } else { t + h_try };
            // Predictive controller (Gustafsson): the error trend of the last two accepted
            // steps, `(h/h_prev)·(err_prev/err)^(1/4)`, extrapolated one step. While the
            // transient a held-input jump excites decays (the error constant falls by about
            // e^(−h/τ) per step), the standard factor lags behind and keeps the error near
            // 0.2; the prediction follows the decay. The larger of the two factors is taken
            // (both within [0.2, 6]); every accepted step still meets the tolerance.
            let fac = match prev_acc {
                Some((h_prev, err_prev)) if !last_reject => {
                    let e = out.err.max(1e-4);
                    let pred = 0.9 * (h_try / h_prev) * (err_prev / (e * e)).sqrt().sqrt();
                    fac.max(pred.clamp(0.2, 6.0))
                }
                _ => fac,
            };
            prev_acc = if last_reject {
                None
            } else {
                Some((h_try, out.err.max(1e-2)))
            };
            let fac = if last_reject { fac.min(1.0) } else { fac };
            last_reject = false;
            // Keep the untruncated step as the warm start when the last step was cut short.
            h = if last {
                h.max(h_try * fac)
            } else {
                h_try * fac
            };
            h = h.clamp(opts.h_min_s, opts.h_max_s);
            fresh = true;
        }
        self.h = h;
        Ok(SegmentEnd::Reached)
    }

    /// Locate the event inside an accepted step `[0, h]` (g(0) = g0 ≥ 0 > g1 = g(h), `y1` the
    /// step's end state); returns the offset and the state there (the first trial state with
    /// g < 0 once the bracket is at most `event_tol_s` wide).
    ///
    /// Each trial is a step of its own size from `y0`. The trials: the Illinois method on the
    /// bracket, with two shortcuts: where the system gives the event's rate
    /// ([`OdeSystem::event_rate`]), the first trial is the root of the cubic Hermite
    /// interpolant of g over the step (g and its rate at both ends); and after a trial whose
    /// Newton estimate of the root (slope: the secant through the last two trials, or the
    /// cubic's at the first) lies inside the bracket, the next trial goes just past that
    /// estimate (by 0.1 % of the distance and a quarter of the tolerance), so that the root is
    /// bracketed tightly from both sides instead of approached from one while the other end
    /// stays far. A shortcut that does not land on the other side is followed by an Illinois
    /// trial; every trial lies strictly inside the bracket, so the bracket always shrinks.
    #[allow(clippy::too_many_arguments)]
    fn locate<S: OdeSystem<N>>(
        &mut self,
        sys: &S,
        y0: &SVector<f64, N>,
        f0: &SVector<f64, N>,
        jac: &SMatrix<f64, N, N>,
        y1: &SVector<f64, N>,
        h: f64,
        g0: f64,
        g1: f64,
        atol: &SVector<f64, N>,
    ) -> Result<(f64, SVector<f64, N>), SimError> {
        let tol = self.options.event_tol_s;
        let (mut a, mut ga) = (0.0_f64, g0);
        let (mut b, mut gb) = (h, g1);
        let mut yb: Option<SVector<f64, N>> = None;
        let mut side = 0i8;
        // The cubic Hermite interpolant of g over the step, when the rates are known.
        let cubic = sys.event_rate(y0, f0).and_then(|m0| {
            let mut f1 = SVector::<f64, N>::zeros();
            sys.rhs(y1, &mut f1);
            self.stats.n_rhs += 1;
            sys.event_rate(y1, &f1)
                .map(|m1| Hermite::new(h, g0, g1, m0, m1))
        });
        let mut next: Option<f64> = cubic.as_ref().and_then(Hermite::root);
        // The last trial (offset, g) and whether it was a shortcut.
        let mut last: Option<(f64, f64)> = None;
        let mut shortcut = next.is_some();
        for _ in 0..200 {
            if b - a <= tol {
                break;
            }
            let mut s = match next.take() {
                Some(s) => s,
                None if ga == gb => 0.5 * (a + b),
                None => (a * gb - b * ga) / (gb - ga),
            };
            if !(s > a && s < b) {
                s = 0.5 * (a + b);
            }
            let Some(out) = self.step(sys, y0, f0, jac, s, atol) else {
                return Err(SimError::SingularMatrix {
                    t_s: f64::NAN,
                    state: y0.iter().copied().collect(),
                });
            };
            let Some(gs) = sys.event(&out.y1) else { break };
            if gs < 0.0 {
                b = s;
                gb = gs;
                yb = Some(out.y1);
                if side == -1 {
                    ga *= 0.5;
                }
                side = -1;
            } else {
                a = s;
                ga = gs;
                if side == 1 {
                    gb *= 0.5;
                }
                side = 1;
                if gs == 0.0 {
                    return Ok((s, out.y1));
                }
            }
            // A shortcut that stayed on the side of the last trial: Illinois next.
            let crossed = last.is_none_or(|(_, gp)| (gp < 0.0) != (gs < 0.0));
            if shortcut && !crossed {
                shortcut = false;
            } else {
                let slope = match last {
                    Some((sp, gp)) if gs != gp => Some((gs - gp) / (s - sp)),
                    Some(_) => None,
                    None => cubic.as_ref().map(|c| c.rate(s)),
                };
                next = slope.and_then(|m| {
                    let dist = -gs / m;
                    let past = s + dist + (1e-3 * dist.abs() + 0.25 * tol).copysign(dist);
                    (dist.is_finite() && past > a && past < b).then_some(past)
                });
                shortcut = next.is_some();
            }
            last = Some((s, gs));
        }
        let y_ev = match yb {
            Some(y) => y,
            None => match self.step(sys, y0, f0, jac, b, atol) {
                Some(out) => out.y1,
                None => {
                    return Err(SimError::SingularMatrix {
                        t_s: f64::NAN,
                        state: y0.iter().copied().collect(),
                    })
                }
            },
        };
        Ok((b, y_ev))
    }
}

/// The cubic Hermite interpolant of g on `[0, h]` from its values and rates at both ends.
struct Hermite {
    h: f64,
    g0: f64,
    g1: f64,
    m0: f64,
    m1: f64,
}

impl Hermite {
    fn new(h: f64, g0: f64, g1: f64, m0: f64, m1: f64) -> Self {
        Self { h, g0, g1, m0, m1 }
    }

    /// Value at `s`.
    fn value(&self, s: f64) -> f64 {
        let t = s / self.h;
        let (t2, t3) = (t * t, t * t * t);
        (2.0 * t3 - 3.0 * t2 + 1.0) * self.g0
            + (t3 - 2.0 * t2 + t) * self.h * self.m0
            + (-2.0 * t3 + 3.0 * t2) * self.g1
            + (t3 - t2) * self.h * self.m1
    }

    /// Rate at `s`.
    fn rate(&self, s: f64) -> f64 {
        let t = s / self.h;
        let t2 = t * t;
        ((6.0 * t2 - 6.0 * t) * (self.g0 - self.g1)) / self.h
            + (3.0 * t2 - 4.0 * t + 1.0) * self.m0
            + (3.0 * t2 - 2.0 * t) * self.m1
    }

    /// A root in (0, h) (g0 ≥ 0 > g1: the interpolant changes sign there): safeguarded
    /// Newton from the secant root, bisection when a Newton step leaves the bracket. `None`
    /// if the values are not finite.
    fn root(&self) -> Option<f64> {
        let (mut lo, mut hi) = (0.0, self.h);
        if !(self.g0 >= 0.0 && self.g1 < 0.0 && self.m0.is_finite() && self.m1.is_finite()) {
            return None;
        }
        let mut s = self.h * self.g0 / (self.g0 - self.g1);
        for _ in 0..30 {
            let v = self.value(s);
            if v >= 0.0 {
                lo = s;
            } else {
                hi = s;
            }
            let m = self.rate(s);
            let mut n = s - v / m;
            if !(n > lo && n < hi) {
                n = 0.5 * (lo + hi);
            }
            if (n - s).abs() <= 1e-6 * self.h * f64::EPSILON.sqrt() {
                return Some(n);
            }
            s = n;
        }
        (s > 0.0 && s < self.h).then_some(s)
    }
}
