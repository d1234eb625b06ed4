//! The analysis: derivatives of the measured position, the nominal model's force residual, each
//! candidate effect fitted on the first part of the log and scored on the rest, and the decision
//! (docs/discrepancy.md §2).

use std::borrow::Cow;

use nalgebra::{DMatrix, DVector, Matrix3, Rotation3, Vector3};

use super::effects::{
    across, arm_columns, symmetric, ArmInertia, Effect, JointSample, Sample, ARM_COLUMNS,
    ARM_FIRST_ORDER, ARM_FRICTION, ARM_HANDLE_MASS, STICK_RATE, STICK_SPEED,
};
use super::log::{Excitation, Log};
use crate::arm::Arm;
use crate::control::compensation::GravityModel;

/// Share of the log the models are fitted on; the rest is held out to score them.
pub const TRAIN_SHARE: f64 = 0.6;
/// A point mass's nominal model: a moving mass per axis.
const POINT_MASS_COLUMNS: usize = 3;
/// Standard deviation of the Gaussian smoothing kernel, s: 7.5 ms passes the excitation (its
/// fastest line, 6 Hz, keeps 95 %) and averages the encoder's steps out of the second
/// derivative.
pub const SMOOTHING_SIGMA: f64 = 0.0075;
/// Effects are named only if together they cut the held-out error's part above the noise
/// floor ([`above_floor`]) to at most this share of the nominal model's.
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
    /// Samples over which the smoothing correlates white noise (√(4π) σ).
    pub window: usize,
    /// The nominal model is the arm's (its samples carry their joints), not a point mass's.
    pub arm: bool,
    /// For an arm: how its nominal model's inertia varies with the pose (the first
    /// [`ArmInertia::columns`] of the design are fitted): first order until [`nominal`]
    /// chooses, which every analysis does before any other fit.
    arm_inertia: ArmInertia,
    /// For an arm: its nominal model's columns ([`arm_columns`]) at every sample,
    /// [`ARM_COLUMNS`] per sample, worked out once (the same in every fit: they neither turn
    /// nor move with a delay).
    arm_design: Vec<Vector3<f64>>,
    /// For an arm: ΦᵀΦ of all those columns over the training samples in motion.
    arm_gram: Option<DMatrix<f64>>,
}

/// Weights over k = −m..m for the smoothed value, first and second derivative (per sample and
/// per sample²): a Savitzky–Golay quadratic ([`Weights::new`]) or a Gaussian
/// ([`Weights::gaussian`]).
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

    /// A Gaussian of standard deviation `sigma` samples, to ±4σ, with its first and second
    /// derivatives: one kernel convolved three ways, so a linear relation between the command
    /// and the motion (F = m Ẍ) holds between the smoothed signals at every frequency.
    /// Normalised so a constant, a ramp and a parabola come through exactly.
    pub fn gaussian(sigma: f64) -> Self {
        let m = (4.0 * sigma).ceil() as i64;
        let ks: Vec<f64> = (-m..=m).map(|k| k as f64).collect();
        let g: Vec<f64> = ks
            .iter()
            .map(|k| (-0.5 * (k / sigma).powi(2)).exp())
            .collect();
        let total: f64 = g.iter().sum();
        let value: Vec<f64> = g.iter().map(|v| v / total).collect();
        let slope: Vec<f64> = ks.iter().zip(&value).map(|(k, v)| k * v).collect();
        let ramp: f64 = slope.iter().zip(&ks).map(|(w, k)| w * k).sum();
        let slope = slope.iter().map(|w| w / ramp).collect();
        let mut curvature: Vec<f64> = ks
            .iter()
            .zip(&value)
            .map(|(k, v)| ((k / sigma).powi(2) - 1.0) * v)
            .collect();
        let offset: f64 = curvature.iter().sum();
        for (c, v) in curvature.iter_mut().zip(&value) {
            *c -= offset * v;
        }
        let parabola: f64 = curvature.iter().zip(&ks).map(|(c, k)| c * k * k).sum();
        let curvature = curvature.iter().map(|c| 2.0 * c / parabola).collect();
        Self {
            value,
            slope,
            curvature,
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
    /// Smooth and differentiate `log`; the gravity force from `model`; with `arm`, the joints
    /// too (each position's joint angles, smoothed and differentiated alike).
    pub fn new(log: &Log, model: &GravityModel, arm: Option<&Arm>) -> Self {
        let period = log.period();
        let w = Weights::gaussian(Signals::sigma(period));
        let m = w.value.len() / 2;
        let up = model.up;
        let g = model.grid.g;
        let range = m..log.len().saturating_sub(m);
        let mut signals = Signals {
            time: Vec::with_capacity(range.len()),
            samples: Vec::with_capacity(range.len()),
            force: Vec::with_capacity(range.len()),
            period,
            first: m,
            // Smoothed white noise stays correlated over √(4π) σ samples.
            window: ((4.0 * std::f64::consts::PI).sqrt() * Signals::sigma(period)).ceil() as usize,
            arm: false,
            arm_design: Vec::new(),
            arm_inertia: ArmInertia::FirstOrder,
            arm_gram: None,
        };
        // The joints of every logged position (a reading out of reach keeps the last ones).
        let joints: Option<Vec<Vector3<f64>>> = arm.map(|arm| {
            let mut last = arm.joints_at(&Vector3::zeros()).unwrap_or_default();
            log.position
                .iter()
                .map(|x| {
                    last = arm.joints_at(x).unwrap_or(last);
                    last
                })
                .collect()
        });
        for k in range {
            let position = Weights::apply(&w.value, &log.position, k);
            signals.time.push(log.time[k]);
            signals.samples.push(Sample {
                position,
                velocity: Weights::apply(&w.slope, &log.position, k) / period,
                acceleration: Weights::apply(&w.curvature, &log.position, k) / (period * period),
                sliding: Vector3::zeros(),
                gravity: model.force(&position),
                up,
                g,
                tilt: model.arm().and_then(|gravity| {
                    // F_G is linear in the gravity vector: its change as v_G turns by δ e is
                    // the arm's force for the gravity vector e × v_G.
                    let theta = nalgebra::SMatrix::<f64, { crate::arm::MAX_PARAMETERS }, 1>::from(
                        gravity.parameters,
                    );
                    let (e1, e2) = across(&gravity.up);
                    let column = |e: Vector3<f64>| {
                        gravity
                            .arm
                            .force_regressor(&position, &e.cross(&gravity.up), gravity.g)
                            .map(|r| r * theta)
                    };
                    Some([column(e1)?, column(e2)?])
                }),
                joint: match (arm, &joints) {
                    (Some(arm), Some(q)) => arm.to_handle(&position).map(|to_handle| JointSample {
                        offset: Weights::apply(&w.value, q, k),
                        rate: Weights::apply(&w.slope, q, k) / period,
                        acceleration: Weights::apply(&w.curvature, q, k) / (period * period),
                        to_handle,
                        sliding: Vector3::zeros(),
                    }),
                    _ => None,
                },
            });
            signals.force.push(Weights::apply(&w.value, &log.force, k));
        }
        signals.smooth_sliding(&w.value);
        // The arm's model serves when every sample has its joints.
        signals.arm = arm.is_some() && signals.samples.iter().all(|s| s.joint.is_some());
        if signals.arm {
            let n = signals.samples.len().max(1) as f64;
            let mean: Vector3<f64> = signals
                .samples
                .iter()
                .filter_map(|s| s.joint.map(|j| j.offset))
                .sum::<Vector3<f64>>()
                / n;
            for s in &mut signals.samples {
                if let Some(j) = &mut s.joint {
                    j.offset -= mean;
                }
            }
            let mut design = vec![Vector3::zeros(); signals.len() * ARM_COLUMNS];
            for (s, row) in signals
                .samples
                .iter()
                .zip(design.chunks_exact_mut(ARM_COLUMNS))
            {
                if let Some(j) = &s.joint {
                    arm_columns(j, &s.acceleration, row);
                }
            }
            signals.arm_design = design;
            let mut gram = DMatrix::<f64>::zeros(ARM_COLUMNS, ARM_COLUMNS);
            for (k, row) in signals
                .arm_design
                .chunks_exact(ARM_COLUMNS)
                .enumerate()
                .take(signals.split().0.end)
            {
                if signals.samples[k].velocity.norm() >= STICK_SPEED {
                    accumulate(&mut gram, &[], row, 0);
                }
            }
            signals.arm_gram = Some(gram);
        } else {
            for s in &mut signals.samples {
                s.joint = None;
            }
        }
        // Each command holds over the period after its tick: on average it acts half a period
        // after the position it answers was sampled.
        signals.force = signals.delayed_force(period / 2.0);
        signals
    }

    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// How an arm's nominal model lets its inertia vary with the pose ([`nominal`] chooses).
    pub fn arm_inertia(&self) -> ArmInertia {
        self.arm_inertia
    }

    /// The arm's nominal columns fitted at sample `k` ([`arm_columns`], the first
    /// [`ArmInertia::columns`]); None for a point mass.
    pub(super) fn arm_row(&self, k: usize) -> Option<&[Vector3<f64>]> {
        let from = k * ARM_COLUMNS;
        self.arm_design.get(from..from + self.arm_inertia.columns())
    }

    /// Each sample's direction of sliding (and each joint's), smoothed by `kernel` (the ends
    /// repeat the first and last samples').
    fn smooth_sliding(&mut self, kernel: &[f64]) {
        let direction = |v: Vector3<f64>, stick: f64| v / (v.norm_squared() + stick * stick).sqrt();
        let handle: Vec<Vector3<f64>> = self
            .samples
            .iter()
            .map(|s| direction(s.velocity, STICK_SPEED))
            .collect();
        let joints: Vec<Vector3<f64>> = self
            .samples
            .iter()
            .map(|s| {
                s.joint.map_or(Vector3::zeros(), |j| {
                    j.rate.map(|r| r / (r * r + STICK_RATE * STICK_RATE).sqrt())
                })
            })
            .collect();
        let m = kernel.len() / 2;
        let n = self.samples.len();
        let smooth = |x: &[Vector3<f64>], k: usize| -> Vector3<f64> {
            kernel
                .iter()
                .enumerate()
                .map(|(i, w)| x[(k + i).saturating_sub(m).min(n - 1)] * *w)
                .sum()
        };
        for k in 0..n {
            self.samples[k].sliding = smooth(&handle, k);
            let joint = smooth(&joints, k);
            if let Some(j) = &mut self.samples[k].joint {
                j.sliding = joint;
            }
        }
    }

    /// The smoothing kernel's standard deviation in samples of `period` s.
    pub fn sigma(period: f64) -> f64 {
        (SMOOTHING_SIGMA / period).max(1.0)
    }

    /// The smoothing kernel (value, first and second derivative).
    pub(super) fn kernel(&self) -> Weights {
        Weights::gaussian(Signals::sigma(self.period))
    }

    /// How many parameters the nominal model has: a moving mass per axis, or the arm's inertia,
    /// joint friction and handle mass.
    pub fn base_count(&self) -> usize {
        if self.arm {
            self.arm_inertia.columns()
        } else {
            POINT_MASS_COLUMNS
        }
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
        (0..self.len()).map(|k| self.delayed_at(k, delay)).collect()
    }

    /// [`Signals::delayed_force`] at sample `k`.
    fn delayed_at(&self, k: usize, delay: f64) -> Vector3<f64> {
        let at = (k as f64 - delay / self.period).max(0.0);
        let i = at.floor() as usize;
        let u = at - i as f64;
        let next = (i + 1).min(self.len() - 1);
        self.force[i] * (1.0 - u) + self.force[next] * u
    }
}

/// One model fitted: the nominal one (no effect) or the nominal one with a set of effects, all
/// their parameters fitted jointly.
#[derive(Clone, Debug, PartialEq)]
pub struct Fit {
    /// The effects, in the order they were found.
    pub effects: Vec<Effect>,
    /// Moving mass along x, y, z, kg (fitted with the effects), and its standard error (zero
    /// for an arm's nominal model).
    pub moving_mass: Vector3<f64>,
    pub moving_mass_sd: Vector3<f64>,
    /// The nominal model's parameters and their standard errors: the moving mass, or the
    /// arm's inertia, joint friction and handle mass ([`arm_columns`]).
    pub base: Vec<f64>,
    pub base_sd: Vec<f64>,
    /// Each effect's linear parameters θ (see [`Effect`]) and their standard errors, in
    /// `effects` order.
    pub theta: Vec<Vec<f64>>,
    pub theta_sd: Vec<Vec<f64>>,
    /// The time delay beyond the sampling's half period, s, and its standard error (zero
    /// unless [`Effect::TimeDelay`] is in the set).
    pub delay: f64,
    pub delay_sd: f64,
    /// The rotation of gravity, rad (zero unless [`Effect::GravityTilt`] is in the set; see
    /// `linear_tilt` and `Fit::turned`).
    pub rotation: Vector3<f64>,
    /// RMS of |residual| on the samples fitted on, and on those held out, N.
    pub train_error: f64,
    pub heldout_error: f64,
    /// The least-squares objective: the sum of squared residuals over the `fitted` training
    /// samples, N² (what the fit minimised, before any scoring rule).
    pub train_sse: f64,
    pub fitted: usize,
    /// The tilt is a linear term of its own (an arm's, [`Sample::tilt`]): θ is the whole
    /// rotation, and `rotation` the last step's, which sets the scales of `Fit::turned`;
    /// otherwise the field turns whole by `rotation` and θ is the last increment.
    pub linear_tilt: bool,
    /// With a linear tilt: the payload (kg) whose weight turns with it, from the previous
    /// Gauss–Newton step (the term m_p g (δ × v_G) is linearised about it).
    pub payload_hint: f64,
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

    /// `s` with gravity and v_G turned by the fit's rotation. An arm's tilt is a linear term
    /// of its own (`linear_tilt`), and the rotation is then the last Gauss–Newton step's δ: the
    /// arm's gravity force is linear in the gravity vector γ, so turned by δ = Σ θ_i e_i across
    /// v_G it is cos|δ| F_G + (sin|δ|/|δ|) Σ θ_i T_i (T_i its tilt columns, [`Sample::tilt`]),
    /// and a payload's weight turns alike ([`Fit::effect_columns`]): F_G and g scaled by
    /// cos|δ|, the tilt's columns by sin|δ|/|δ|, linear in θ about the last step's |δ|. (First
    /// order alone leaves −(δ²/2) F_G, which a payload under a gram took up beside a 5° tilt
    /// on the simulated delta.)
    fn turned<'a>(&self, s: &'a Sample) -> Cow<'a, Sample> {
        if self.rotation == Vector3::zeros() {
            return Cow::Borrowed(s);
        }
        if self.linear_tilt {
            let (cos, sinc) = self.tilt_scales();
            return Cow::Owned(Sample {
                gravity: s.gravity * cos,
                g: s.g * cos,
                tilt: s.tilt.map(|columns| columns.map(|c| c * sinc)),
                ..*s
            });
        }
        let r = Rotation3::new(self.rotation);
        Cow::Owned(Sample {
            gravity: r * s.gravity,
            up: r * s.up,
            ..*s
        })
    }

    /// For an arm's linear tilt: cos|δ| and sin|δ|/|δ| of the last step's rotation δ.
    fn tilt_scales(&self) -> (f64, f64) {
        let angle = self.rotation.norm();
        if angle == 0.0 {
            (1.0, 1.0)
        } else {
            (angle.cos(), angle.sin() / angle)
        }
    }

    /// `effect`'s columns at `s` in this fit ([`Effect::columns`]; a linear tilt's with the
    /// turning of the hinted payload's weight); how many.
    fn effect_columns(&self, effect: Effect, s: &Sample, out: &mut [Vector3<f64>; 4]) -> usize {
        let n = effect.columns(s, out);
        if effect == Effect::GravityTilt && self.linear_tilt && self.payload_hint != 0.0 {
            let (e1, e2) = across(&s.up);
            // s.g is g cos|δ| ([`Fit::turned`]); the weight turns by g sin|δ|/|δ| per θ.
            let (cos, sinc) = self.tilt_scales();
            let weight = s.up * (self.payload_hint * s.g * sinc / cos);
            out[0] += e1.cross(&weight);
            out[1] += e2.cross(&weight);
        }
        n
    }

    /// The force the model needs for the motion at sample `s` (already turned; `arm` its
    /// arm's columns, [`Signals::arm_row`]), without the Coulomb term, N.
    fn smooth_force(&self, s: &Sample, arm: Option<&[Vector3<f64>]>) -> Vector3<f64> {
        let mut columns = [Vector3::zeros(); 4];
        let mut f = s.gravity;
        match arm {
            Some(base) if self.is_arm() => {
                for (c, t) in base.iter().zip(&self.base) {
                    f += c * *t;
                }
            }
            _ => f += s.acceleration.component_mul(&self.moving_mass),
        }
        for (effect, theta) in self.effects.iter().zip(&self.theta) {
            if *effect == Effect::CoulombFriction {
                continue;
            }
            let n = self.effect_columns(*effect, s, &mut columns);
            for (c, t) in columns[..n].iter().zip(theta) {
                f += c * *t;
            }
        }
        f
    }

    /// The force the model says the device needs for the motion at sample `s` (`arm` its
    /// arm's columns, [`Signals::arm_row`]), N.
    fn model_force(&self, s: &Sample, arm: Option<&[Vector3<f64>]>) -> Vector3<f64> {
        let s = self.turned(s);
        let mut f = self.smooth_force(&s, arm);
        if let [f_c] = self.theta_of(Effect::CoulombFriction) {
            let mut columns = [Vector3::zeros(); 4];
            Effect::CoulombFriction.columns(&s, &mut columns);
            f += columns[0] * *f_c;
        }
        f
    }

    /// Command `f` minus what the model needs at `s`, N. A handle stuck in Coulomb friction
    /// (slower than [`STICK_SPEED`]) takes any force up to f_c: only the excess is residual. An
    /// arm's joint that sticks, for the whole kernel or part of it, holds any torque up to its
    /// friction, which no smooth friction column follows: only what lies beyond is residual
    /// ([`beyond_joint_friction`]), and nothing while the handle rests.
    fn residual(&self, s: &Sample, arm: Option<&[Vector3<f64>]>, f: &Vector3<f64>) -> Vector3<f64> {
        if self.is_arm() {
            if s.velocity.norm() < STICK_SPEED {
                return Vector3::zeros();
            }
            if let Some(joint) = &s.joint {
                let friction = [0, 1, 2].map(|j| self.base[ARM_FRICTION + 2 * j]);
                return beyond_joint_friction(joint, &friction, f - self.model_force(s, arm));
            }
        }
        if let [f_c] = self.theta_of(Effect::CoulombFriction) {
            if s.velocity.norm() < STICK_SPEED {
                let r = f - self.smooth_force(&self.turned(s), arm);
                let excess = r.norm() - f_c.max(0.0);
                return if excess > 0.0 {
                    r * (excess / r.norm())
                } else {
                    Vector3::zeros()
                };
            }
        }
        f - self.model_force(s, arm)
    }

    /// The residual at every sample, N.
    pub fn residuals(&self, signals: &Signals) -> Vec<Vector3<f64>> {
        if self.delay > 0.0 {
            self.residuals_to(signals, &signals.delayed_force(self.delay))
        } else {
            self.residuals_to(signals, &signals.force)
        }
    }

    /// The residual at every sample of the command `force`, N.
    fn residuals_to(&self, signals: &Signals, force: &[Vector3<f64>]) -> Vec<Vector3<f64>> {
        signals
            .samples
            .iter()
            .zip(force)
            .enumerate()
            .map(|(k, (s, f))| self.residual(s, signals.arm_row(k), f))
            .collect()
    }

    /// The force this model asks per unit of the handle's acceleration at `s`, kg: its
    /// Cartesian inertia, diag(m) for a point mass, J⁻ᵀ M(q) J⁻¹ + m_h I for an arm (its
    /// velocity-product terms left out).
    pub fn handle_inertia(&self, s: &Sample) -> Matrix3<f64> {
        let joint = match (&s.joint, self.is_arm()) {
            (Some(joint), true) => joint,
            _ => return Matrix3::from_diagonal(&self.moving_mass),
        };
        let b = &self.base;
        let mut inertia = symmetric(&b[..6]);
        if self.arm_inertia() == Some(ArmInertia::FirstOrder) {
            for k in 0..3 {
                let at = ARM_FIRST_ORDER + 6 * k;
                inertia += symmetric(&b[at..at + 6]) * joint.offset[k];
            }
        }
        joint.to_handle * inertia * joint.to_handle.transpose()
            + Matrix3::from_diagonal_element(b[ARM_HANDLE_MASS])
    }

    /// Whether this is an arm's model (its nominal part the arm's columns).
    pub fn is_arm(&self) -> bool {
        self.base.len() != POINT_MASS_COLUMNS
    }

    /// How an arm's model lets its inertia vary with the pose (None for a point mass).
    pub fn arm_inertia(&self) -> Option<ArmInertia> {
        match self.base.len() {
            POINT_MASS_COLUMNS => None,
            n if n > ARM_FIRST_ORDER => Some(ArmInertia::FirstOrder),
            _ => Some(ArmInertia::Constant),
        }
    }

    /// The rotation of gravity this fit found, rad (zero without [`Effect::GravityTilt`]),
    /// and the standard error of its angle.
    pub fn tilt(&self, up: &Vector3<f64>) -> (Vector3<f64>, f64) {
        let (theta, sd) = match self.effects.iter().position(|e| *e == Effect::GravityTilt) {
            Some(i) => (&self.theta[i], &self.theta_sd[i]),
            None => return (Vector3::zeros(), 0.0),
        };
        let (e1, e2) = across(up);
        let increment = e1 * theta[0] + e2 * theta[1];
        let rotation = if self.linear_tilt {
            increment
        } else {
            self.rotation + increment
        };
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

/// What of an arm's handle-force residual `r` its joints' friction cannot hold (`friction`,
/// each joint's fitted Coulomb level f_c,j, N m). A joint at rest (slower than [`STICK_RATE`])
/// holds any torque within ±f_c,j: of the torque it holds there (the residual's, Jᵀ r, plus the
/// model's own friction term f_c,j s_j, which `r` took out) only what lies beyond is residual.
/// A joint that stuck or turned within the kernel's span, its smoothed direction of sliding
/// |s_j| < 1, slid for at most |s_j| of it one way: the rest of the span (a share of at most
/// 1 − |s_j|) it held any torque within ±f_c,j, so the smoothed friction lies within
/// f_c,j (1 − |s_j|) of the model's f_c,j s_j, and only the residual's torque beyond that band
/// counts. A joint sliding throughout (|s_j| = 1) counts whole.
fn beyond_joint_friction(
    joint: &JointSample,
    friction: &[f64; 3],
    r: Vector3<f64>,
) -> Vector3<f64> {
    let Some(to_joints) = joint.to_handle.try_inverse() else {
        return Vector3::zeros();
    };
    let mut torque = to_joints * r;
    for (j, t) in torque.iter_mut().enumerate() {
        let f_c = friction[j].max(0.0);
        if joint.rate[j].abs() < STICK_RATE {
            let held = *t + friction[j] * joint.sliding[j];
            *t = held.signum() * (held.abs() - f_c).max(0.0);
        } else {
            let band = f_c * (1.0 - joint.sliding[j].abs()).max(0.0);
            *t = t.signum() * (t.abs() - band).max(0.0);
        }
    }
    joint.to_handle * torque
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
    turn: Turn,
) -> Option<Fit> {
    fit_on(signals.arm, effects, signals, force, delay, turn)
}

/// How gravity is turned for a fit: the rotation, and for a linear tilt the payload whose
/// weight turns with it ([`Fit::payload_hint`]).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Turn {
    pub rotation: Vector3<f64>,
    pub payload: f64,
}

impl Fit {
    /// The turn this fit was made in.
    fn turn(&self) -> Turn {
        Turn {
            rotation: self.rotation,
            payload: self.payload_hint,
        }
    }
}

/// Column `i` of one sample's design ([`design_row`]): the arm's cached columns `arm` first,
/// then `phi`'s.
fn column<'a>(arm: &'a [Vector3<f64>], phi: &'a [Vector3<f64>], i: usize) -> &'a Vector3<f64> {
    arm.get(i).unwrap_or_else(|| &phi[i])
}

/// Adds the upper triangle of φᵀφ for one sample's columns (`arm`'s, then `phi`'s; as many as
/// `phi` has) to `normal`, leaving out the block of the first `known` columns with each other.
fn accumulate(normal: &mut DMatrix<f64>, arm: &[Vector3<f64>], phi: &[Vector3<f64>], known: usize) {
    for j in known..phi.len() {
        let b = column(arm, phi, j);
        let upper = &mut normal.column_mut(j);
        let (from_arm, own) = upper.as_mut_slice()[..=j].split_at_mut(arm.len().min(j + 1));
        for (n, a) in from_arm.iter_mut().zip(arm) {
            *n += a.dot(b);
        }
        for (n, a) in own.iter_mut().zip(&phi[arm.len().min(j + 1)..]) {
            *n += a.dot(b);
        }
    }
}

/// The normal matrix ΦᵀΦ of a fit of `frame`'s effects (`p` columns, the arm's nominal model's
/// first where `arm`) over the training samples, the arm's cached block filled in. A handle at
/// rest is left out where friction or an arm is fitted (its friction is no column's). `each` is
/// handed every sample taken, turned by `frame`, with its design row (the arm's columns, then
/// `phi`'s: [`column()`] reads them), for the right-hand sides.
fn normal_matrix(
    signals: &Signals,
    arm: bool,
    frame: &Fit,
    p: usize,
    mut each: impl FnMut(usize, &Sample, &[Vector3<f64>], &[Vector3<f64>]),
) -> DMatrix<f64> {
    let moving_only = frame.effects.contains(&Effect::CoulombFriction) || arm;
    let mut normal = DMatrix::<f64>::zeros(p, p);
    let mut phi = vec![Vector3::zeros(); p];
    let known = cached(signals, arm);
    for k in signals.split().0 {
        let s = frame.turned(&signals.samples[k]);
        if moving_only && s.velocity.norm() < STICK_SPEED {
            continue;
        }
        let arm_row = design_row(
            arm.then(|| signals.arm_row(k)).flatten(),
            frame,
            &s,
            &mut phi,
        );
        accumulate(&mut normal, arm_row, &phi, known);
        each(k, &s, arm_row, &phi);
    }
    complete(signals, arm, &mut normal);
    normal
}

/// `normal` with the arm's cached block (upper triangle, when `arm`) and mirrored.
fn complete(signals: &Signals, arm: bool, normal: &mut DMatrix<f64>) {
    if let (Some(gram), true) = (&signals.arm_gram, arm) {
        let b = signals.arm_inertia.columns();
        normal
            .view_mut((0, 0), (b, b))
            .copy_from(&gram.view((0, 0), (b, b)));
    }
    let p = normal.nrows();
    for i in 0..p {
        for j in 0..i {
            normal[(i, j)] = normal[(j, i)];
        }
    }
}

/// How many leading columns of a fit's design the cached arm block covers.
fn cached(signals: &Signals, arm: bool) -> usize {
    match (&signals.arm_gram, arm) {
        (Some(_), true) => signals.arm_inertia.columns(),
        _ => 0,
    }
}

/// The columns of the model at sample `s` (already turned): the nominal model's (the arm's
/// columns `arm`, returned and not copied, or a moving mass per axis into `phi`), then each
/// effect's into `phi` after them. [`column()`] reads them.
fn design_row<'a>(
    arm: Option<&'a [Vector3<f64>]>,
    frame: &Fit,
    s: &Sample,
    phi: &mut [Vector3<f64>],
) -> &'a [Vector3<f64>] {
    let effects = &frame.effects;
    let (arm, b) = match arm {
        Some(columns) => (columns, columns.len()),
        None => {
            phi[0] = Vector3::new(s.acceleration.x, 0.0, 0.0);
            phi[1] = Vector3::new(0.0, s.acceleration.y, 0.0);
            phi[2] = Vector3::new(0.0, 0.0, s.acceleration.z);
            (&[][..], 3)
        }
    };
    let mut columns = [Vector3::zeros(); 4];
    let mut at = b;
    for effect in effects {
        let n = frame.effect_columns(*effect, s, &mut columns);
        phi[at..at + n].copy_from_slice(&columns[..n]);
        at += n;
    }
    arm
}

/// [`fit_linear`] with the arm's nominal model (`arm`) or a point mass's.
fn fit_on(
    arm: bool,
    effects: &[Effect],
    signals: &Signals,
    force: &[Vector3<f64>],
    delay: f64,
    turn: Turn,
) -> Option<Fit> {
    let b = if arm {
        signals.arm_inertia.columns()
    } else {
        POINT_MASS_COLUMNS
    };
    let p = b + effects.iter().map(|e| e.linear_parameters()).sum::<usize>();
    let mut fit = Fit {
        base: vec![0.0; b],
        base_sd: vec![0.0; b],
        delay,
        rotation: turn.rotation,
        payload_hint: turn.payload,
        ..nominal_frame(effects, signals)
    };
    let mut rhs = DVector::<f64>::zeros(p);
    let (mut fitted, mut yy) = (0usize, 0.0);
    let normal = normal_matrix(signals, arm, &fit, p, |k, s, arm_row, phi| {
        fitted += 1;
        let y = force[k] - s.gravity;
        yy += y.norm_squared();
        for i in 0..p {
            rhs[i] += column(arm_row, phi, i).dot(&y);
        }
    });
    let cholesky = normal.clone().cholesky()?;
    // A set one of whose columns the others hold exactly has no least-squares answer: a
    // payload beside a spring (its weight a constant force, which the anchor takes; its inertia
    // the moving mass's or the handle's). Rounding leaves such a pivot some 1e-14 of its
    // column's squared norm, where the least independent column of a sound fit keeps over 1e-4.
    let l = cholesky.l_dirty();
    if (0..p).any(|i| l[(i, i)] * l[(i, i)] < DEGENERATE * normal[(i, i)]) {
        return None;
    }
    let theta = cholesky.solve(&rhs);
    // Residual sum of squares on the fitted samples, σ² per component, and the covariance.
    let rss = (yy - 2.0 * theta.dot(&rhs) + (&normal * &theta).dot(&theta)).max(0.0);
    fit.train_sse = rss;
    fit.fitted = fitted;
    let dof = (3 * fitted).saturating_sub(p).max(1) as f64;
    let variance = rss / dof * signals.window as f64;
    let covariance = cholesky.inverse() * variance;
    let sd = |i: usize| covariance[(i, i)].max(0.0).sqrt();
    for i in 0..b {
        fit.base[i] = theta[i];
        fit.base_sd[i] = sd(i);
    }
    if !arm {
        fit.moving_mass = Vector3::new(theta[0], theta[1], theta[2]);
        fit.moving_mass_sd = Vector3::new(sd(0), sd(1), sd(2));
    }
    let mut at = b;
    for (i, effect) in effects.iter().enumerate() {
        for j in 0..effect.linear_parameters() {
            fit.theta[i][j] = theta[at];
            fit.theta_sd[i][j] = sd(at);
            at += 1;
        }
    }
    let residuals = fit.residuals_to(signals, force);
    let (train, heldout) = signals.split();
    fit.train_error = rms(&residuals, train);
    fit.heldout_error = rms(&residuals, heldout);
    Some(fit)
}

/// The nominal model: the grid's gravity force and a moving mass per axis, or for an arm its
/// inertia, joint friction and handle mass. An arm's inertia is held constant unless letting it
/// vary to first order in the pose cuts the held-out error to [`COMPLEXITY_MARGIN`] of that
/// (the rule every added parameter meets); `signals` keeps the choice for every later fit.
/// First order in the pose is what a serial arm needs; on a delta, whose arms turn about fixed
/// axes with only the platform's mass (the handle's column) moving, its 18 parameters follow
/// the training poses and left twice the held-out error of a constant inertia on a clean log.
pub fn nominal(signals: &mut Signals) -> Option<Fit> {
    let fit = |signals: &Signals| fit_linear(&[], signals, &signals.force, 0.0, Turn::default());
    if !signals.arm {
        return fit(signals);
    }
    signals.arm_inertia = ArmInertia::Constant;
    let constant = fit(signals)?;
    signals.arm_inertia = ArmInertia::FirstOrder;
    match fit(signals) {
        Some(first) if first.heldout_error <= COMPLEXITY_MARGIN * constant.heldout_error => {
            Some(first)
        }
        _ => {
            signals.arm_inertia = ArmInertia::Constant;
            Some(constant)
        }
    }
}

/// A column keeping less than this share of its squared norm beside the columns before it
/// makes a fit degenerate ([`fit_on`]).
const DEGENERATE: f64 = 1e-9;

/// Gauss–Newton steps for the gravity tilt.
const TILT_STEPS: usize = 4;
/// The delay search: first every [`COARSE_DELAY_STEP`], then every [`DELAY_STEP`] around the
/// best.
const COARSE_DELAY_STEP: f64 = 1e-3;

/// The delay in `range` (s) that best explains the training samples, searched every `step`,
/// with the other effects fitted at each. Only the command moves with the delay: one pass over
/// the samples builds the design's normal matrix once and each delay's right-hand side, so the
/// design is never stored and each delay costs a solve.
fn search_delay(
    effects: &[Effect],
    signals: &Signals,
    turn: Turn,
    range: (f64, f64),
    step: f64,
) -> Option<Fit> {
    let arm = signals.arm;
    let p = signals.base_count() + effects.iter().map(|e| e.linear_parameters()).sum::<usize>();
    let frame = Fit {
        rotation: turn.rotation,
        payload_hint: turn.payload,
        ..nominal_frame(effects, signals)
    };
    let steps = ((range.1 - range.0) / step).round() as usize;
    let delays: Vec<f64> = (0..=steps)
        .map(|k| range.0 + k as f64 * step)
        .filter(|delay| *delay > 0.0 && *delay <= MAX_DELAY + 1e-12)
        .collect();
    if delays.is_empty() {
        return None;
    }
    // Each delay's Φᵀy (row i of `rhs`: column i's product with each delay's y, delays
    // contiguous so the products vectorise) and yᵀy; y at one sample, a component per array.
    let count = delays.len();
    let mut rhs = vec![0.0; p * count];
    let mut yy = vec![0.0; count];
    let mut y = [vec![0.0; count], vec![0.0; count], vec![0.0; count]];
    let normal = normal_matrix(signals, arm, &frame, p, |k, s, arm_row, phi| {
        for (d, delay) in delays.iter().enumerate() {
            let y_d = signals.delayed_at(k, *delay) - s.gravity;
            yy[d] += y_d.norm_squared();
            for (a, y) in y.iter_mut().enumerate() {
                y[d] = y_d[a];
            }
        }
        for (i, row) in rhs.chunks_exact_mut(count).enumerate() {
            let c = column(arm_row, phi, i);
            for (d, r) in row.iter_mut().enumerate() {
                *r += c.x * y[0][d] + c.y * y[1][d] + c.z * y[2][d];
            }
        }
    });
    let cholesky = normal.cholesky()?;
    let best = delays
        .iter()
        .enumerate()
        .map(|(d, delay)| {
            let rhs = DVector::from_fn(p, |i, _| rhs[i * count + d]);
            let theta = cholesky.solve(&rhs);
            (*delay, yy[d] - theta.dot(&rhs))
        })
        .min_by(|a, b| a.1.total_cmp(&b.1))?
        .0;
    let force = signals.delayed_force(best);
    fit_linear(effects, signals, &force, best, turn)
}

/// An unfitted fit of `effects`: the frame [`Fit::turned`] needs.
fn nominal_frame(effects: &[Effect], signals: &Signals) -> Fit {
    Fit::unfitted(
        effects,
        signals.base_count(),
        signals.samples.first().is_some_and(|s| s.tilt.is_some()),
    )
}

impl Fit {
    /// `effects` on a nominal model of `base` parameters, every parameter zero.
    fn unfitted(effects: &[Effect], base: usize, linear_tilt: bool) -> Self {
        Fit {
            effects: effects.to_vec(),
            moving_mass: Vector3::zeros(),
            moving_mass_sd: Vector3::zeros(),
            base: vec![0.0; base],
            base_sd: vec![0.0; base],
            theta: effects
                .iter()
                .map(|e| vec![0.0; e.linear_parameters()])
                .collect(),
            theta_sd: effects
                .iter()
                .map(|e| vec![0.0; e.linear_parameters()])
                .collect(),
            delay: 0.0,
            delay_sd: 0.0,
            rotation: Vector3::zeros(),
            train_error: 0.0,
            heldout_error: 0.0,
            train_sse: 0.0,
            fitted: 0,
            linear_tilt,
            payload_hint: 0.0,
        }
    }
}

/// The delay's standard error from the curvature of the least-squares objective (the mean
/// squared residual on the samples fitted) around the best delay, inflated as the linear
/// parameters' are.
fn delay_sd(effects: &[Effect], signals: &Signals, best: &Fit) -> f64 {
    let h = DELAY_STEP;
    let n = best.fitted.max(1) as f64;
    let sse = |delay: f64| -> Option<f64> {
        let force = signals.delayed_force(delay);
        let f = fit_linear(effects, signals, &force, delay, best.turn())?;
        Some(f.train_sse / n)
    };
    let (Some(lo), Some(hi)) = (sse(best.delay - h), sse(best.delay + h)) else {
        return DELAY_STEP;
    };
    let mid = best.train_sse / n;
    let curvature = (lo - 2.0 * mid + hi) / (h * h);
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
            // A field that turns whole turns by the tilt found; a linear tilt takes the
            // payload found into its columns and the angle found into its scales.
            let turn = if fit.linear_tilt {
                Turn {
                    rotation: fit.tilt(&up).0,
                    payload: fit.payload(),
                }
            } else {
                Turn {
                    rotation: fit.tilt(&up).0,
                    payload: 0.0,
                }
            };
            fit = fit_linear(effects, signals, &force, fit.delay, turn)?;
        }
        Some(fit)
    };
    let mut fit = if has_delay {
        search_delay(
            effects,
            signals,
            Turn::default(),
            (0.0, MAX_DELAY),
            COARSE_DELAY_STEP,
        )?
    } else {
        fit_linear(effects, signals, &signals.force, 0.0, Turn::default())?
    };
    if has_tilt {
        fit = tilt_steps(fit)?;
    }
    if has_delay {
        let around = (fit.delay - COARSE_DELAY_STEP, fit.delay + COARSE_DELAY_STEP);
        fit = search_delay(effects, signals, fit.turn(), around, DELAY_STEP)?;
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
/// it cuts the nominal error's part above the floor to [`NAMING_SHRINK`] or less; otherwise
/// nothing is named. Returns
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
    // Each set, in its order, is fitted once: a lookahead's sets are the next step's trials,
    // and the backward pass's are earlier steps'.
    let memo = std::cell::RefCell::new(Vec::<(Vec<Effect>, Option<Fit>)>::new());
    let fit_once = |set: &[Effect], signals: &Signals| -> Option<Fit> {
        if let Some((_, known)) = memo.borrow().iter().find(|(s, _)| s == set) {
            return known.clone();
        }
        let new = fit(set, signals);
        memo.borrow_mut().push((set.to_vec(), new.clone()));
        new
    };
    loop {
        let trials: Vec<Fit> = candidates
            .iter()
            .filter(|e| !current.has(**e))
            .filter_map(|e| {
                let mut set = current.effects.clone();
                set.push(*e);
                fit_once(&set, signals)
            })
            .collect();
        if steps.is_empty() {
            first = trials.clone();
        }
        // The best held-out error of `fit` with one more candidate, all within `budget`
        // parameters beyond the current set.
        let continued = |fit: &Fit, budget: usize| -> Option<f64> {
            let used: usize = fit.effects[current.effects.len()..]
                .iter()
                .map(|e| e.parameters())
                .sum();
            candidates
                .iter()
                .filter(|e| !fit.has(**e) && used + e.parameters() <= budget)
                .filter_map(|e| {
                    let mut set = fit.effects.clone();
                    set.push(*e);
                    fit_once(&set, signals)
                })
                .map(|f| f.heldout_error)
                .min_by(f64::total_cmp)
        };
        if let Some(chosen) = choose(&current, &trials, &up, &continued) {
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
                let fit = fit_once(&set, signals)?;
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
            let reduced = fit_once(&set, signals)?;
            (current.heldout_error > STEP_SHRINK * reduced.heldout_error).then_some(reduced)
        });
        match without {
            Some(reduced) => current = reduced,
            None => break,
        }
    }
    if above_floor(current.heldout_error, floor)
        > NAMING_SHRINK * above_floor(nominal.heldout_error, floor)
    {
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
        // As the fit saw them: a named linear tilt's turns the payload's weight too.
        let mut c = [Vector3::zeros(); 4];
        let n = named.effect_columns(effect, s, &mut c);
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
                match signals.arm_row(k) {
                    Some(base) => out.extend_from_slice(base),
                    None => {
                        out.push(Vector3::new(s.acceleration.x, 0.0, 0.0));
                        out.push(Vector3::new(0.0, s.acceleration.y, 0.0));
                        out.push(Vector3::new(0.0, 0.0, s.acceleration.z));
                    }
                }
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

/// The part of a held-out error `error` above the noise floor `floor` (the two add as
/// independent), N.
pub fn above_floor(error: f64, floor: f64) -> f64 {
    (error * error - floor * floor).max(0.0).sqrt()
}

/// Of `trials` (each `current` with one effect more), the one to add, if any.
/// A candidate with more parameters replaces a simpler one unless the simpler one, with one
/// more effect of no more parameters in all, does as well (`continued`: the best such
/// continuation's held-out error): two simple effects are named before one complex effect that
/// mimics both (a spring's constant and gradient for a payload beside a tilt).
fn choose<'a>(
    current: &Fit,
    trials: &'a [Fit],
    up: &Vector3<f64>,
    continued: &dyn Fn(&Fit, usize) -> Option<f64>,
) -> Option<&'a Fit> {
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
                let budget = added(c).parameters();
                let simpler_path = continued(best, budget)
                    .is_some_and(|e| e * COMPLEXITY_MARGIN <= c.heldout_error);
                if !simpler_path {
                    chosen = Some(c)
                }
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
                up: grid.up,
                g: grid.grid.g,
                sliding: v / (v.norm_squared() + STICK_SPEED.powi(2)).sqrt(),
                joint: None,
                tilt: None,
            };
            let needed = fit.model_force(&s, None);
            let a = (applied - needed).component_div(&inertia);
            v += a * dt;
            x += v * dt;
        }
    }
    Some(positions)
}

#[cfg(test)]
mod tests {
    use nalgebra::Matrix3;

    use super::*;

    /// A non-symmetric J⁻ᵀ, so that rows and columns cannot be mixed up.
    fn to_handle() -> Matrix3<f64> {
        Matrix3::new(3.0, 1.0, -2.0, 0.5, 4.0, 1.5, -1.0, 2.5, 5.0)
    }

    /// Joints 0 and 2 rest, joint 1 slides throughout the kernel; the model's smoothed
    /// directions of sliding are not zero at rest.
    fn resting() -> JointSample {
        JointSample {
            offset: Vector3::zeros(),
            rate: Vector3::new(0.0, 0.5, -0.2 * STICK_RATE),
            acceleration: Vector3::zeros(),
            to_handle: to_handle(),
            sliding: Vector3::new(0.5, 1.0, -0.2),
        }
    }

    /// A resting joint forgives the torque it holds (what the residual asks of it plus the
    /// model's own friction term) within its friction band, and no more; a moving joint's
    /// torque counts whole.
    #[test]
    fn a_resting_joint_holds_the_torque_within_its_friction_and_no_more() {
        let joint = resting();
        let friction = [0.01, 0.02, 0.03];
        // The model's friction torques at the resting joints: 0.005 and −0.006 N m.
        let residual_of = |torque: Vector3<f64>| {
            let r = beyond_joint_friction(&joint, &friction, to_handle() * torque);
            to_handle().try_inverse().unwrap() * r
        };
        // Held 0.009 and −0.026 N m: inside the bands, nothing left; joint 1: all of it.
        let left = residual_of(Vector3::new(0.004, 0.05, -0.02));
        assert!(
            (left - Vector3::new(0.0, 0.05, 0.0)).norm() < 1e-12,
            "{left}"
        );
        // Held −0.009 N m (the residual alone, −0.014, would be beyond the band).
        let left = residual_of(Vector3::new(-0.014, 0.0, 0.0));
        assert!(left.norm() < 1e-12, "{left}");
        // Held 0.013 and 0.034 N m: beyond the bands, the excess, with its sign.
        let left = residual_of(Vector3::new(0.008, 0.0, 0.04));
        assert!(
            (left - Vector3::new(0.003, 0.0, 0.004)).norm() < 1e-12,
            "{left}"
        );
    }

    /// An arm's inertia at the handle is the force its columns ask per unit of the handle's
    /// acceleration: with the joints still (no velocity products), the columns' force for
    /// q̈ = J⁻¹ Ẍ is Λ Ẍ, first-order terms and the handle's mass included.
    #[test]
    fn an_arms_inertia_at_the_handle_is_what_its_columns_ask_of_an_acceleration() {
        let mut fit = Fit::unfitted(&[], ARM_COLUMNS, false);
        for (i, b) in fit.base.iter_mut().enumerate() {
            *b = 1e-3 * (1.0 + (i as f64 * 0.37).sin());
        }
        let to_handle = to_handle();
        let handle_acceleration = Vector3::new(0.4, -1.2, 0.9);
        let joint = JointSample {
            offset: Vector3::new(0.1, -0.2, 0.05),
            rate: Vector3::zeros(),
            acceleration: to_handle.transpose() * handle_acceleration,
            to_handle,
            sliding: Vector3::zeros(),
        };
        let mut columns = [Vector3::zeros(); ARM_COLUMNS];
        arm_columns(&joint, &handle_acceleration, &mut columns);
        let asked: Vector3<f64> = columns.iter().zip(&fit.base).map(|(c, b)| c * *b).sum();
        let sample = Sample {
            position: Vector3::zeros(),
            velocity: Vector3::zeros(),
            acceleration: handle_acceleration,
            sliding: Vector3::zeros(),
            gravity: Vector3::zeros(),
            up: Vector3::z(),
            g: 9.81,
            joint: Some(joint),
            tilt: None,
        };
        let lambda = fit.handle_inertia(&sample) * handle_acceleration;
        assert!(
            (lambda - asked).norm() < 1e-12 * asked.norm(),
            "{lambda} {asked}"
        );
    }

    /// An arm's fit scores a sample where joints rest through their fitted Coulomb levels (its
    /// parameters [`ARM_FRICTION`] + 2j): a command that holds the resting joints within them
    /// leaves only the sliding joint's torque; joints that turned or stuck within the kernel's
    /// span (|s_j| < 1) forgive within f_c,j (1 − |s_j|) of the model's friction; joints that
    /// slide throughout count whole; with the handle at rest, nothing.
    #[test]
    fn an_arm_fit_forgives_its_resting_joints_their_fitted_friction() {
        let joint = resting();
        let friction = [0.01, 0.02, 0.03];
        let mut fit = Fit::unfitted(&[], ARM_COLUMNS, false);
        for (j, f_c) in friction.iter().enumerate() {
            fit.base[ARM_FRICTION + 2 * j] = *f_c;
        }
        let gravity = Vector3::new(0.0, 0.0, 0.8);
        let mut sample = Sample {
            position: Vector3::zeros(),
            velocity: Vector3::new(0.02, 0.0, 0.0),
            acceleration: Vector3::zeros(),
            sliding: Vector3::x(),
            gravity,
            up: Vector3::z(),
            g: 9.81,
            joint: Some(joint),
            tilt: None,
        };
        let mut columns = [Vector3::zeros(); ARM_COLUMNS];
        arm_columns(&joint, &sample.acceleration, &mut columns);
        // The joints hold 0.009, (sliding) 0.02 + 0.02 and −0.026 N m.
        let command = gravity + to_handle() * Vector3::new(0.009, 0.04, -0.026);
        let r = fit.residual(&sample, Some(&columns), &command);
        let torque = to_handle().try_inverse().unwrap() * r;
        assert!(
            (torque - Vector3::new(0.0, 0.02, 0.0)).norm() < 1e-12,
            "{torque}"
        );
        // No joint at rest, but joints 0 and 2 turned within the kernel's span (they slid a half
        // and a fifth of it net one way): their residual torques, 0.004 and −0.02 N m, lie
        // within 0.005 and 0.024 N m of the model's friction.
        let mut moving = sample;
        moving.joint = Some(JointSample {
            rate: Vector3::new(0.3, 0.5, -0.4),
            ..joint
        });
        let r = fit.residual(&moving, Some(&columns), &command);
        let torque = to_handle().try_inverse().unwrap() * r;
        assert!(
            (torque - Vector3::new(0.0, 0.02, 0.0)).norm() < 1e-12,
            "{torque}"
        );
        // Every joint sliding throughout (the model's friction 0.01, 0.02 and −0.03 N m): the
        // whole residual.
        let sliding = JointSample {
            rate: Vector3::new(0.3, 0.5, -0.4),
            sliding: Vector3::new(1.0, 1.0, -1.0),
            ..joint
        };
        moving.joint = Some(sliding);
        arm_columns(&sliding, &moving.acceleration, &mut columns);
        let r = fit.residual(&moving, Some(&columns), &command);
        let torque = to_handle().try_inverse().unwrap() * r;
        assert!(
            (torque - Vector3::new(-0.001, 0.02, 0.004)).norm() < 1e-12,
            "{torque}"
        );
        // The handle at rest: nothing.
        sample.velocity = Vector3::zeros();
        assert_eq!(
            fit.residual(&sample, Some(&columns), &command),
            Vector3::zeros()
        );
    }
}
