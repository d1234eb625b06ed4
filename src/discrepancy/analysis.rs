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
/// An effect is named only if it cuts the held-out error to at most this share of the nominal
/// model's.
pub const NAMING_SHRINK: f64 = 0.5;
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
struct Weights {
    value: Vec<f64>,
    slope: Vec<f64>,
    curvature: Vec<f64>,
}

impl Weights {
    fn new(m: usize) -> Self {
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

/// One model fitted: the nominal one (`Effect::None`) or the nominal one with an effect.
#[derive(Clone, Debug, PartialEq)]
pub struct Fit {
    pub effect: Effect,
    /// Moving mass along x, y, z, kg (fitted with the effect).
    pub moving_mass: Vector3<f64>,
    /// The effect's linear parameters θ (see [`Effect`]).
    pub theta: Vec<f64>,
    /// The time delay beyond the sampling's half period, s (0 unless `effect` is
    /// [`Effect::TimeDelay`]).
    pub delay: f64,
    /// The rotation of gravity, rad (zero unless `effect` is [`Effect::GravityTilt`]; then
    /// θ is the last Gauss–Newton increment on it).
    pub rotation: Vector3<f64>,
    /// RMS of |residual| on the samples fitted on, and on those held out, N.
    pub train_error: f64,
    pub heldout_error: f64,
}

impl Fit {
    /// `s` with gravity turned by the fit's rotation.
    fn turned(&self, s: &Sample) -> Sample {
        if self.rotation == Vector3::zeros() {
            return *s;
        }
        Sample {
            gravity: Rotation3::new(self.rotation) * s.gravity,
            ..*s
        }
    }

    /// The force the model says the device needs for the motion at sample `s`, N.
    pub fn model_force(&self, s: &Sample) -> Vector3<f64> {
        let s = self.turned(s);
        let mut columns = [Vector3::zeros(); 4];
        let n = self.effect.columns(&s, &mut columns);
        let mut f = s.gravity + s.acceleration.component_mul(&self.moving_mass);
        for (c, t) in columns[..n].iter().zip(&self.theta) {
            f += c * *t;
        }
        f
    }

    /// Command `f` minus what the model needs at `s`, N. A handle stuck in Coulomb friction
    /// (slower than [`STICK_SPEED`]) takes any force up to f_c: only the excess is residual.
    pub fn residual(&self, s: &Sample, f: &Vector3<f64>) -> Vector3<f64> {
        if self.effect == Effect::CoulombFriction && s.velocity.norm() < STICK_SPEED {
            let t = self.turned(s);
            let r = f - t.gravity - t.acceleration.component_mul(&self.moving_mass);
            let excess = r.norm() - self.theta[0].max(0.0);
            return if excess > 0.0 {
                r * (excess / r.norm())
            } else {
                Vector3::zeros()
            };
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

    /// The rotation of gravity this fit found, rad (zero but for [`Effect::GravityTilt`]).
    pub fn tilt(&self, up: &Vector3<f64>) -> Vector3<f64> {
        if self.effect != Effect::GravityTilt {
            return Vector3::zeros();
        }
        let (e1, e2) = across(up);
        self.rotation + e1 * self.theta[0] + e2 * self.theta[1]
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

/// Least squares for the moving mass and `effect`'s θ on the training samples, with `force` as
/// the command and gravity turned by `rotation`. Coulomb friction is fitted on the samples in
/// motion. None when the regressors are degenerate.
fn fit_linear(
    effect: Effect,
    signals: &Signals,
    force: &[Vector3<f64>],
    delay: f64,
    rotation: Vector3<f64>,
) -> Option<Fit> {
    let p = 3 + effect.linear_parameters();
    let mut fit = Fit {
        effect,
        moving_mass: Vector3::zeros(),
        theta: vec![0.0; p - 3],
        delay,
        rotation,
        train_error: 0.0,
        heldout_error: 0.0,
    };
    let (train, heldout) = signals.split();
    let mut normal = DMatrix::<f64>::zeros(p, p);
    let mut rhs = DVector::<f64>::zeros(p);
    let mut columns = [Vector3::zeros(); 4];
    let mut phi = vec![Vector3::zeros(); p];
    for k in train.clone() {
        let s = &fit.turned(&signals.samples[k]);
        if effect == Effect::CoulombFriction && s.velocity.norm() < STICK_SPEED {
            continue;
        }
        let y = force[k] - s.gravity;
        phi[0] = Vector3::new(s.acceleration.x, 0.0, 0.0);
        phi[1] = Vector3::new(0.0, s.acceleration.y, 0.0);
        phi[2] = Vector3::new(0.0, 0.0, s.acceleration.z);
        let n = effect.columns(s, &mut columns);
        phi[3..3 + n].copy_from_slice(&columns[..n]);
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
    let theta = normal.cholesky()?.solve(&rhs);
    fit.moving_mass = Vector3::new(theta[0], theta[1], theta[2]);
    fit.theta = theta.iter().skip(3).copied().collect();
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
    fit_linear(Effect::None, signals, &signals.force, 0.0, Vector3::zeros())
}

/// Gauss–Newton steps for the gravity tilt.
const TILT_STEPS: usize = 4;

/// `effect` fitted on the training samples and scored on the held-out ones.
pub fn fit(effect: Effect, signals: &Signals) -> Option<Fit> {
    let zero = Vector3::zeros();
    match effect {
        Effect::TimeDelay => {
            // The delay that best explains the training samples, by search.
            let steps = (MAX_DELAY / DELAY_STEP).round() as usize;
            (1..=steps)
                .filter_map(|k| {
                    let delay = k as f64 * DELAY_STEP;
                    let force = signals.delayed_force(delay);
                    fit_linear(effect, signals, &force, delay, zero)
                })
                .min_by(|a, b| a.train_error.total_cmp(&b.train_error))
        }
        Effect::GravityTilt => {
            let up = signals.samples.first()?.up;
            let mut fit = fit_linear(effect, signals, &signals.force, 0.0, zero)?;
            for _ in 0..TILT_STEPS {
                let rotation = fit.tilt(&up);
                fit = fit_linear(effect, signals, &signals.force, 0.0, rotation)?;
            }
            Some(fit)
        }
        _ => fit_linear(effect, signals, &signals.force, 0.0, zero),
    }
}

/// The decision: of the candidates that cut the held-out error to [`NAMING_SHRINK`] of the
/// nominal model's or less, the simplest, unless one with more parameters does better again by
/// [`COMPLEXITY_MARGIN`]; [`Effect::None`] if none qualifies.
pub fn name_effect(nominal: &Fit, candidates: &[Fit]) -> Effect {
    let mut qualified: Vec<&Fit> = candidates
        .iter()
        .filter(|c| c.heldout_error <= NAMING_SHRINK * nominal.heldout_error)
        .collect();
    qualified.sort_by(|a, b| {
        a.effect
            .parameters()
            .cmp(&b.effect.parameters())
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
    chosen.map_or(Effect::None, |c| c.effect)
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
    let payload = if fit.effect == Effect::Payload {
        fit.theta[0]
    } else {
        0.0
    };
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
