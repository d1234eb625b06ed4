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
    /// window.
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
///   line through `y_k` with slope `b_n`.
/// * [`FoawVariant::BestFit`]: the line is the least-squares fit (slope *and*
///   intercept) through `y_{k-n} ..= y_k`, and every one of those `n + 1`
///   samples must lie within `d` of it. This is the least-squares variant on
///   purpose; some public implementations instead force the line through the
///   newest sample. Running sums make each slope O(1); the check is O(n).
///
/// The search stops at the first invalid window and returns the slope of the
/// last valid one, so the cost per sample is O(n²) in the chosen window.
/// `n = 1` (the plain finite difference) is always valid.
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

/// End-fit search over `h` (newest first, `h.len() >= 2`). Returns the window
/// and the slope in units per sample.
fn end_fit(h: &[f64], d: f64) -> (usize, f64) {
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

/// Three independent [`FoawAxis`] estimators, one per Cartesian axis, sharing
/// the same parameters (the peak-norm bound `d` applies to each axis).
#[derive(Clone, Debug)]
pub struct Foaw {
    axes: [FoawAxis; 3],
}

impl Foaw {
    /// See [`FoawAxis::new`].
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
}
