//! The analysis: derivatives of the measured position, the nominal model's force residual, each
//! candidate effect fitted on the first part of the log and scored on the rest, and the decision
//! (docs/discrepancy.md §2).

use nalgebra::{DMatrix, DVector, Rotation3, Vector3};

use super::effects::{across, Effect, Sample, STICK_SPEED};
use super::log::{Excitation, Log};
use crate::control::compensation::GravityModel;

/// Share of the log the models are fitted on; the rest is held out to score them.
pub const TRAIN_SHARE: f64 = 0.6;
/// Half-width of the Savitzky–Golay window, s: ±15 ms passes the excitation (up to about 4 Hz)
/// and averages out the encoder's steps in the second derivative.
pub const SMOOTHING_HALF_WIDTH: f64 = 0.015;
/// Effects are named only if together they cut the held-out error to at most this share of
/// the nominal model's.
pub const NAMING_SHRINK: f64 = 0.5;
/// Each effect added must cut the held-out error of those before it to at most this share.
pub const STEP_SHRINK: f64 = 0.8;
/// When no one effect qualifies and the held-out error stays above this many noise floors,
/// pairs are tried.
pub const GAP_FOR_PAIRS: f64 = 2.0;
/// A candidate with more parameters replaces a simpler one only if its held-out error is at most
/// this share of the simpler one's.
pub const COMPLEXITY_MARGIN: f64 = 0.75;
/// Time delays searched: 0 to this, s, in steps of [`DELAY_STEP`].
pub const MAX_DELAY: f64 = 0.04;
pub const DELAY_STEP: f64 = 2.5e-4;

/// The log, smoothed and differentiated, with the nominal gravity force at each sample. Index k
/// here is row `first + k` of the log (the window's half-width is lost at each end).
pub struct Signals {
    pub time: Vec<f64>,
    pub samples: Vec<Sample>,
    /// The command, smoothed as the position is and half a period late (as it acts), N.
    pub force: Vec<Vector3<f64>>,
    /// Sample period, s.
    pub period: f64,
    pub first: usize,
    /// Length of the smoothing window, samples.
    pub window: usize,
}

/// Savitzky–Golay weights for a quadratic over k = −m..m: smoothed value, first and second
/// derivative (per sample and per sample²).
pub(super) struct Weights {
    pub value: Vec<f64>,
    pub slope: Vec<f64>,
    pub curvature: Vec<f64>,
}

impl Weights {
    pub fn new(m: usize) -> Self {
        let mf = m as f64;
        let n = 2.0 * mf + 1.0;
        let s2 = mf * (mf + 1.0) * (2.0 * mf + 1.0) / 3.0;
        let s4 = mf * (mf + 1.0) * (2.0 * mf + 1.0) * (3.0 * mf * mf + 3.0 * mf - 1.0) / 15.0;
        let ks = (-(m as i64)..=m as i64).map(|k| k as f64);
        Self {
            value: ks
                .clone()
                .map(|k| {
                    3.0 * (3.0 * mf * mf + 3.0 * mf - 1.0 - 5.0 * k * k)
                        / ((4.0 * mf * mf - 1.0) * (2.0 * mf + 3.0))
                })
                .collect(),
            slope: ks.clone().map(|k| k / s2).collect(),
            curvature: ks
                .map(|k| 2.0 * (k * k - s2 / n) / (s4 - s2 * s2 / n))
                .collect(),
        }
    }

    fn apply(weights: &[f64], x: &[Vector3<f64>], centre: usize) -> Vector3<f64> {
        let m = weights.len() / 2;
        weights
            .iter()
            .zip(&x[centre - m..=centre + m])
            .map(|(w, v)| v * *w)
            .sum()
    }
}

impl Signals {
    /// Smooth and differentiate `log`; the gravity force from `model`.
    pub fn new(log: &Log, model: &GravityModel) -> Self {
        let period = log.period();
        let m = ((SMOOTHING_HALF_WIDTH / period).round() as usize).max(2);
        let w = Weights::new(m);
        let up = model.grid.gravity_direction;
        let g = model.grid.g;
        let range = m..log.len().saturating_sub(m);
        let mut signals = Signals {
            time: Vec::with_capacity(range.len()),
            samples: Vec::with_capacity(range.len()),
            force: Vec::with_capacity(range.len()),
            period,
            first: m,
            window: 2 * m + 1,
        };
        for k in range {
            let position = Weights::apply(&w.value, &log.position, k);
            signals.time.push(log.time[k]);
            signals.samples.push(Sample {
                position,
                velocity: Weights::apply(&w.slope, &log.position, k) / period,
                acceleration: Weights::apply(&w.curvature, &log.position, k) / (period * period),
                gravity: model.force(&position),
                up,
                g,
            });
            signals.force.push(Weights::apply(&w.value, &log.force, k));
        }
        // Each command holds over the period after its tick: on average it acts half a period
        // after the position it answers was sampled.
        signals.force = signals.delayed_force(period / 2.0);
        signals
    }

    pub fn len(&self) -> usize {
        self.samples.len()
    }

    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// Samples fitted on, and held out.
    pub fn split(&self) -> (std::ops::Range<usize>, std::ops::Range<usize>) {
        let cut = (self.len() as f64 * TRAIN_SHARE) as usize;
        (0..cut, cut..self.len())
    }

    /// The command as it reaches the handle `delay` s late (linear interpolation; the first
    /// samples repeat the first command).
    pub fn delayed_force(&self, delay: f64) -> Vec<Vector3<f64>> {
        let shift = delay / self.period;
        (0..self.len())
            .map(|k| {
                let at = (k as f64 - shift).max(0.0);
                let i = at.floor() as usize;
                let u = at - i as f64;
                let next = (i + 1).min(self.len() - 1);
                self.force[i] * (1.0 - u) + self.force[next] * u
            })
            .collect()
    }
}

/// One model fitted: the nominal one (no effect) or the nominal one with a set of effects, all
/// their parameters fitted jointly.
#[derive(Clone, Debug, PartialEq)]
pub struct Fit {
    /// The effects, in the order they were found.
    pub effects: Vec<Effect>,
    /// Moving mass along x, y, z, kg (fitted with the effects), and its standard error.
    pub moving_mass: Vector3<f64>,
    pub moving_mass_sd: Vector3<f64>,
    /// Each effect's linear parameters θ (see [`Effect`]) and their standard errors, in
    /// `effects` order.
    pub theta: Vec<Vec<f64>>,
    pub theta_sd: Vec<Vec<f64>>,
    /// The time delay beyond the sampling's half period, s, and its standard error (zero
    /// unless [`Effect::TimeDelay`] is in the set).
    pub delay: f64,
    pub delay_sd: f64,
    /// The rotation of gravity, rad (zero unless [`Effect::GravityTilt`] is in the set; its
    /// θ is then the last Gauss–Newton increment on it).
    pub rotation: Vector3<f64>,
    /// RMS of |residual| on the samples fitted on, and on those held out, N.
    pub train_error: f64,
    pub heldout_error: f64,
}

impl Fit {
    /// Whether `effect` is in the set.
    pub fn has(&self, effect: Effect) -> bool {
        self.effects.contains(&effect)
    }

    /// The linear parameters of `effect` (empty when it is not in the set).
    pub fn theta_of(&self, effect: Effect) -> &[f64] {
        self.effects
            .iter()
            .position(|e| *e == effect)
            .map_or(&[], |i| &self.theta[i])
    }

    /// `s` with gravity (and v_G) turned by the fit's rotation.
    fn turned(&self, s: &Sample) -> Sample {
        if self.rotation == Vector3::zeros() {
            return *s;
        }
        let r = Rotation3::new(self.rotation);
        Sample {
            gravity: r * s.gravity,
            up: r * s.up,
            ..*s
        }
    }

    /// The force the model needs for the motion at sample `s` (already turned), without the
    /// Coulomb term, N.
    fn smooth_force(&self, s: &Sample) -> Vector3<f64> {
        let mut columns = [Vector3::zeros(); 4];
        let mut f = s.gravity + s.acceleration.component_mul(&self.moving_mass);
        for (effect, theta) in self.effects.iter().zip(&self.theta) {
            if *effect == Effect::CoulombFriction {
                continue;
            }
            let n = effect.columns(s, &mut columns);
            for (c, t) in columns[..n].iter().zip(theta) {
                f += c * *t;
            }
        }
        f
    }

    /// The force the model says the device needs for the motion at sample `s`, N.
    pub fn model_force(&self, s: &Sample) -> Vector3<f64> {
        let s = self.turned(s);
        let mut f = self.smooth_force(&s);
        if let [f_c] = self.theta_of(Effect::CoulombFriction) {
            let mut columns = [Vector3::zeros(); 4];
            Effect::CoulombFriction.columns(&s, &mut columns);
            f += columns[0] * *f_c;
        }
        f
    }

    /// Command `f` minus what the model needs at `s`, N. A handle stuck in Coulomb friction
    /// (slower than [`STICK_SPEED`]) takes any force up to f_c: only the excess is residual.
    pub fn residual(&self, s: &Sample, f: &Vector3<f64>) -> Vector3<f64> {
        if let [f_c] = self.theta_of(Effect::CoulombFriction) {
            if s.velocity.norm() < STICK_SPEED {
                let r = f - self.smooth_force(&self.turned(s));
                let excess = r.norm() - f_c.max(0.0);
                return if excess > 0.0 {
                    r * (excess / r.norm())
                } else {
                    Vector3::zeros()
                };
            }
        }
        f - self.model_force(s)
    }

    /// The residual at every sample, N.
    pub fn residuals(&self, signals: &Signals) -> Vec<Vector3<f64>> {
        let force = if self.delay > 0.0 {
            signals.delayed_force(self.delay)
        } else {
            signals.force.clone()
        };
        signals
            .samples
            .iter()
            .zip(&force)
            .map(|(s, f)| self.residual(s, f))
            .collect()
    }

    /// The rotation of gravity this fit found, rad (zero without [`Effect::GravityTilt`]),
    /// and the standard error of its angle.
    pub fn tilt(&self, up: &Vector3<f64>) -> (Vector3<f64>, f64) {
        let (theta, sd) = match self.effects.iter().position(|e| *e == Effect::GravityTilt) {
            Some(i) => (&self.theta[i], &self.theta_sd[i]),
            None => return (Vector3::zeros(), 0.0),
        };
        let (e1, e2) = across(up);
        let rotation = self.rotation + e1 * theta[0] + e2 * theta[1];
        (rotation, sd[0].hypot(sd[1]))
    }

    /// The payload's mass, kg (zero without [`Effect::Payload`]).
    pub fn payload(&self) -> f64 {
        self.theta_of(Effect::Payload)
            .first()
            .copied()
            .unwrap_or(0.0)
    }
}

/// RMS of |r| over `range`.
pub fn rms(residuals: &[Vector3<f64>], range: std::ops::Range<usize>) -> f64 {
    let n = range.len().max(1) as f64;
    (residuals[range]
        .iter()
        .map(|r| r.norm_squared())
        .sum::<f64>()
        / n)
        .sqrt()
}

/// Least squares for the moving mass and the effects' θ on the training samples, with `force`
/// as the command and gravity turned by `rotation`. With Coulomb friction in the set, only the
/// samples in motion are fitted on. The standard errors come from the covariance σ² (ΦᵀΦ)⁻¹,
/// inflated by the smoothing window (neighbouring samples are not independent). None when the
/// regressors are degenerate.
fn fit_linear(
    effects: &[Effect],
    signals: &Signals,
    force: &[Vector3<f64>],
    delay: f64,
    rotation: Vector3<f64>,
) -> Option<Fit> {
    let p = 3 + effects.iter().map(|e| e.linear_parameters()).sum::<usize>();
    let mut fit = Fit {
        effects: effects.to_vec(),
        moving_mass: Vector3::zeros(),
        moving_mass_sd: Vector3::zeros(),
        theta: effects
            .iter()
            .map(|e| vec![0.0; e.linear_parameters()])
            .collect(),
        theta_sd: effects
            .iter()
            .map(|e| vec![0.0; e.linear_parameters()])
            .collect(),
        delay,
        delay_sd: 0.0,
        rotation,
        train_error: 0.0,
        heldout_error: 0.0,
    };
    let moving_only = effects.contains(&Effect::CoulombFriction);
    let (train, heldout) = signals.split();
    let mut normal = DMatrix::<f64>::zeros(p, p);
    let mut rhs = DVector::<f64>::zeros(p);
    let mut columns = [Vector3::zeros(); 4];
    let mut phi = vec![Vector3::zeros(); p];
    let (mut fitted, mut yy) = (0usize, 0.0);
    for k in train.clone() {
        let s = &fit.turned(&signals.samples[k]);
        if moving_only && s.velocity.norm() < STICK_SPEED {
            continue;
        }
        fitted += 1;
        let y = force[k] - s.gravity;
        yy += y.norm_squared();
        phi[0] = Vector3::new(s.acceleration.x, 0.0, 0.0);
        phi[1] = Vector3::new(0.0, s.acceleration.y, 0.0);
        phi[2] = Vector3::new(0.0, 0.0, s.acceleration.z);
        let mut at = 3;
        for effect in effects {
            let n = effect.columns(s, &mut columns);
            phi[at..at + n].copy_from_slice(&columns[..n]);
            at += n;
        }
        for i in 0..p {
            rhs[i] += phi[i].dot(&y);
            for j in i..p {
                normal[(i, j)] += phi[i].dot(&phi[j]);
            }
        }
    }
    for i in 0..p {
        for j in 0..i {
            normal[(i, j)] = normal[(j, i)];
        }
    }
    let cholesky = normal.clone().cholesky()?;
    let theta = cholesky.solve(&rhs);
    // Residual sum of squares on the fitted samples, σ² per component, and the covariance.
    let rss = (yy - 2.0 * theta.dot(&rhs) + (&normal * &theta).dot(&theta)).max(0.0);
    let dof = (3 * fitted).saturating_sub(p).max(1) as f64;
    let variance = rss / dof * signals.window as f64;
    let covariance = cholesky.inverse() * variance;
    let sd = |i: usize| covariance[(i, i)].max(0.0).sqrt();
    fit.moving_mass = Vector3::new(theta[0], theta[1], theta[2]);
    fit.moving_mass_sd = Vector3::new(sd(0), sd(1), sd(2));
    let mut at = 3;
    for (i, effect) in effects.iter().enumerate() {
        for j in 0..effect.linear_parameters() {
            fit.theta[i][j] = theta[at];
            fit.theta_sd[i][j] = sd(at);
            at += 1;
        }
    }
    let residuals: Vec<Vector3<f64>> = signals
        .samples
        .iter()
        .zip(force)
        .map(|(s, f)| fit.residual(s, f))
        .collect();
    fit.train_error = rms(&residuals, train);
    fit.heldout_error = rms(&residuals, heldout);
    Some(fit)
}

/// The nominal model: the grid's gravity force and a moving mass per axis.
pub fn nominal(signals: &Signals) -> Option<Fit> {
    fit_linear(&[], signals, &signals.force, 0.0, Vector3::zeros())
}

/// Gauss–Newton steps for the gravity tilt.
const TILT_STEPS: usize = 4;
/// The delay search: first every [`COARSE_DELAY_STEP`], then every [`DELAY_STEP`] around the
/// best.
const COARSE_DELAY_STEP: f64 = 1e-3;

/// The delay in `range` (s) that best explains the training samples, searched every `step`,
/// with the other effects fitted at each.
fn search_delay(
    effects: &[Effect],
    signals: &Signals,
    rotation: Vector3<f64>,
    range: (f64, f64),
    step: f64,
) -> Option<Fit> {
    let steps = ((range.1 - range.0) / step).round() as usize;
    (0..=steps)
        .map(|k| range.0 + k as f64 * step)
        .filter(|delay| *delay > 0.0 && *delay <= MAX_DELAY + 1e-12)
        .filter_map(|delay| {
            let force = signals.delayed_force(delay);
            fit_linear(effects, signals, &force, delay, rotation)
        })
        .min_by(|a, b| a.train_error.total_cmp(&b.train_error))
}

/// The delay's standard error from the curvature of the training error around the best delay,
/// inflated as the linear parameters' are.
fn delay_sd(effects: &[Effect], signals: &Signals, best: &Fit) -> f64 {
    let h = DELAY_STEP;
    let sse = |delay: f64| -> Option<f64> {
        let force = signals.delayed_force(delay);
        let f = fit_linear(effects, signals, &force, delay, best.rotation)?;
        Some(f.train_error.powi(2))
    };
    let (Some(lo), Some(hi)) = (sse(best.delay - h), sse(best.delay + h)) else {
        return DELAY_STEP;
    };
    let mid = best.train_error.powi(2);
    let curvature = (lo - 2.0 * mid + hi) / (h * h);
    let n = signals.split().0.len() as f64;
    if curvature > 0.0 {
        (2.0 * mid * signals.window as f64 / (n * curvature))
            .sqrt()
            .max(DELAY_STEP / 2.0)
    } else {
        DELAY_STEP
    }
}

/// `effects` fitted jointly on the training samples and scored on the held-out ones: the
/// linear parameters by least squares, a delay by search, a tilt by Gauss–Newton steps.
pub fn fit(effects: &[Effect], signals: &Signals) -> Option<Fit> {
    let has_delay = effects.contains(&Effect::TimeDelay);
    let has_tilt = effects.contains(&Effect::GravityTilt);
    let up = signals.samples.first()?.up;
    let tilt_steps = |mut fit: Fit| -> Option<Fit> {
        for _ in 0..TILT_STEPS {
            let force = signals.delayed_force(fit.delay);
            fit = fit_linear(effects, signals, &force, fit.delay, fit.tilt(&up).0)?;
        }
        Some(fit)
    };
    let mut fit = if has_delay {
        search_delay(
            effects,
            signals,
            Vector3::zeros(),
            (0.0, MAX_DELAY),
            COARSE_DELAY_STEP,
        )?
    } else {
        fit_linear(effects, signals, &signals.force, 0.0, Vector3::zeros())?
    };
    if has_tilt {
        fit = tilt_steps(fit)?;
    }
    if has_delay {
        let around = (fit.delay - COARSE_DELAY_STEP, fit.delay + COARSE_DELAY_STEP);
        fit = search_delay(effects, signals, fit.rotation, around, DELAY_STEP)?;
        if has_tilt {
            fit = tilt_steps(fit)?;
        }
        fit.delay_sd = delay_sd(effects, signals, &fit);
    }
    Some(fit)
}

/// One step of the selection: the set tried and its fit.
#[derive(Clone, Debug, PartialEq)]
pub struct Step {
    /// The effect this step added to the previous set.
    pub added: Effect,
    /// The previous set with `added`, fitted jointly.
    pub fit: Fit,
}

/// The selection (docs/discrepancy.md §2): from the nominal model, add a candidate that cuts
/// the held-out error to [`STEP_SHRINK`] of the current error or less (of those that do, the
/// simplest, unless one with more parameters does better again by [`COMPLEXITY_MARGIN`]),
/// refit all jointly, and repeat; when none qualifies while the error stays above
/// [`GAP_FOR_PAIRS`] noise floors `floor`, a pair that cuts it to [`STEP_SHRINK`]² with both
/// significant; then drop any named effect the others no longer need it
/// beside (without it the error grows by less than 1/[`STEP_SHRINK`]). The set stands only if
/// it cuts the nominal error to [`NAMING_SHRINK`] or less; otherwise nothing is named. Returns
/// the final fit, the steps taken and every candidate's fit at the first step. `candidates`
/// are the effects tried.
pub fn select(
    nominal: &Fit,
    signals: &Signals,
    candidates: &[Effect],
    floor: f64,
) -> (Fit, Vec<Step>, Vec<Fit>) {
    let mut current = nominal.clone();
    let mut steps = Vec::new();
    let mut first = Vec::new();
    let up = signals.samples.first().map_or(Vector3::z(), |s| s.up);
    loop {
        let trials: Vec<Fit> = candidates
            .iter()
            .filter(|e| !current.has(**e))
            .filter_map(|e| {
                let mut set = current.effects.clone();
                set.push(*e);
                fit(&set, signals)
            })
            .collect();
        if steps.is_empty() {
            first = trials.clone();
        }
        if let Some(chosen) = choose(&current, &trials, &up) {
            let added = *chosen.effects.last().expect("a trial adds an effect");
            steps.push(Step {
                added,
                fit: chosen.clone(),
            });
            current = chosen.clone();
            continue;
        }
        // No one effect pays its way, but the gap is still wide: two that hide each other
        // (friction and a delay both reshape the fast segments) may, added together, if both
        // are significant and together they pay two steps' worth.
        if current.heldout_error <= floor * GAP_FOR_PAIRS {
            break;
        }
        let left: Vec<Effect> = candidates
            .iter()
            .copied()
            .filter(|e| !current.has(*e))
            .collect();
        let pair = left
            .iter()
            .enumerate()
            .flat_map(|(i, a)| left[i + 1..].iter().map(move |b| (*a, *b)))
            .filter_map(|(a, b)| {
                let mut set = current.effects.clone();
                set.extend([a, b]);
                let fit = fit(&set, signals)?;
                let significant = [a, b].iter().all(|e| {
                    fit.main_parameter(*e, &up)
                        .is_some_and(|(value, sd)| value.abs() >= SIGNIFICANCE * sd)
                });
                (significant
                    && fit.heldout_error <= STEP_SHRINK * STEP_SHRINK * current.heldout_error)
                    .then_some(fit)
            })
            .min_by(|x, y| x.heldout_error.total_cmp(&y.heldout_error));
        let Some(pair) = pair else {
            break;
        };
        for added in &pair.effects[current.effects.len()..] {
            steps.push(Step {
                added: *added,
                fit: pair.clone(),
            });
        }
        current = pair;
    }
    // Backward: an effect the others now explain is dropped.
    while current.effects.len() > 1 {
        let without = current.effects.iter().enumerate().find_map(|(i, _)| {
            let mut set = current.effects.clone();
            set.remove(i);
            let reduced = fit(&set, signals)?;
            (current.heldout_error > STEP_SHRINK * reduced.heldout_error).then_some(reduced)
        });
        match without {
            Some(reduced) => current = reduced,
            None => break,
        }
    }
    if current.heldout_error > NAMING_SHRINK * nominal.heldout_error {
        current = nominal.clone();
    }
    (current, steps, first)
}

/// An effect whose parameter's standard error would grow this many times beside the named set
/// cannot be told from it: its signature lies (almost) in theirs.
pub const CONFOUNDED_INFLATION: f64 = 10.0;

/// Share of `main`'s squared norm that the span of `others` leaves, over the training samples
/// (1: independent; 1/inflation²: the parameter's standard error grows `inflation` times).
/// `columns(k, out)` writes sample k's columns, others first, main last.
fn independence(
    signals: &Signals,
    count: usize,
    columns: &dyn Fn(usize, &mut Vec<Vector3<f64>>),
) -> f64 {
    let mut gram = DMatrix::<f64>::zeros(count, count);
    let mut at = Vec::with_capacity(count);
    for k in signals.split().0 {
        at.clear();
        columns(k, &mut at);
        for i in 0..count {
            for j in i..count {
                gram[(i, j)] += at[i].dot(&at[j]);
            }
        }
    }
    for i in 0..count {
        for j in 0..i {
            gram[(i, j)] = gram[(j, i)];
        }
    }
    let m = count - 1;
    let main = gram[(m, m)];
    if main <= 0.0 {
        return 0.0;
    }
    let others = gram.view((0, 0), (m, m)).into_owned();
    let cross = gram.view((0, m), (m, 1)).into_owned();
    let tolerance = 1e-12 * others.amax().max(f64::MIN_POSITIVE);
    let projected = match others.svd(true, true).solve(&cross, tolerance) {
        Ok(b) => cross.dot(&b),
        Err(_) => 0.0,
    };
    ((main - projected) / main).max(0.0)
}

/// The candidates not in `named` that the log cannot tell from it, each with the named effects
/// whose signature holds its own: a candidate's main parameter (a spring's stiffness, a tilt's
/// two angles, a delay, the one parameter of the others) is confounded when its column, beside
/// the named set's (the moving mass included) and its own other columns, keeps less than
/// 1/[`CONFOUNDED_INFLATION`]² of its norm.
pub fn confounded(
    named: &Fit,
    signals: &Signals,
    candidates: &[Effect],
) -> Vec<(Effect, Vec<Effect>)> {
    if named.effects.is_empty() {
        return vec![];
    }
    let force_rate: Vec<Vector3<f64>> = (0..signals.len())
        .map(|k| {
            let (a, b) = (k.saturating_sub(1), (k + 1).min(signals.len() - 1));
            (signals.force[b] - signals.force[a]) / ((b - a).max(1) as f64 * signals.period)
        })
        .collect();
    let columns_of = |effect: Effect, s: &Sample, k: usize, out: &mut Vec<Vector3<f64>>| {
        if effect == Effect::TimeDelay {
            out.push(force_rate[k]);
            return;
        }
        let mut c = [Vector3::zeros(); 4];
        let n = effect.columns(s, &mut c);
        out.extend_from_slice(&c[..n]);
    };
    let limit = CONFOUNDED_INFLATION.powi(-2);
    // Whether `effect`'s main columns are held by `set`'s.
    let held = |set: &[Effect], effect: Effect| -> bool {
        let mains = match effect {
            Effect::GravityTilt => 2,
            _ => 1,
        };
        (0..mains).any(|main| {
            let write = |k: usize, out: &mut Vec<Vector3<f64>>| {
                let s = named.turned(&signals.samples[k]);
                out.push(Vector3::new(s.acceleration.x, 0.0, 0.0));
                out.push(Vector3::new(0.0, s.acceleration.y, 0.0));
                out.push(Vector3::new(0.0, 0.0, s.acceleration.z));
                for e in set {
                    columns_of(*e, &s, k, out);
                }
                let first = out.len();
                columns_of(effect, &s, k, out);
                // Its own main column last, its others before it.
                let last = out.len() - 1;
                out.swap(first + main, last);
            };
            let mut count = Vec::new();
            write(0, &mut count);
            independence(signals, count.len(), &write) < limit
        })
    };
    candidates
        .iter()
        .copied()
        .filter(|e| !named.has(*e) && held(&named.effects, *e))
        .map(|effect| {
            let sharing: Vec<Effect> = named
                .effects
                .iter()
                .copied()
                .filter(|e| held(&[*e], effect))
                .collect();
            (
                effect,
                if sharing.is_empty() {
                    named.effects.clone()
                } else {
                    sharing
                },
            )
        })
        .collect()
}

/// An effect is named only if its main parameter is at least this many standard errors from
/// zero: a spring without stiffness is a constant force, not a spring.
pub const SIGNIFICANCE: f64 = 3.0;

impl Fit {
    /// `effect`'s main parameter (a spring's stiffness, a tilt's angle, the delay, the one
    /// parameter of the others) and its standard error.
    pub fn main_parameter(&self, effect: Effect, up: &Vector3<f64>) -> Option<(f64, f64)> {
        match effect {
            Effect::None => None,
            Effect::TimeDelay => Some((self.delay, self.delay_sd)),
            Effect::GravityTilt => {
                let (rotation, sd) = self.tilt(up);
                Some((rotation.norm(), sd))
            }
            _ => {
                let i = self.effects.iter().position(|e| *e == effect)?;
                Some((self.theta[i][0], self.theta_sd[i][0]))
            }
        }
    }
}

/// Of `trials` (each `current` with one effect more), the one to add, if any.
fn choose<'a>(current: &Fit, trials: &'a [Fit], up: &Vector3<f64>) -> Option<&'a Fit> {
    let added = |f: &Fit| *f.effects.last().expect("a trial adds an effect");
    let significant = |f: &Fit| {
        f.main_parameter(added(f), up)
            .is_some_and(|(value, sd)| value.abs() >= SIGNIFICANCE * sd)
    };
    let mut qualified: Vec<&Fit> = trials
        .iter()
        .filter(|c| c.heldout_error <= STEP_SHRINK * current.heldout_error && significant(c))
        .collect();
    qualified.sort_by(|a, b| {
        added(a)
            .parameters()
            .cmp(&added(b).parameters())
            .then(a.heldout_error.total_cmp(&b.heldout_error))
    });
    let mut chosen: Option<&Fit> = None;
    for c in qualified {
        match chosen {
            None => chosen = Some(c),
            Some(best) if c.heldout_error <= COMPLEXITY_MARGIN * best.heldout_error => {
                chosen = Some(c)
            }
            _ => {}
        }
    }
    chosen
}

/// The smallest moving mass simulated, kg (a fit that finds less is not a plant to integrate).
const MIN_SIMULATED_MASS: f64 = 0.01;

/// The closed-loop position the model predicts: the excitation's PD law tracking the logged
/// reference on the model's plant, from the log's first state, at the log's rate. None without a
/// reference or the gains.
pub fn simulate(
    log: &Log,
    signals: &Signals,
    fit: &Fit,
    grid: &GravityModel,
    excitation: &Excitation,
) -> Option<Vec<Vector3<f64>>> {
    let reference = log.reference.as_ref()?;
    let period = signals.period;
    let substeps = 20;
    let dt = period / f64::from(substeps);
    let delay_ticks = (fit.delay / period).round() as usize;
    let mut pending = std::collections::VecDeque::with_capacity(delay_ticks + 1);
    let (mut x, mut v) = (log.position[0], Vector3::zeros());
    let mut positions = Vec::with_capacity(log.len());
    let payload = fit.payload();
    let inertia = fit.moving_mass.map(|m| m.max(MIN_SIMULATED_MASS)) + Vector3::repeat(payload);
    for k in 0..log.len() {
        positions.push(x);
        let r = reference[k];
        let r_dot = if k + 1 < log.len() {
            (reference[k + 1] - r) / period
        } else {
            Vector3::zeros()
        };
        let command =
            grid.force(&x) + (r - x) * excitation.stiffness + (r_dot - v) * excitation.damping;
        pending.push_back(command);
        let applied = if pending.len() > delay_ticks {
            pending.pop_front().unwrap_or(command)
        } else {
            Vector3::zeros()
        };
        for _ in 0..substeps {
            let s = Sample {
                position: x,
                velocity: v,
                acceleration: Vector3::zeros(),
                gravity: grid.force(&x),
                up: grid.grid.gravity_direction,
                g: grid.grid.g,
            };
            let needed = fit.model_force(&s);
            let a = (applied - needed).component_div(&inertia);
            v += a * dt;
            x += v * dt;
        }
    }
    Some(positions)
}
