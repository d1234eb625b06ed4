//! First-Order Adaptive Windowing (FOAW) velocity estimation.
//!
//! F. Janabi-Sharifi, V. Hayward, C.-S. J. Chen, "Discrete-time adaptive
//! windowing for velocity estimation", IEEE TCST 8(6), 2000.
//!
//! A finite difference over a window of `n` sample periods trades noise
//! (`~ d / (nT)`) against lag (`~ nT`). FOAW chooses `n` per sample: it grows
//! the window for as long as a straight line explains every sample in it to
//! within the measurement noise bound `d`, and returns the slope of that line.
//! Long windows are therefore used while the motion is close to linear and
//! short ones at once when it is not (reversals, impacts, steps).
//!
//! The 3-D formulation (Formaglio et al.) with a peak-norm bound `d` is applied
//! axis by axis: every axis is an independent [`FoawAxis`] that selects its
//! own window. Each axis holds a fixed-size buffer; nothing is allocated,
//! neither at construction nor per sample.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use wide::f64x2;

/// Largest supported window, in sample periods.
pub const MAX_WINDOW: usize = 64;

/// A window of `n` periods spans `n + 1` samples.
const CAP: usize = MAX_WINDOW + 1;

/// How the line over a candidate window is fitted.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FoawVariant {
    /// Line through the newest and the oldest sample of the window.
    EndFit,
    /// Least-squares line (slope and intercept) through all samples of the
    /// window; every sample, the newest and the oldest included, must lie
    /// within `d` of it. Sinclair's public C implementation (radarsat1/FOAW)
    /// instead tests the least-squares slope on a line forced through the
    /// newest sample, against the inner samples only. hgcd keeps the true
    /// least-squares line on purpose: it is the line the window's samples
    /// support, and its slope is the estimate returned.
    BestFit,
}

/// Invalid estimator parameters.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FoawError {
    #[error("FOAW noise bound must be finite and > 0, got {0}")]
    InvalidNoiseBound(f64),
    #[error("FOAW window must be in 1..={MAX_WINDOW}, got {0}")]
    InvalidWindow(usize),
    #[error("FOAW sample period must be finite and > 0, got {0}")]
    InvalidPeriod(f64),
}

/// FOAW velocity estimator for one scalar axis.
///
/// Window search, with `y_k` the newest sample and `n = 1, 2, ..., max_window`:
///
/// * [`FoawVariant::EndFit`]: the slope is `b_n = (y_k - y_{k-n}) / (nT)`; the
///   window is valid if every `y_{k-i}`, `i = 1..n-1`, lies within `d` of the
///   line through `y_k` with slope `b_n`. The slopes that fit every inner
///   sample form an interval, narrowed by one sample per window, so each
///   window costs O(1).
/// * [`FoawVariant::BestFit`]: the line is the least-squares fit (slope *and*
///   intercept) through `y_{k-n} ..= y_k`, and every one of those `n + 1`
///   samples must lie within `d` of it (see the variant for why this is not
///   the public C code's line). Running sums make each line O(1); its check
///   is O(n), computed two lanes at a time.
///
/// The search stops at the first invalid window and returns the slope of the
/// last valid one. `n = 1` (the plain finite difference) is always valid.
///
/// "Within `d`" includes `d` itself, as in both published definitions. That
/// matters: encoders quantise positions, and with `d` a whole number of quanta
/// many residuals equal `d` exactly. Computed from doubles, such a residual
/// lands a few units of roundoff above or below `d`; a residual that exceeds
/// `d` by no more than `TIE` times the window's magnitude counts as equal.
/// On quantised positions the window choice is then that of exact
/// arithmetic.
///
/// The first sample after construction or [`reset`](Self::reset) pre-fills the
/// whole history, so the estimator starts at rest (estimate 0) instead of
/// seeing a false jump from a zeroed buffer.
///
/// A non-finite sample (NaN, ±∞) resets the estimator and returns 0; the next
/// finite sample starts afresh. Finite input never panics; the estimate is
/// finite as long as differences of samples do not overflow (|x| < ~1e307).
#[derive(Clone, Debug)]
pub struct FoawAxis {
    variant: FoawVariant,
    noise_bound: f64,
    max_window: usize,
    rate: f64,
    /// Mirrored ring: every sample is stored at `head` and at `head + CAP`, so
    /// `buf[head..head + CAP]` is always the contiguous history, newest first
    /// (`buf[head + i] = y_{k-i}`), with no index wrapping in the inner loops.
    buf: [f64; 2 * CAP],
    head: usize,
    primed: bool,
    window: usize,
}

impl FoawAxis {
    /// `noise_bound` is the peak measurement error `d` (input units, e.g.
    /// metres), `max_window` the largest window in periods
    /// (`1..=MAX_WINDOW`; 1 degenerates to the finite difference) and `period`
    /// the sample period `T` in seconds.
    ///
    /// Errors: [`FoawError`] naming the first parameter out of its range.
    pub fn new(
        variant: FoawVariant,
        noise_bound: f64,
        max_window: usize,
        period: f64,
    ) -> Result<Self, FoawError> {
        if !(noise_bound.is_finite() && noise_bound > 0.0) {
            return Err(FoawError::InvalidNoiseBound(noise_bound));
        }
        if !(1..=MAX_WINDOW).contains(&max_window) {
            return Err(FoawError::InvalidWindow(max_window));
        }
        if !(period.is_finite() && period > 0.0) {
            return Err(FoawError::InvalidPeriod(period));
        }
        Ok(Self {
            variant,
            noise_bound,
            max_window,
            rate: 1.0 / period,
            buf: [0.0; 2 * CAP],
            head: 0,
            primed: false,
            window: 0,
        })
    }

    /// Forgets the history; the next sample pre-fills the window.
    pub fn reset(&mut self) {
        self.primed = false;
        self.window = 0;
    }

    /// Pushes a sample and returns the velocity estimate in input units per
    /// second.
    pub fn update(&mut self, x: f64) -> f64 {
        if !x.is_finite() {
            self.reset();
            return 0.0;
        }
        if self.primed {
            self.head = if self.head == 0 {
                CAP - 1
            } else {
                self.head - 1
            };
            self.buf[self.head] = x;
            self.buf[self.head + CAP] = x;
        } else {
            self.buf = [x; 2 * CAP];
            self.primed = true;
        }
        let h = &self.buf[self.head..=self.head + self.max_window];
        let (n, rise) = match self.variant {
            FoawVariant::EndFit => end_fit(h, self.noise_bound),
            FoawVariant::BestFit => best_fit(h, self.noise_bound),
        };
        self.window = n;
        rise * self.rate
    }

    /// Window length `n` (periods) chosen at the last update; 0 if there has
    /// been none since construction or reset.
    pub fn window(&self) -> usize {
        self.window
    }
}

/// Per-window constants, read instead of converted or divided in the loops.
struct Tables {
    /// `n` as a float.
    age: [f64; CAP],
    /// `1 / n` (`[0]` unused).
    inv: [f64; CAP],
    /// Best-fit slope weights for a window of `n` periods, with
    /// `den = n (n+1) (n+2)`: `12 / den` on `S_iz` ...
    w_iz: [f64; CAP],
    /// ... and `6 n / den` on `S_z` (`[0]` unused).
    w_z: [f64; CAP],
    /// `1 / (n + 1)` and `n / 2`, for the best-fit intercept.
    inv_len: [f64; CAP],
    half: [f64; CAP],
}

const TABLES: Tables = {
    let mut t = Tables {
        age: [0.0; CAP],
        inv: [0.0; CAP],
        w_iz: [0.0; CAP],
        w_z: [0.0; CAP],
        inv_len: [0.0; CAP],
        half: [0.0; CAP],
    };
    let mut i = 0;
    while i < CAP {
        let n = i as f64;
        t.age[i] = n;
        t.inv_len[i] = 1.0 / (n + 1.0);
        t.half[i] = 0.5 * n;
        if i > 0 {
            t.inv[i] = 1.0 / n;
            t.w_iz[i] = 12.0 / (n * (n + 1.0) * (n + 2.0));
            t.w_z[i] = 6.0 / ((n + 1.0) * (n + 2.0));
        }
        i += 1;
    }
    t
};

/// Slack for ties, relative to the magnitude `M` of the quantities a test
/// involves (positions, their differences and `d`): a residual up to
/// `d + TIE·M` counts as `d`, and so does an end-fit slope that far outside
/// its interval.
///
/// Rounding (of the positions themselves, then of the arithmetic) moves a
/// computed residual by a few `ε·M`; `TIE = 64 ε` leaves a wide margin (4 ε
/// already reproduces exact arithmetic on the quantised test inputs). It
/// stays far below the smallest
/// amount by which a residual that is not a tie can exceed `d` when `d` is a
/// whole number of quanta `q`: `n` times an end-fit residual and
/// `2 n (n+1) (n+2)` times a best-fit one are whole numbers of quanta, so that
/// amount is at least `q / 549120` (best-fit, `n = 64`). The choice therefore
/// equals that of exact arithmetic for any quantum above about `1e-8·M`
/// (2 nm for positions within 0.2 m).
const TIE: f64 = 64.0 * f64::EPSILON;

/// `max` and `min` for operands known not to be NaN: one instruction each,
/// where `f64::max` adds NaN handling.
fn max(a: f64, b: f64) -> f64 {
    if a > b {
        a
    } else {
        b
    }
}

fn min(a: f64, b: f64) -> f64 {
    // Written so that it compiles to `minpd`/`minsd` (`b > a ? a : b`).
    if b > a {
        a
    } else {
        b
    }
}

/// End-fit search over `h` (newest first, `h.len() >= 2`). Returns the window
/// and the slope in units per sample.
fn end_fit(h: &[f64], d: f64) -> (usize, f64) {
    let y0 = h[0];
    let base = y0.abs() + d;
    // The line through y0 with slope v (per sample, forward in time) has value
    // y0 - v*i at age i, so sample i fits iff |z_i + v*i| <= d with
    // z_i = y_i - y0, i.e. iff v lies in [(-d - z_i)/i, (d - z_i)/i]. The
    // slopes that fit all inner samples form the running intersection
    // [lo, hi] of these intervals. Only the bound of a sample about d from
    // the line can make a tie, and such a sample has |z_i| < |z_n| + d: the
    // magnitude the slack scales with.
    //
    // Indices run over `h` and the tables in step (no `n - 1`, no enumerate counter): the
    // release profile's overflow checks would otherwise cost a third of the loop.
    let mut z_prev = h[1] - y0;
    let mut inv_prev = TABLES.inv[1];
    let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
    let mut best = (1, -z_prev);
    for (n, (&y, &inv)) in (2..h.len()).zip(h[2..].iter().zip(&TABLES.inv[2..])) {
        lo = max(lo, (-d - z_prev) * inv_prev);
        hi = min(hi, (d - z_prev) * inv_prev);
        let z = y - y0;
        let v = -z * inv;
        let tol = TIE * (base + z.abs());
        if !(v >= lo - tol && v <= hi + tol) {
            break;
        }
        best = (n, v);
        z_prev = z;
        inv_prev = inv;
    }
    best
}

/// Best-fit (least-squares) search over `h` (newest first, `h.len() >= 2`).
/// Returns the window and the slope in units per sample.
fn best_fit(h: &[f64], d: f64) -> (usize, f64) {
    // Fit z_i = h[i] - h[0] (centred for accuracy) against the age i = 0..=n
    // as z = a + b*i. With S_z = Σ z_i and S_iz = Σ i z_i, the normal
    // equations (Σ i = n(n+1)/2, Σ i² = n(n+1)(2n+1)/6) give
    //   b = (12 S_iz - 6 n S_z) / (n (n+1) (n+2)),   a = S_z/(n+1) - b n/2.
    // Age runs backwards in time, so the velocity is -b per sample.
    let y0 = h[0];
    let z1 = h[1] - y0;
    // n = 1: the two-point fit is exact, hence always valid.
    if h.len() == 2 {
        return (1, -z1);
    }
    // n = 2 and 3 in closed form. The residuals of a line fitted to three
    // samples are e/6 times (-1, 2, -1), with e = 2 z_1 - z_2; those of a line
    // fitted to four are p (1, -1, -1, 1) + q (-1, 3, -3, 1): the contrasts
    // orthogonal to lines.
    let z2 = h[2] - y0;
    let e = 2.0 * z1 - z2;
    if !fits(e.abs() / 3.0, d, y0, e / 6.0, 0.5 * z2, 2) {
        return (1, -z1);
    }
    if h.len() == 3 {
        return (2, -0.5 * z2);
    }
    let z3 = h[3] - y0;
    let (mut s_z, mut s_iz) = (z1 + z2 + z3, z1 + 2.0 * z2 + 3.0 * z3);
    let b = TABLES.w_iz[3] * s_iz - TABLES.w_z[3] * s_z;
    let a = TABLES.inv_len[3] * s_z - TABLES.half[3] * b;
    let (p, q) = (0.25 * (z3 - z1 - z2), 0.05 * (3.0 * (z1 - z2) + z3));
    if !fits(p.abs() + 3.0 * q.abs(), d, y0, a, b, 3) {
        return (2, -0.5 * z2);
    }
    let mut best = (3, b);
    for n in 4..h.len() {
        let nf = TABLES.age[n];
        let z = h[n] - y0;
        s_z += z;
        s_iz += nf * z;
        let b = TABLES.w_iz[n] * s_iz - TABLES.w_z[n] * s_z;
        let a = TABLES.inv_len[n] * s_z - TABLES.half[n] * b;
        if !fits(deviation(h, n, y0 + a, b), d, y0, a, b, n) {
            break;
        }
        best = (n, b);
    }
    (best.0, -best.1)
}

/// Whether a best-fit window of `n` periods whose line is `y0 + a + b*i` and
/// whose largest residual is `dev` is valid.
fn fits(dev: f64, d: f64, y0: f64, a: f64, b: f64, n: usize) -> bool {
    dev <= d || dev <= tie_bound(d, y0, a, b, n)
}

/// `d` plus the tie slack for a best-fit window of `n` periods whose line is
/// `y0 + a + b*i`. The largest residual decides a tie only if it is about `d`;
/// then every sample of the window lies within about `d` of the line, so the
/// window's magnitude is at most `|y0| + |a| + |b| n + 2d`.
fn tie_bound(d: f64, y0: f64, a: f64, b: f64, n: usize) -> f64 {
    d + TIE * (y0.abs() + a.abs() + b.abs() * TABLES.age[n] + 2.0 * d)
}

/// Largest residual `|h[i] - (c + b*i)|` over `i = 0..=n` (`n >= 3`), four
/// samples at a time as two independent packed pairs (explicit `f64x2`, so
/// that the compiler cannot scatter the lanes); when `n + 1` is not a
/// multiple of four, the last group overlaps the one before.
fn deviation(h: &[f64], n: usize, c: f64, b: f64) -> f64 {
    let (c, b) = (f64x2::splat(c), f64x2::splat(b));
    let (h, age) = (&h[..=n], &TABLES.age[..=n]);
    let group = |k: usize| {
        let (y, i) = (&h[k..k + 4], &age[k..k + 4]);
        let r = |j: usize| {
            (f64x2::from([y[j], y[j + 1]]) - c - b * f64x2::from([i[j], i[j + 1]])).abs()
        };
        (r(0), r(2))
    };
    let (mut m0, mut m1) = group(0);
    let mut k = 4;
    while k + 4 <= h.len() {
        let (r0, r1) = group(k);
        (m0, m1) = (m0.fast_max(r0), m1.fast_max(r1));
        k += 4;
    }
    if k < h.len() {
        let (r0, r1) = group(h.len() - 4);
        (m0, m1) = (m0.fast_max(r0), m1.fast_max(r1));
    }
    let m = m0.fast_max(m1).to_array();
    max(m[0], m[1])
}

/// Three independent [`FoawAxis`] estimators, one per Cartesian axis, sharing
/// the same parameters (the peak-norm bound `d` applies to each axis).
#[derive(Clone, Debug)]
pub struct Foaw {
    axes: [FoawAxis; 3],
}

impl Foaw {
    /// See [`FoawAxis::new`], whose errors it returns.
    pub fn new(
        variant: FoawVariant,
        noise_bound: f64,
        max_window: usize,
        period: f64,
    ) -> Result<Self, FoawError> {
        let axis = FoawAxis::new(variant, noise_bound, max_window, period)?;
        Ok(Self {
            axes: [axis.clone(), axis.clone(), axis],
        })
    }

    /// Forgets the history of all axes.
    pub fn reset(&mut self) {
        self.axes.iter_mut().for_each(FoawAxis::reset);
    }

    /// Pushes a position sample and returns the velocity estimate (units/s).
    /// Non-finite components reset only their own axis (see
    /// [`FoawAxis::update`]).
    pub fn update(&mut self, x: &Vector3<f64>) -> Vector3<f64> {
        Vector3::new(
            self.axes[0].update(x.x),
            self.axes[1].update(x.y),
            self.axes[2].update(x.z),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::Uniform;
    use std::f64::consts::TAU;

    const T: f64 = 1e-3;
    const VARIANTS: [FoawVariant; 2] = [FoawVariant::EndFit, FoawVariant::BestFit];

    fn axis(variant: FoawVariant, d: f64, n: usize) -> FoawAxis {
        FoawAxis::new(variant, d, n, T).unwrap()
    }

    #[test]
    fn construction_rejects_bad_parameters() {
        use FoawError::*;
        let v = FoawVariant::EndFit;
        for d in [0.0, -1e-6, f64::INFINITY, f64::NEG_INFINITY] {
            assert_eq!(
                FoawAxis::new(v, d, 16, T).unwrap_err(),
                InvalidNoiseBound(d)
            );
        }
        // NaN != NaN, so match the variant instead.
        assert!(matches!(
            FoawAxis::new(v, f64::NAN, 16, T),
            Err(InvalidNoiseBound(_))
        ));
        for n in [0, MAX_WINDOW + 1, usize::MAX] {
            assert_eq!(FoawAxis::new(v, 1e-6, n, T).unwrap_err(), InvalidWindow(n));
        }
        for t in [0.0, -1e-3, f64::INFINITY] {
            assert_eq!(FoawAxis::new(v, 1e-6, 16, t).unwrap_err(), InvalidPeriod(t));
        }
        assert!(matches!(
            FoawAxis::new(v, 1e-6, 16, f64::NAN),
            Err(InvalidPeriod(_))
        ));
        assert!(Foaw::new(v, 1e-6, 0, T).is_err());
        assert!(FoawAxis::new(v, 1e-6, 1, T).is_ok());
        assert!(FoawAxis::new(v, 1e-6, MAX_WINDOW, T).is_ok());
    }

    #[test]
    fn variant_serde_names_are_kebab_case() {
        #[derive(Deserialize)]
        struct Cfg {
            a: FoawVariant,
            b: FoawVariant,
        }
        let c: Cfg = toml::from_str("a = \"end-fit\"\nb = \"best-fit\"").unwrap();
        assert_eq!((c.a, c.b), (FoawVariant::EndFit, FoawVariant::BestFit));
    }

    #[test]
    fn first_sample_prefills_window() {
        for v in VARIANTS {
            let mut f = axis(v, 1e-6, 16);
            assert_eq!(f.window(), 0);
            assert_eq!(f.update(0.123), 0.0);
            assert_eq!(f.window(), 16);
            // Second sample: only the last period moved, the rest is at rest.
            let est = f.update(0.123 + 1e-3);
            assert!((est - 1.0).abs() < 1e-9, "{v:?}: {est}");
            assert_eq!(f.window(), 1);
        }
    }

    #[test]
    fn noiseless_ramp_gives_exact_slope() {
        for v in VARIANTS {
            for n in [1, 16, MAX_WINDOW] {
                let mut f = axis(v, 1e-9, n);
                for k in 0..300 {
                    let est = f.update(0.05 - 0.037 * k as f64 * T);
                    if k >= n {
                        assert!((est + 0.037).abs() < 1e-9, "{v:?} n={n} k={k}: {est}");
                        assert_eq!(f.window(), n);
                    }
                }
            }
        }
    }

    /// With a huge bound every window is valid: FOAW reduces to the fixed
    /// window of `max_window` periods (end-fit) or to the least-squares slope
    /// over it (best-fit). With a tiny bound on noisy data no window beyond
    /// n = 1 is valid: it reduces to the finite difference.
    #[test]
    fn degenerate_bounds_reduce_to_classical_estimators() {
        const N: usize = 8;
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let y: Vec<f64> = (0..200).map(|_| rng.gen_range(-1.0..1.0)).collect();
        let mut end = axis(FoawVariant::EndFit, 1e9, N);
        let mut lsq = axis(FoawVariant::BestFit, 1e9, N);
        let mut tiny = [
            axis(FoawVariant::EndFit, 1e-12, N),
            axis(FoawVariant::BestFit, 1e-12, N),
        ];
        for k in 0..y.len() {
            let (e, l) = (end.update(y[k]), lsq.update(y[k]));
            let t: Vec<f64> = tiny.iter_mut().map(|f| f.update(y[k])).collect();
            if k < N {
                continue;
            }
            let fixed = (y[k] - y[k - N]) / (N as f64 * T);
            assert!((e - fixed).abs() < 1e-9);
            // Textbook least-squares slope of y against time over the window.
            let w = &y[k - N..=k];
            let tm = N as f64 / 2.0;
            let ym = w.iter().sum::<f64>() / w.len() as f64;
            let (mut sxy, mut sxx) = (0.0, 0.0);
            for (j, &yj) in w.iter().enumerate() {
                sxy += (j as f64 - tm) * (yj - ym);
                sxx += (j as f64 - tm).powi(2);
            }
            assert!((l - sxy / sxx / T).abs() < 1e-9, "{l} vs {}", sxy / sxx / T);
            let fd = (y[k] - y[k - 1]) / T;
            for (f, est) in tiny.iter().zip(&t) {
                assert!((est - fd).abs() < 1e-9);
                assert_eq!(f.window(), 1);
            }
        }
    }

    /// History (oldest first) 0, 0, ..., 0, -a, a, 0 with d = 1: the n = 2
    /// window is invalid but n = 3 (and longer) would be valid, so only a
    /// search that stops at the first failure returns n = 1.
    /// End-fit: n = 2 deviates by 1.5a, n = 3 by a, so a in (2/3, 1].
    /// Best-fit: least-squares residuals peak at a for n = 2 and at 0.9a for
    /// n = 3, so a in (1, 1/0.9].
    #[test]
    fn search_stops_at_first_invalid_window() {
        for (v, a) in [(FoawVariant::EndFit, 0.9), (FoawVariant::BestFit, 1.05)] {
            let mut f = axis(v, 1.0, 8);
            for x in [0.0, -a, a] {
                f.update(x);
            }
            let est = f.update(0.0);
            assert!((est + a / T).abs() < 1e-9, "{v:?}: {est}");
            assert_eq!(f.window(), 1, "{v:?}");
        }
    }

    /// On y = a t²/2 the end-fit chord over n periods deviates from the
    /// parabola by a T² i (n - i) / 2 at age i, at most a T² ⌊n²/4⌋ / 2; the
    /// chosen window is the largest n keeping that within d, and the chord
    /// slope equals the true velocity at the window midpoint.
    #[test]
    fn end_fit_window_on_parabola_matches_analysis() {
        let (a, d) = (2.0, 3.2e-5); // a T²/2 = 1e-6: ⌊n²/4⌋ <= 32 -> n = 11
        let expected = (1..=MAX_WINDOW)
            .take_while(|&n| a * T * T * ((n * n / 4) as f64) / 2.0 <= d)
            .last()
            .unwrap();
        assert_eq!(expected, 11);
        let mut f = axis(FoawVariant::EndFit, d, 32);
        for k in 0..200 {
            let t = k as f64 * T;
            let est = f.update(a * t * t / 2.0);
            if k >= 32 {
                assert_eq!(f.window(), expected, "k={k}");
                let mid = t - expected as f64 * T / 2.0;
                assert!((est - a * mid).abs() < 1e-6, "k={k}: {est} vs {}", a * mid);
            }
        }
    }

    #[test]
    fn window_adapts_to_ramp_and_step() {
        const N: usize = 32;
        const H: f64 = 0.01;
        for v in VARIANTS {
            // Noiseless: a slow ramp keeps the full window, a step cuts it to
            // the samples taken since the step (all older windows straddle it).
            let mut f = axis(v, 4e-6, N);
            for k in 0..400 {
                let step = 200;
                let x = 1e-3 * k as f64 * T + if k >= step { H } else { 0.0 };
                f.update(x);
                // Before k = N the window still reaches back into the
                // pre-filled (resting) history, a corner of its own.
                let expected = match k {
                    k if k < N => continue,
                    k if k < step => N,
                    k => (k - step).clamp(1, N),
                };
                assert_eq!(f.window(), expected, "{v:?} k={k}");
            }
            // Noisy: long windows on the slow ramp, short right after a step.
            // The least-squares line averages the noise out, so its residuals
            // rarely reach d and most windows are full. The end-fit chord runs
            // through two noisy samples, each up to d off, so inner samples may
            // sit up to 2d from it and windows are cut at random lengths; they
            // must still be several periods long on average.
            let (d, mut meas) = noisy(11);
            let mut f = axis(v, d, N);
            let (mut sum, mut full, mut count) = (0, 0, 0);
            for k in 0..1000 {
                f.update(meas(1e-3 * k as f64 * T));
                if k >= N {
                    sum += f.window();
                    full += usize::from(f.window() == N);
                    count += 1;
                }
            }
            let mean = sum as f64 / count as f64;
            match v {
                FoawVariant::EndFit => assert!(mean > 4.0, "mean end-fit window {mean}"),
                FoawVariant::BestFit => assert!(2 * full > count, "{full}/{count} full"),
            }
            f.update(meas(1e-3 + H));
            assert_eq!(f.window(), 1, "{v:?}: at the step");
            for j in 1..5 {
                f.update(meas(1e-3 + H));
                assert!(f.window() <= j, "{v:?}: {j} after step: {}", f.window());
            }
        }
    }

    #[test]
    fn non_finite_input_resets() {
        for v in VARIANTS {
            let mut f = axis(v, 1e-6, 16);
            for k in 0..50 {
                f.update(0.01 * k as f64);
            }
            for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
                assert_eq!(f.update(bad), 0.0);
                assert_eq!(f.window(), 0);
                // The next finite sample pre-fills: no jump from the old history.
                assert_eq!(f.update(5.0), 0.0);
                assert_eq!(f.update(5.0), 0.0);
            }
        }
        let mut f = Foaw::new(FoawVariant::BestFit, 1e-6, 8, T).unwrap();
        for k in 0..20 {
            f.update(&Vector3::repeat(k as f64 * T));
        }
        let v = f.update(&Vector3::new(f64::NAN, 20.0 * T, 20.0 * T));
        assert_eq!(v.x, 0.0);
        assert!((v.y - 1.0).abs() < 1e-9 && (v.z - 1.0).abs() < 1e-9);
    }

    #[test]
    fn extreme_finite_input_does_not_panic() {
        for v in VARIANTS {
            let mut f = axis(v, 1e-6, MAX_WINDOW);
            let xs = [f64::MAX, -f64::MAX, 0.0, f64::MIN_POSITIVE, 1e-320, 1e300];
            for k in 0..500 {
                f.update(xs[k % xs.len()] * if k % 7 == 0 { -1.0 } else { 1.0 });
                assert!((1..=MAX_WINDOW).contains(&f.window()));
            }
            // Large but non-overflowing values give finite estimates.
            f.reset();
            for k in 0..500 {
                assert!(f.update(1e300 * (k as f64).sin()).is_finite());
            }
        }
    }

    #[test]
    fn foaw_3d_is_per_axis() {
        let mut f3 = Foaw::new(FoawVariant::EndFit, 4e-6, 16, T).unwrap();
        let mut f1: Vec<FoawAxis> = (0..3)
            .map(|_| axis(FoawVariant::EndFit, 4e-6, 16))
            .collect();
        let (_, mut meas) = noisy(3);
        for k in 0..500 {
            let t = k as f64 * T;
            let x = Vector3::new(meas(0.02 * (TAU * t).sin()), meas(0.1 * t), meas(0.0));
            let v = f3.update(&x);
            for i in 0..3 {
                assert_eq!(v[i], f1[i].update(x[i]));
            }
        }
        f3.reset();
        assert_eq!(f3.update(&Vector3::new(1.0, 2.0, 3.0)), Vector3::zeros());
    }

    /// Measurement model: uniform noise of peak 3 µm plus quantisation to
    /// 2 µm, so the true peak error bound is d = 3 + 1 = 4 µm. Returns d and
    /// a deterministic measuring closure.
    fn noisy(seed: u64) -> (f64, impl FnMut(f64) -> f64) {
        const NOISE: f64 = 3e-6;
        const Q: f64 = 2e-6;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let u = Uniform::new_inclusive(-NOISE, NOISE);
        (NOISE + Q / 2.0, move |x: f64| {
            ((x + rng.sample(u)) / Q).round() * Q
        })
    }

    /// RMS velocity errors of (FOAW, finite difference, fixed N-period
    /// window) over samples `k >= warm_up` not excluded by `skip`.
    fn rms_errors(
        variant: FoawVariant,
        n: usize,
        seed: u64,
        len: usize,
        pos: impl Fn(f64) -> f64,
        vel: impl Fn(f64) -> f64,
        skip: impl Fn(usize) -> bool,
    ) -> [f64; 3] {
        let (d, mut meas) = noisy(seed);
        let y: Vec<f64> = (0..len).map(|k| meas(pos(k as f64 * T))).collect();
        let mut f = axis(variant, d, n);
        let mut sq = [0.0; 3];
        let mut count = 0;
        for (k, &yk) in y.iter().enumerate() {
            let est = f.update(yk);
            if k < n + 50 || skip(k) {
                continue;
            }
            let truth = vel(k as f64 * T);
            let fd = (yk - y[k - 1]) / T;
            let fixed = (yk - y[k - n]) / (n as f64 * T);
            for (s, e) in sq.iter_mut().zip([est, fd, fixed]) {
                *s += (e - truth).powi(2);
            }
            count += 1;
        }
        sq.map(|s| (s / count as f64).sqrt())
    }

    fn assert_beats(what: &str, v: FoawVariant, [foaw, fd, fixed]: [f64; 3], vs_fixed: bool) {
        assert!(
            foaw < fd,
            "{what} {v:?}: FOAW {foaw} vs finite difference {fd}"
        );
        if vs_fixed {
            assert!(
                foaw < fixed,
                "{what} {v:?}: FOAW {foaw} vs fixed window {fixed}"
            );
        }
    }

    /// On a pure ramp the fixed window has no lag, so it is the yardstick
    /// rather than a baseline to beat: best-fit uses all n + 1 samples and
    /// beats it, end-fit (an end-point difference over a window at most as
    /// long, often cut short by noise) cannot and is only checked against the
    /// finite difference.
    #[test]
    fn noisy_ramp_beats_baselines() {
        for v in VARIANTS {
            for n in [16, 32] {
                let e = rms_errors(v, n, 1, 3000, |t| 0.05 * t, |_| 0.05, |_| false);
                assert_beats("ramp", v, e, v == FoawVariant::BestFit);
            }
        }
    }

    /// 20 mm at 1 Hz (peak acceleration 0.79 m/s²). The claim only holds in a
    /// band of accelerations, for well-understood reasons. On a curve of
    /// acceleration a, the chord stays within d of the samples for windows
    /// up to ~√(8d/a) long, and its slope lags by half the window: a velocity
    /// bias of up to ~√(2da). Best-fit lags more, because least-squares
    /// residuals are smaller and it accepts longer windows. With this noise
    /// (d = 4 µm) the bias makes FOAW lose to the finite difference (noise
    /// ~2.6 mm/s RMS) at 20 mm / 1.5 Hz for best-fit and 2 Hz for end-fit.
    /// At 0.5 Hz and below the lag of a 16-period fixed window is small
    /// enough that it beats end-fit (and at 0.25 Hz best-fit too).
    #[test]
    fn noisy_sine_beats_baselines() {
        let (a, w) = (0.02, TAU);
        for v in VARIANTS {
            for n in [16, 32] {
                let e = rms_errors(
                    v,
                    n,
                    2,
                    3000,
                    |t| a * (w * t).sin(),
                    |t| a * w * (w * t).cos(),
                    |_| false,
                );
                assert_beats("sine", v, e, true);
            }
        }
    }

    /// A 10 mm step at rest. The true velocity is 0 everywhere except at the
    /// step instant, where it is a Dirac impulse and no sampled estimate has a
    /// meaningful error, so that one sample is left out of the comparison.
    /// The fixed window smears the step over N samples; FOAW cuts its window
    /// at the step and uses long windows on either side.
    #[test]
    fn noisy_step_beats_baselines() {
        const STEP: usize = 1500;
        for v in VARIANTS {
            for n in [16, 32] {
                let e = rms_errors(
                    v,
                    n,
                    3,
                    3000,
                    |t| {
                        if t >= STEP as f64 * T - T / 2.0 {
                            0.01
                        } else {
                            0.0
                        }
                    },
                    |_| 0.0,
                    |k| k == STEP,
                );
                assert_beats("step", v, e, true);
            }
        }
    }

    /// Window chosen by exact arithmetic on integer positions `m` (quanta,
    /// newest first) with the bound `dq` quanta: residuals scaled to whole
    /// numbers, so a residual equal to the bound is exactly a tie, accepted
    /// (as both published definitions say) if `ties`, rejected otherwise.
    fn exact_window(variant: FoawVariant, m: &[i64], dq: i64, ties: bool) -> usize {
        let z: Vec<i128> = m.iter().map(|&v| i128::from(v - m[0])).collect();
        let dq = i128::from(dq);
        let within = |r: i128, bound: i128| r.abs() < bound || (ties && r.abs() == bound);
        let valid = |n: usize| {
            let nn = n as i128;
            match variant {
                // n times the residual of sample i: n z_i - i z_n.
                FoawVariant::EndFit => {
                    (1..n).all(|i| within(nn * z[i] - i as i128 * z[n], dq * nn))
                }
                // With den = n(n+1)(n+2), B = 12 S_iz - 6n S_z = den b and
                // A = 2n(n+2) S_z - n B = 2 den a: 2 den r_j = 2 den z_j - A - 2 B j.
                FoawVariant::BestFit => {
                    let (s_z, s_iz) = best_fit_sums(&z, n);
                    let den = nn * (nn + 1) * (nn + 2);
                    let b = 12 * s_iz - 6 * nn * s_z;
                    let a = 2 * nn * (nn + 2) * s_z - nn * b;
                    (0..=n).all(|j| within(2 * den * z[j] - a - 2 * b * j as i128, 2 * den * dq))
                }
            }
        };
        (2..m.len()).take_while(|&n| valid(n)).last().unwrap_or(1)
    }

    /// `S_z = Σ z_j` and `S_iz = Σ j z_j` over `j = 0..=n`.
    fn best_fit_sums(z: &[i128], n: usize) -> (i128, i128) {
        let s_z = z[..=n].iter().sum();
        let s_iz = (0..=n).map(|j| j as i128 * z[j]).sum();
        (s_z, s_iz)
    }

    /// The method's velocity, in quanta per period, from the window of `n`
    /// periods over integer positions `m` (newest first): the slope of the
    /// variant's line, an exact ratio rounded once.
    fn exact_slope(variant: FoawVariant, m: &[i64], n: usize) -> f64 {
        let z: Vec<i128> = m.iter().map(|&v| i128::from(v - m[0])).collect();
        let nn = n as i128;
        match variant {
            FoawVariant::EndFit => -z[n] as f64 / n as f64,
            FoawVariant::BestFit => {
                let (s_z, s_iz) = best_fit_sums(&z, n);
                -((12 * s_iz - 6 * nn * s_z) as f64) / (nn * (nn + 1) * (nn + 2)) as f64
            }
        }
    }

    /// The estimator before the tie fix (commit 78e0dea), its search
    /// functions verbatim: "before" in [`velocity_error_is_the_methods_with_ties_accepted`].
    /// Its tests are plain `<= d` on residuals computed in doubles, so a
    /// residual that is exactly `d` passes or fails by roundoff.
    mod pre_fix {
        pub fn end_fit(h: &[f64], d: f64) -> (usize, f64) {
            let y0 = h[0];
            let mut best = (1, y0 - h[1]);
            for n in 2..h.len() {
                let s = (y0 - h[n]) / n as f64;
                // The line has value y0 - s*i at age i; residual = (y - y0) + s*i.
                let mut i = 0.0;
                let fits = h[1..n].iter().all(|&y| {
                    i += 1.0;
                    ((y - y0) + s * i).abs() <= d
                });
                if !fits {
                    break;
                }
                best = (n, s);
            }
            best
        }

        pub fn best_fit(h: &[f64], d: f64) -> (usize, f64) {
            let y0 = h[0];
            let z1 = h[1] - y0;
            // n = 1: the two-point fit is exact, hence always valid.
            let (mut s_z, mut s_iz) = (z1, z1);
            let mut best = (1, -z1);
            for n in 2..h.len() {
                let nf = n as f64;
                let z = h[n] - y0;
                s_z += z;
                s_iz += nf * z;
                let b = (12.0 * s_iz - 6.0 * nf * s_z) / (nf * (nf + 1.0) * (nf + 2.0));
                let a = s_z / (nf + 1.0) - 0.5 * b * nf;
                let mut line = a;
                let fits = h[..=n].iter().all(|&y| {
                    let ok = ((y - y0) - line).abs() <= d;
                    line += b;
                    ok
                });
                if !fits {
                    break;
                }
                best = (n, -b);
            }
            best
        }
    }

    /// 20 mm minimum-jerk reaches of 0.4 s, each followed by a 0.4 s hold,
    /// back and forth: (position, velocity) at time t.
    fn reach_and_hold(t: f64) -> (f64, f64) {
        const H: f64 = 0.02;
        const D: f64 = 0.4;
        let (p, back) = (t % (4.0 * D), t % (4.0 * D) >= 2.0 * D);
        let s = ((p % (2.0 * D)) / D).min(1.0);
        let pos = H * s.powi(3) * (10.0 - 15.0 * s + 6.0 * s * s);
        let vel = if s < 1.0 {
            H * 30.0 * s * s * (1.0 - s).powi(2) / D
        } else {
            0.0
        };
        if back {
            (H - pos, -vel)
        } else {
            (pos, vel)
        }
    }

    /// A 20 mm sine of `f` Hz: (position, velocity) at time t.
    fn sine_hz(f: f64, t: f64) -> (f64, f64) {
        (
            0.02 * (TAU * f * t).sin(),
            0.02 * TAU * f * (TAU * f * t).cos(),
        )
    }

    /// The benchmark's 20 mm, 1 Hz sine (peak acceleration 0.79 m/s²).
    fn sine(t: f64) -> (f64, f64) {
        sine_hz(1.0, t)
    }

    fn slow_sine(t: f64) -> (f64, f64) {
        sine_hz(0.5, t)
    }

    fn fast_sine(t: f64) -> (f64, f64) {
        sine_hz(2.0, t)
    }

    /// Positions in quanta `q`, 4000 samples of the trajectory plus an offset,
    /// measured with uniform noise of ±(`dq` - 1/2) quanta drawn from `seed`:
    /// with the rounding, the error is within `d` = `dq` quanta, and residuals
    /// of exactly `d` are common.
    fn quantised(q: f64, offset: f64, path: fn(f64) -> (f64, f64), dq: i64, seed: u64) -> Vec<i64> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let half = dq as f64 - 0.5;
        let noise = Uniform::new_inclusive(-half, half);
        (0..4000)
            .map(|k| ((offset + path(k as f64 * T).0) / q + rng.sample(noise)).round() as i64)
            .collect()
    }

    /// History (newest first, `window + 1` samples) at sample `k`: the
    /// estimator pre-fills its history with the first sample.
    fn history<X: Copy>(m: &[X], k: usize, window: usize) -> impl Iterator<Item = X> + '_ {
        (0..=window).map(move |i| m[k.saturating_sub(i)])
    }

    /// Fraction of samples whose window equals the exact one on
    /// [`quantised`] positions (seed 19), with `d` = 2 quanta.
    fn against_exact(
        variant: FoawVariant,
        window: usize,
        q: f64,
        offset: f64,
        path: fn(f64) -> (f64, f64),
    ) -> f64 {
        let m = quantised(q, offset, path, 2, 19);
        let mut f = axis(variant, 2.0 * q, window);
        let mut same = 0;
        for (k, &mk) in m.iter().enumerate() {
            f.update(mk as f64 * q);
            let hist: Vec<i64> = history(&m, k, window).collect();
            same += usize::from(f.window() == exact_window(variant, &hist, 2, true));
        }
        same as f64 / m.len() as f64
    }

    /// RMS velocity errors (m/s) against the true derivative, after the first
    /// 100 samples, on [`quantised`] positions at 2 µm around 0 with `d` =
    /// `dq` quanta, of: hgcd's estimator, the method in exact arithmetic
    /// (ties accepted), the estimator before the tie fix, and exact arithmetic
    /// with ties rejected. Checks on every sample that the pre-fix window lies
    /// between the two exact ones (roundoff only ever decided ties), and that
    /// hgcd's window is the exact one on at least 99 % of samples (it is on
    /// all of them).
    fn velocity_rms(
        variant: FoawVariant,
        window: usize,
        path: fn(f64) -> (f64, f64),
        dq: i64,
        seed: u64,
    ) -> [f64; 4] {
        const Q: f64 = 2e-6;
        let d = dq as f64 * Q;
        let m = quantised(Q, 0.0, path, dq, seed);
        let mut f = axis(variant, d, window);
        let mut sq = [0.0; 4];
        let mut differ = 0;
        for (k, &mk) in m.iter().enumerate() {
            let est = f.update(mk as f64 * Q);
            let hist: Vec<i64> = history(&m, k, window).collect();
            let h: Vec<f64> = hist.iter().map(|&v| v as f64 * Q).collect();
            let (n_before, before) = match variant {
                FoawVariant::EndFit => pre_fix::end_fit(&h, d),
                FoawVariant::BestFit => pre_fix::best_fit(&h, d),
            };
            let [n_exact, n_strict] = [true, false].map(|t| exact_window(variant, &hist, dq, t));
            assert!(
                (n_strict..=n_exact).contains(&n_before),
                "{variant:?} seed {seed}, sample {k}: pre-fix window {n_before} outside \
                 {n_strict}..={n_exact}"
            );
            differ += usize::from(f.window() != n_exact);
            if k >= 100 {
                let truth = path(k as f64 * T).1;
                let slope = |n: usize| exact_slope(variant, &hist, n) * Q / T;
                let all = [est, slope(n_exact), before / T, slope(n_strict)];
                for (s, e) in sq.iter_mut().zip(all) {
                    *s += (e - truth).powi(2);
                }
            }
        }
        assert!(
            differ * 100 <= m.len(),
            "{variant:?} seed {seed}: {differ} windows of {} differ from exact arithmetic",
            m.len()
        );
        sq.map(|s| (s / (m.len() - 100) as f64).sqrt())
    }

    /// Encoders quantise positions, and with `d` a whole number of quanta many
    /// residuals equal `d` exactly; both published definitions accept them
    /// ("within d"). Computed from doubles they land a hair above or below
    /// `d`. The window choice must equal exact integer arithmetic on at least
    /// 99 % of samples, for both variants, windows 16 and 32, quanta of 2 µm
    /// (the benchmark's) and 0.25 µm, around 0 and around 0.1 m. Every sample
    /// agrees on these inputs. Before the fix, which rejected ties, at 2 µm
    /// around 0 end-fit agreed on 77 % of the sine's samples and 70 % of the
    /// reaches', best-fit on 95 % and 98 %.
    #[test]
    fn windows_on_quantised_positions_equal_exact_arithmetic() {
        for v in VARIANTS {
            for window in [16, 32] {
                for (q, offset) in [(2e-6, 0.0), (2e-6, 0.1), (0.25e-6, 0.0), (0.25e-6, 0.1)] {
                    for path in [sine as fn(f64) -> (f64, f64), reach_and_hold] {
                        let same = against_exact(v, window, q, offset, path);
                        assert!(
                            same >= 0.99,
                            "{v:?} window {window}, q {q}, offset {offset}: {:.2} % exact",
                            100.0 * same
                        );
                    }
                }
            }
        }
    }

    /// Accepting ties lengthens windows to what the method defines: longer
    /// windows average more noise out and lag more under acceleration, so
    /// whether the velocity error falls or rises depends on which of the two
    /// dominates. Velocity RMS error against the true derivative, mean over
    /// noise seeds 0..50 of each seed's RMS, in mm/s, on [`quantised`]
    /// positions (2 µm quanta, `d` = 1, 2 or 3 quanta, noise ±(`d` - 1/2
    /// quantum)); "before" is the estimator of commit 78e0dea ([`pre_fix`]),
    /// "strict" exact arithmetic with ties rejected. Window 16; at the benchmark's
    /// `d` = 2 window 32 runs too, its changes within 0.16 points of these:
    ///
    /// | variant  | d | path           | before | after  | change  | strict |
    /// | -------- | - | -------------- | ------ | ------ | ------- | ------ |
    /// | end-fit  | 1 | 0.5 Hz sine    | 0.7718 | 0.5753 | -25.5 % | 0.8889 |
    /// | end-fit  | 1 | 1 Hz sine      | 1.1335 | 1.1666 |  +2.9 % | 1.1500 |
    /// | end-fit  | 1 | 2 Hz sine      | 2.1259 | 2.4329 | +14.4 % | 1.9369 |
    /// | end-fit  | 1 | reach and hold | 0.7631 | 0.7737 |  +1.4 % | 0.7787 |
    /// | end-fit  | 2 | 0.5 Hz sine    | 1.6015 | 1.3026 | -18.7 % | 1.7988 |
    /// | end-fit  | 2 | 1 Hz sine      | 1.8812 | 1.7141 |  -8.9 % | 2.0131 |
    /// | end-fit  | 2 | 2 Hz sine      | 3.0695 | 3.1678 |  +3.2 % | 3.0070 |
    /// | end-fit  | 2 | reach and hold | 1.4857 | 1.1648 | -21.6 % | 1.6848 |
    /// | end-fit  | 3 | 0.5 Hz sine    | 2.6553 | 2.4279 |  -8.6 % | 2.9513 |
    /// | end-fit  | 3 | 1 Hz sine      | 2.8368 | 2.6568 |  -6.3 % | 3.0921 |
    /// | end-fit  | 3 | 2 Hz sine      | 3.9313 | 3.9349 |  +0.1 % | 3.9976 |
    /// | end-fit  | 3 | reach and hold | 2.4707 | 2.3655 |  -4.3 % | 2.8734 |
    /// | best-fit | 1 | 0.5 Hz sine    | 0.6942 | 0.6883 |  -0.9 % | 0.7033 |
    /// | best-fit | 1 | 1 Hz sine      | 1.4958 | 1.5200 |  +1.6 % | 1.4761 |
    /// | best-fit | 1 | 2 Hz sine      | 3.0959 | 3.2650 |  +5.5 % | 2.9834 |
    /// | best-fit | 1 | reach and hold | 0.9956 | 1.0146 |  +1.9 % | 0.9830 |
    /// | best-fit | 2 | 0.5 Hz sine    | 0.8930 | 0.8589 |  -3.8 % | 0.9433 |
    /// | best-fit | 2 | 1 Hz sine      | 1.9499 | 1.9537 | +0.19 % | 1.9591 |
    /// | best-fit | 2 | 2 Hz sine      | 4.1868 | 4.2695 |  +2.0 % | 4.1017 |
    /// | best-fit | 2 | reach and hold | 1.2952 | 1.2937 | -0.12 % | 1.3027 |
    /// | best-fit | 3 | 0.5 Hz sine    | 1.1259 | 0.9973 | -11.4 % | 1.2195 |
    /// | best-fit | 3 | 1 Hz sine      | 2.2775 | 2.2317 |  -2.0 % | 2.3185 |
    /// | best-fit | 3 | 2 Hz sine      | 4.9254 | 4.9580 | +0.66 % | 4.8905 |
    /// | best-fit | 3 | reach and hold | 1.5216 | 1.4904 |  -2.1 % | 1.5469 |
    ///
    /// hgcd's error equals that of the method in exact arithmetic in every
    /// case (asserted): where it is worse than before, the method is, not its
    /// evaluation. Before the fix, roundoff rejected some ties at random, so
    /// its windows lay between the exact ones with ties rejected and accepted
    /// (asserted on every sample), and its error with them, or below both
    /// where the best window for the error is in between (best-fit, `d` = 2,
    /// 1 Hz). Where noise dominates (slow motion, larger `d`) accepting ties
    /// helps, up to 25 %; where lag does (the 2 Hz sine, `d` = 1 quantum) it
    /// costs up to 14 % (end-fit) and 5.5 % (best-fit). Each case asserts its
    /// measured direction with a margin: "no worse" where it gained, at least
    /// 5 % better where it gained more than that (this fails if ties are
    /// rejected again), and a bound above the measured change where it lost.
    /// With `--nocapture` the test prints this table.
    #[test]
    fn velocity_error_is_the_methods_with_ties_accepted() {
        use FoawVariant::{BestFit, EndFit};
        type Path = fn(f64) -> (f64, f64);
        const SEEDS: std::ops::Range<u64> = 0..50;
        const PATHS: [(&str, Path); 4] = [
            ("0.5 Hz sine", slow_sine),
            ("1 Hz sine", sine),
            ("2 Hz sine", fast_sine),
            ("reach and hold", reach_and_hold),
        ];
        // Per variant and d (quanta), per path as in PATHS: the largest
        // allowed after / before.
        let bounds: [(FoawVariant, i64, [f64; 4]); 6] = [
            (EndFit, 1, [0.95, 1.035, 1.15, 1.02]),
            (EndFit, 2, [0.95, 0.95, 1.035, 0.95]),
            (EndFit, 3, [0.95, 0.95, 1.005, 1.0]),
            (BestFit, 1, [1.0, 1.02, 1.06, 1.025]),
            (BestFit, 2, [1.0, 1.005, 1.025, 1.0]),
            (BestFit, 3, [0.95, 1.0, 1.01, 1.0]),
        ];
        for (v, dq, bound) in bounds {
            for ((name, path), bound) in PATHS.into_iter().zip(bound) {
                let windows: &[usize] = if dq == 2 { &[16, 32] } else { &[16] };
                for &window in windows {
                    let mut mean = [0.0; 4];
                    for s in SEEDS {
                        let rms = velocity_rms(v, window, path, dq, s);
                        for (m, r) in mean.iter_mut().zip(rms) {
                            *m += 1e3 * r / SEEDS.count() as f64;
                        }
                    }
                    let [after, exact, before, strict] = mean;
                    let change = 100.0 * (after / before - 1.0);
                    println!(
                        "| {v:?} | {dq} | {name} | {window} | {before:.4} | {after:.4} \
                         | {change:+.2} % | {strict:.4} |"
                    );
                    assert!(
                        (after - exact).abs() <= 1e-9 * exact,
                        "{v:?} d {dq} {name} window {window}: {after} mm/s, exact {exact} mm/s"
                    );
                    assert!(
                        after <= before * bound,
                        "{v:?} d {dq} {name} window {window}: {after:.4} mm/s, before \
                         {before:.4} mm/s, bound {bound} times before"
                    );
                }
            }
        }
    }
}
