//! What the log itself can tell (docs/discrepancy.md §2): its noise floor, what its excitation
//! cannot reveal, and where a residual the named effects leave lives.

use nalgebra::{Matrix3, Vector3};

use super::analysis::{Fit, Signals, Weights};
use super::effects::Effect;
use super::log::Log;

/// Slower than this the handle counts as held, m/s.
pub const HOLD_SPEED: f64 = 2e-3;
/// A hold counts when it lasts at least this long, s.
pub const MIN_HOLD: f64 = 0.3;
/// The held-out residual of the named effects is unexplained above this many noise floors.
pub const UNEXPLAINED_FACTOR: f64 = 2.0;

/// The residual a model that explained everything would still leave: what the white noise of
/// the measured position and of the command become through the smoothing (docs/discrepancy.md
/// §2).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NoiseFloor {
    /// RMS |r|, N.
    pub force: f64,
    /// Its two parts: m Ẍ from the position's noise, and F from the command's, N.
    pub from_position: f64,
    pub from_command: f64,
    /// The white noise found per axis in the position, m, and in the command, N.
    pub position_noise: Vector3<f64>,
    pub command_noise: Vector3<f64>,
}

/// The runs of samples slower than [`HOLD_SPEED`] lasting [`MIN_HOLD`] or more, each trimmed by
/// a smoothing window at both ends (the filter reaches into the motion there).
pub fn holds(signals: &Signals) -> Vec<std::ops::Range<usize>> {
    let min = (MIN_HOLD / signals.period).ceil() as usize;
    let trim = signals.first;
    let mut runs = Vec::new();
    let mut start = None;
    for k in 0..=signals.len() {
        let held = k < signals.len() && signals.samples[k].velocity.norm() < HOLD_SPEED;
        match (held, start) {
            (true, None) => start = Some(k),
            (false, Some(s)) => {
                if k - s >= min && k - s > 2 * trim + 1 {
                    runs.push(s + trim..k - trim);
                }
                start = None;
            }
            _ => {}
        }
    }
    runs
}

/// Half-width of the quadratic whose leftovers measure a signal's white noise, samples.
const NOISE_HALF_WIDTH: usize = 3;

/// The white noise per axis of `x` (standard deviation): what a quadratic over ±3 samples
/// leaves, scaled by the share of a white noise's variance that it leaves (1 − w₀, the
/// smoother's weight on its own sample). The motion, smooth over 7 samples, leaves nothing.
fn white_noise(x: &[Vector3<f64>]) -> Vector3<f64> {
    let h = NOISE_HALF_WIDTH;
    let w = Weights::new(h);
    let mut sum = Vector3::zeros();
    for k in h..x.len() - h {
        let smooth: Vector3<f64> = (0..=2 * h).map(|j| x[k + j - h] * w.value[j]).sum();
        sum += (x[k] - smooth).map(|e| e * e);
    }
    let n = (x.len() - 2 * h) as f64;
    (sum / (n * (1.0 - w.value[h]))).map(f64::sqrt)
}

/// The noise floor of `model` on `log` as `signals` smoothed it: the position's white noise
/// through the smoother's second derivative times the model's inertia at the handle
/// ([`Fit::handle_inertia`]: a point mass's moving mass, an arm's J⁻ᵀ M J⁻¹ and handle mass,
/// as a mean square over the samples), and the command's through its value, added as
/// independent.
pub fn noise_floor(log: &Log, signals: &Signals, model: &Fit) -> NoiseFloor {
    let w = signals.kernel();
    let norm = |weights: &[f64]| weights.iter().map(|c| c * c).sum::<f64>().sqrt();
    let position_noise = white_noise(&log.position);
    let command_noise = white_noise(&log.force);
    let acceleration_noise = position_noise * (norm(&w.curvature) / signals.period.powi(2));
    let square: f64 = signals
        .samples
        .iter()
        .map(|s| {
            (model.handle_inertia(s) * Matrix3::from_diagonal(&acceleration_noise)).norm_squared()
        })
        .sum();
    let from_position = (square / signals.len().max(1) as f64).sqrt();
    let from_command = (command_noise * norm(&w.value)).norm();
    NoiseFloor {
        force: from_position.hypot(from_command),
        from_position,
        from_command,
        position_noise,
        command_noise,
    }
}

/// Something the log's excitation cannot show, and the effects it hides.
#[derive(Clone, Debug, PartialEq)]
pub struct Limit {
    /// Which check: `fast_motion`, `speed_range`, `travel_x` (y, z), `holds`, `delay_side`,
    /// `confounded`, `noise_floor`.
    pub check: &'static str,
    /// The effects the log cannot reveal or tell apart because of it.
    pub effects: Vec<Effect>,
    /// One line for the user.
    pub message: String,
}

/// Below this share of the velocity's power above [`FAST_HZ`] the log has no fast motion.
const MIN_FAST_SHARE: f64 = 0.05;
pub const FAST_HZ: f64 = 1.0;
/// The speeds in motion (above [`HOLD_SPEED`]) must span this ratio, 90th to 10th percentile,
/// for friction and damping to be told apart.
const MIN_SPEED_RATIO: f64 = 3.0;
/// Travel along an axis (5th to 95th percentile) below this cannot show a spring along it, m.
const MIN_TRAVEL: f64 = 5e-3;

/// What the excitation of `signals` cannot reveal.
pub fn excitation_limits(signals: &Signals) -> Vec<Limit> {
    let mut limits = Vec::new();
    let n = signals.len();
    // Fast motion: the velocity's part that a moving average over one period of FAST_HZ
    // does not follow.
    let half = ((0.5 / FAST_HZ) / signals.period).round() as usize;
    let velocity: Vec<Vector3<f64>> = signals.samples.iter().map(|s| s.velocity).collect();
    let mut prefix = vec![Vector3::zeros(); n + 1];
    for k in 0..n {
        prefix[k + 1] = prefix[k] + velocity[k];
    }
    let (mut fast, mut total) = (0.0, 0.0);
    for k in half..n.saturating_sub(half) {
        let mean = (prefix[k + half + 1] - prefix[k - half]) / (2 * half + 1) as f64;
        fast += (velocity[k] - mean).norm_squared();
        total += velocity[k].norm_squared();
    }
    if total <= 0.0 || fast / total < MIN_FAST_SHARE {
        limits.push(Limit {
            check: "fast_motion",
            effects: vec![Effect::TimeDelay],
            message: format!(
                "no motion faster than about {FAST_HZ} Hz ({:.0} % of the velocity's power): a \
                 time delay cannot show, and the moving mass is uncertain",
                1e2 * fast / total.max(f64::MIN_POSITIVE)
            ),
        });
    }
    let mut speeds: Vec<f64> = velocity
        .iter()
        .map(|v| v.norm())
        .filter(|v| *v >= HOLD_SPEED)
        .collect();
    speeds.sort_by(f64::total_cmp);
    let percentile = |v: &[f64], p: f64| v[((v.len() - 1) as f64 * p) as usize];
    if speeds.len() < 2 || percentile(&speeds, 0.9) < MIN_SPEED_RATIO * percentile(&speeds, 0.1) {
        limits.push(Limit {
            check: "speed_range",
            effects: vec![Effect::CoulombFriction, Effect::ViscousDamping],
            message: "the speeds in motion span less than a factor of 3: Coulomb friction and \
                      viscous damping cannot be told apart"
                .into(),
        });
    }
    for (axis, name) in ["travel_x", "travel_y", "travel_z"].into_iter().enumerate() {
        let mut x: Vec<f64> = signals.samples.iter().map(|s| s.position[axis]).collect();
        x.sort_by(f64::total_cmp);
        let travel = percentile(&x, 0.95) - percentile(&x, 0.05);
        if travel < MIN_TRAVEL {
            limits.push(Limit {
                check: name,
                effects: vec![Effect::Spring],
                message: format!(
                    "{:.1} mm of travel along {} (5th to 95th percentile): a spring along it \
                     cannot be told from a constant force",
                    travel * 1e3,
                    &name[7..]
                ),
            });
        }
    }
    if holds(signals).is_empty() {
        limits.push(Limit {
            check: "holds",
            effects: vec![],
            message: format!(
                "no holds (slower than {} mm/s for {} s): friction at rest (stiction) cannot \
                 show",
                HOLD_SPEED * 1e3,
                MIN_HOLD
            ),
        });
    }
    limits
}

/// The one limit every log of commands and reported positions has, said when a delay is named.
pub fn delay_side() -> Limit {
    Limit {
        check: "delay_side",
        effects: vec![Effect::TimeDelay],
        message: "a log of commands and reported positions shows only the sum of the actuation \
                  delay (the force acts late) and the sensing delay (the position is reported \
                  late): time_delay is that sum, and which side holds it cannot be told from the \
                  log"
        .into(),
    }
}

/// What every log cannot show: a force below its noise floor `floor` (N).
pub fn below_floor(floor: f64) -> Limit {
    Limit {
        check: "noise_floor",
        effects: vec![],
        message: format!(
            "effects whose force stays below the log's noise floor ({:.1} mN RMS): none is \
             named for them, whatever they are",
            floor * 1e3
        ),
    }
}

/// An effect the log cannot tell from the named ones `with`.
pub fn confounded(effect: Effect, with: &[Effect]) -> Limit {
    let names: Vec<&str> = with.iter().map(|e| e.name()).collect();
    Limit {
        check: "confounded",
        effects: vec![effect],
        message: format!(
            "{} cannot be told from {} in this log: its signature lies in theirs (its \
             parameter's standard error would grow over {}-fold beside them), so they may hold \
             part of it",
            effect.name(),
            names.join(" and "),
            super::analysis::CONFOUNDED_INFLATION,
        ),
    }
}

/// What orders a residual best: the variable whose bins explain the largest share of its
/// variance.
#[derive(Clone, Debug, PartialEq)]
pub struct Ordering {
    /// `position`, `velocity`, `acceleration`, `time` or `frequency`.
    pub by: &'static str,
    /// Share of the residual's variance its binned means (or, for frequency, its strongest
    /// spectral line) explain, 0 to 1.
    pub share: f64,
    /// Every variable's share, in the order above.
    pub shares: [(&'static str, f64); 5],
    /// The residual against that variable, per axis: (value in its unit, residual N), every
    /// few samples (for the figure); for frequency the spectrum, (Hz, N).
    pub points: [Vec<(f64, f64)>; 3],
    /// The unit the points' first value is in.
    pub unit: &'static str,
}

/// A variable of the samples: its value at sample k along axis a.
type Value<'a> = dyn Fn(usize, usize) -> f64 + 'a;

/// Bins along each axis for the binned means.
const BINS: usize = 60;

/// Share of the variance of `r` (per axis, summed) that the means of `BINS` bins of `value`
/// explain; a bin needs several samples to count.
fn binned_share(r: &[Vector3<f64>], value: &Value) -> f64 {
    let (mut explained, mut total) = (0.0, 0.0);
    for axis in 0..3 {
        let values: Vec<f64> = (0..r.len()).map(|k| value(k, axis)).collect();
        let lo = values.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let mean = r.iter().map(|v| v[axis]).sum::<f64>() / r.len() as f64;
        let mut sums = [(0.0, 0usize); BINS];
        for (k, v) in values.iter().enumerate() {
            let b = if hi > lo {
                (((v - lo) / (hi - lo)) * BINS as f64) as usize
            } else {
                0
            };
            let bin = &mut sums[b.min(BINS - 1)];
            bin.0 += r[k][axis];
            bin.1 += 1;
        }
        for (sum, count) in sums {
            if count >= 10 {
                explained += count as f64 * (sum / count as f64 - mean).powi(2);
            }
        }
        total += r.iter().map(|v| (v[axis] - mean).powi(2)).sum::<f64>();
    }
    if total > 0.0 {
        (explained / total).min(1.0)
    } else {
        0.0
    }
}

/// Where the residual `r` of the held-out samples `range` of `signals` lives.
pub fn ordering(signals: &Signals, r: &[Vector3<f64>], range: std::ops::Range<usize>) -> Ordering {
    let s = &signals.samples[range.clone()];
    let r = &r[range.clone()];
    let t = &signals.time[range];
    let variables: [(&'static str, &Value); 4] = [
        ("position", &|k, a| s[k].position[a]),
        ("velocity", &|k, a| s[k].velocity[a]),
        ("acceleration", &|k, a| s[k].acceleration[a]),
        ("time", &|k, _| t[k]),
    ];
    let mut shares = [("", 0.0); 5];
    for (i, (name, value)) in variables.iter().enumerate() {
        shares[i] = (name, binned_share(r, *value));
    }
    // Frequency: the strongest line's share of the variance (a ripple, a vibration).
    let spectrum = spectrum(r, signals.period);
    let variance: f64 = {
        let n = r.len() as f64;
        let mean: Vector3<f64> = r.iter().sum::<Vector3<f64>>() / n;
        r.iter().map(|v| (v - mean).norm_squared()).sum::<f64>() / n
    };
    let line = spectrum.iter().map(|(_, power)| *power).fold(0.0, f64::max);
    shares[4] = (
        "frequency",
        if variance > 0.0 {
            (line / variance).min(1.0)
        } else {
            0.0
        },
    );
    let (best, share) = shares
        .iter()
        .copied()
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .expect("five variables");
    let step = (r.len() / 2000).max(1);
    let points = std::array::from_fn(|a| match best {
        "frequency" => spectrum
            .iter()
            .map(|(hz, power)| (*hz, (2.0 * power).sqrt()))
            .collect(),
        _ => {
            let (_, value) = variables
                .iter()
                .find(|(name, _)| *name == best)
                .expect("a variable");
            (0..r.len())
                .step_by(step)
                .map(|k| (value(k, a), r[k][a]))
                .collect()
        }
    });
    let unit = match best {
        "position" => "m",
        "velocity" => "m/s",
        "acceleration" => "m/s²",
        "time" => "s",
        _ => "Hz",
    };
    Ordering {
        by: best,
        share,
        shares,
        points,
        unit,
    }
}

/// Power of each spectral line of `r` (summed over axes: the variance a sine at that frequency
/// carries), 0.2 to 50 Hz.
fn spectrum(r: &[Vector3<f64>], period: f64) -> Vec<(f64, f64)> {
    let n = r.len();
    let duration = n as f64 * period;
    // Lines every 1/duration Hz would resolve everything; 400 lines spaced evenly in log
    // frequency are enough to find a strong one.
    let step = (n / 4000).max(1);
    (0..400)
        .map(|i| {
            let hz = 0.2 * (250.0f64).powf(i as f64 / 399.0);
            let hz = (hz * duration).round() / duration;
            let w = std::f64::consts::TAU * hz * period;
            // One sine and cosine per sample, for the three axes.
            let (mut re, mut im) = (Vector3::<f64>::zeros(), Vector3::<f64>::zeros());
            for k in (0..n).step_by(step) {
                let (sin, cos) = (w * k as f64).sin_cos();
                for a in 0..3 {
                    re[a] += r[k][a] * cos;
                    im[a] += r[k][a] * sin;
                }
            }
            let m = n.div_ceil(step) as f64;
            let power: f64 = (0..3)
                .map(|a| 2.0 * (re[a] * re[a] + im[a] * im[a]) / (m * m))
                .sum();
            (hz, power)
        })
        .collect()
}
