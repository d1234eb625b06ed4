//! Where the nominal model's residual lives (axis, region, speed, lag, frequency, whiteness), and
//! the files `hgcd analyze` writes: `summary.json`, `report.md`, the figures, the grid and the
//! augmented model (docs/discrepancy.md §4).

use std::fmt::Write as _;
use std::path::Path;

use nalgebra::Vector3;
use plotters::coord::Shift;
use plotters::prelude::*;
use serde_json::json;

use super::analysis::{self, Fit, Signals};
use super::effects::{Effect, ARM_FRICTION, ARM_HANDLE_MASS};
use super::{evidence, Analysis, AnalyzeError, AnalyzeRequest};
use crate::control::compensation::GravityModel;
use crate::figure::{self, Figure, OutError};
use crate::grid::{EffectRecord, GridFile, ModelFile, MODEL_FORMAT};

/// Speed bands the residual is split into, m/s: holds, slow and fast motion.
const SPEED_BANDS: [f64; 2] = [0.005, 0.03];
/// Lags of the command correlated with the residual, s (both ways).
const MAX_LAG: f64 = 0.05;
/// Autocorrelation lags of the whiteness test, in smoothing windows (the smoothing itself
/// correlates neighbouring samples).
const WHITENESS_LAGS: usize = 20;
/// The residual's spectrum: this many frequencies up to [`MAX_FREQUENCY`], Hz.
const FREQUENCIES: usize = 200;
const MAX_FREQUENCY: f64 = 20.0;

/// Where the nominal model's held-out residual lives, and how white each model's residual is.
#[derive(Clone, Debug, PartialEq)]
pub struct Diagnostics {
    /// RMS per axis, N.
    pub axis_rms: Vector3<f64>,
    /// RMS |r| at speeds below 5 mm/s, 5 to 30 mm/s and above, N (NaN where no sample).
    pub speed_rms: [f64; 3],
    /// RMS |r| per octant of the grid about its centre (x fastest, − before +), N.
    pub octant_rms: [f64; 8],
    /// Correlation of each axis's residual with its velocity, position and acceleration.
    pub velocity_correlation: Vector3<f64>,
    pub position_correlation: Vector3<f64>,
    pub acceleration_correlation: Vector3<f64>,
    /// Correlation of the residual with the command `lag` s earlier (summed over axes), per lag.
    pub command_lags: Vec<(f64, f64)>,
    /// Amplitude spectrum of the residual (|r| summed over axes), N, per frequency, Hz.
    pub spectrum: Vec<(f64, f64)>,
    /// Share of autocorrelation lags (1 to 20 smoothing windows) outside ±1.96/√N: nominal,
    /// augmented (white: about 5 %).
    pub whiteness: (f64, f64),
    /// Share of command lags whose correlation with the residual lies outside ±1.96/√N.
    pub input_correlation: (f64, f64),
}

fn correlation(a: impl Iterator<Item = f64> + Clone, b: impl Iterator<Item = f64> + Clone) -> f64 {
    let n = a.clone().count() as f64;
    let (ma, mb) = (a.clone().sum::<f64>() / n, b.clone().sum::<f64>() / n);
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for (x, y) in a.zip(b) {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    let d = (saa * sbb).sqrt();
    if d > 0.0 {
        sab / d
    } else {
        0.0
    }
}

/// Share of lags `step`, 2 `step` … `lags` `step` whose normalised autocorrelation of `r`
/// (summed over axes) lies outside the 95 % band of white noise.
fn whiteness(r: &[Vector3<f64>], step: usize, lags: usize) -> f64 {
    let n = r.len();
    let mean: Vector3<f64> = r.iter().sum::<Vector3<f64>>() / n as f64;
    let c = |k: usize| -> f64 {
        (0..n - k)
            .map(|i| (r[i] - mean).dot(&(r[i + k] - mean)))
            .sum::<f64>()
    };
    let c0 = c(0);
    let bound = 1.96 / (n as f64).sqrt();
    (1..=lags)
        .filter(|&k| (c(k * step) / c0).abs() > bound)
        .count() as f64
        / lags as f64
}

/// Correlation of `r` with the command `lag` samples earlier, summed over axes.
fn lagged(r: &[Vector3<f64>], f: &[Vector3<f64>], offset: usize, lag: i64) -> f64 {
    let range = offset as i64..(offset + r.len()) as i64;
    let indices = range.filter(|&k| k - lag >= 0 && ((k - lag) as usize) < f.len());
    (0..3)
        .map(|a| {
            correlation(
                indices.clone().map(|k| r[(k - offset as i64) as usize][a]),
                indices.clone().map(|k| f[(k - lag) as usize][a]),
            )
        })
        .sum::<f64>()
        / 3.0
}

impl Diagnostics {
    pub fn new(signals: &Signals, nominal: &Fit, augmented: &Fit, model: &GravityModel) -> Self {
        let (_, heldout) = signals.split();
        let r_all = nominal.residuals(signals);
        let r = &r_all[heldout.clone()];
        let s = &signals.samples[heldout.clone()];
        let n = r.len() as f64;
        let axis_rms =
            Vector3::from_fn(|a, _| (r.iter().map(|v| v[a] * v[a]).sum::<f64>() / n).sqrt());
        let band_rms = |keep: &dyn Fn(usize) -> bool| {
            let picked: Vec<f64> = (0..r.len())
                .filter(|&k| keep(k))
                .map(|k| r[k].norm_squared())
                .collect();
            if picked.is_empty() {
                f64::NAN
            } else {
                (picked.iter().sum::<f64>() / picked.len() as f64).sqrt()
            }
        };
        let speed = |k: usize| s[k].velocity.norm();
        let speed_rms = [
            band_rms(&|k| speed(k) < SPEED_BANDS[0]),
            band_rms(&|k| speed(k) >= SPEED_BANDS[0] && speed(k) < SPEED_BANDS[1]),
            band_rms(&|k| speed(k) >= SPEED_BANDS[1]),
        ];
        let centre = (model.grid.origin + model.grid.far_corner()) / 2.0;
        let octant = |k: usize| {
            let d = s[k].position - centre;
            usize::from(d.x > 0.0) + 2 * usize::from(d.y > 0.0) + 4 * usize::from(d.z > 0.0)
        };
        let octant_rms = std::array::from_fn(|o| band_rms(&|k| octant(k) == o));
        let per_axis = |field: &dyn Fn(usize) -> Vector3<f64>| {
            Vector3::from_fn(|a, _| {
                correlation(
                    r.iter().map(move |v| v[a]),
                    (0..r.len()).map(move |k| field(k)[a]),
                )
            })
        };
        let max_lag = (MAX_LAG / signals.period).round() as i64;
        let step = (max_lag / 25).max(1);
        let command_lags = (-max_lag..=max_lag)
            .step_by(step as usize)
            .map(|lag| {
                (
                    lag as f64 * signals.period,
                    lagged(r, &signals.force, heldout.start, lag),
                )
            })
            .collect();
        let spectrum = (1..=FREQUENCIES)
            .map(|i| {
                let hz = MAX_FREQUENCY * i as f64 / FREQUENCIES as f64;
                let w = 2.0 * std::f64::consts::PI * hz * signals.period;
                // One sine and cosine per sample, for the three axes.
                let (mut re, mut im) = (Vector3::<f64>::zeros(), Vector3::<f64>::zeros());
                for (k, v) in r.iter().enumerate() {
                    let (sin, cos) = (w * k as f64).sin_cos();
                    for a in 0..3 {
                        re[a] += v[a] * cos;
                        im[a] += v[a] * sin;
                    }
                }
                let amplitude: f64 = (0..3)
                    .map(|a| 2.0 * (re[a] * re[a] + im[a] * im[a]).sqrt() / n)
                    .sum();
                (hz, amplitude)
            })
            .collect();
        let augmented_r = augmented.residuals(signals);
        let input = |res: &[Vector3<f64>]| {
            let bound = 1.96 / n.sqrt();
            let lags: Vec<i64> = (0..=max_lag).step_by(step as usize).collect();
            lags.iter()
                .filter(|&&lag| lagged(res, &signals.force, heldout.start, lag).abs() > bound)
                .count() as f64
                / lags.len() as f64
        };
        Self {
            axis_rms,
            speed_rms,
            octant_rms,
            velocity_correlation: per_axis(&|k| s[k].velocity),
            position_correlation: per_axis(&|k| s[k].position),
            acceleration_correlation: per_axis(&|k| s[k].acceleration),
            command_lags,
            spectrum,
            whiteness: (
                whiteness(r, signals.window, WHITENESS_LAGS),
                whiteness(
                    &augmented_r[heldout.clone()],
                    signals.window,
                    WHITENESS_LAGS,
                ),
            ),
            input_correlation: (input(r), input(&augmented_r[heldout.clone()])),
        }
    }
}

/// The fitted parameters of `effect` in `fit`, SI, as `summary.json` gives them, and their
/// standard errors under the same keys.
fn effect_parameters(
    fit: &Fit,
    effect: Effect,
    up: &Vector3<f64>,
) -> (serde_json::Value, serde_json::Value) {
    let (mut p, mut sd) = (json!({}), json!({}));
    let i = fit.effects.iter().position(|e| *e == effect);
    let (t, e) = match i {
        Some(i) => (fit.theta[i].as_slice(), fit.theta_sd[i].as_slice()),
        None => return (p, sd),
    };
    match effect {
        Effect::None => {}
        Effect::Payload => (p["mass_kg"], sd["mass_kg"]) = (json!(t[0]), json!(e[0])),
        Effect::CoulombFriction => (p["force_n"], sd["force_n"]) = (json!(t[0]), json!(e[0])),
        Effect::ViscousDamping => {
            (p["damping_n_s_per_m"], sd["damping_n_s_per_m"]) = (json!(t[0]), json!(e[0]))
        }
        Effect::GravityTilt => {
            let (delta, angle_sd) = fit.tilt(up);
            let angle = delta.norm();
            p["angle_rad"] = json!(angle);
            p["angle_deg"] = json!(angle.to_degrees());
            sd["angle_rad"] = json!(angle_sd);
            sd["angle_deg"] = json!(angle_sd.to_degrees());
            let axis = if angle > 0.0 { delta / angle } else { delta };
            p["rotation_axis"] = json!([axis.x, axis.y, axis.z]);
        }
        Effect::Spring => {
            let k = t[0];
            let anchor = -Vector3::new(t[1], t[2], t[3]) / k;
            p["stiffness_n_per_m"] = json!(k);
            sd["stiffness_n_per_m"] = json!(e[0]);
            p["anchor_m"] = json!([anchor.x, anchor.y, anchor.z]);
        }
        Effect::TimeDelay => {
            (p["delay_s"], sd["delay_s"]) = (json!(fit.delay), json!(fit.delay_sd));
            (p["delay_ms"], sd["delay_ms"]) = (json!(fit.delay * 1e3), json!(fit.delay_sd * 1e3));
        }
    }
    (p, sd)
}

/// Every parameter of `fit`, SI, as `summary.json` gives them: the moving mass and each
/// effect's.
fn parameters(fit: &Fit, up: &Vector3<f64>) -> serde_json::Value {
    let m = fit.moving_mass;
    let mut p = if let Some(inertia) = fit.arm_inertia() {
        // The arm's nominal model: M₀ (xx, yy, zz, xy, xz, yz), whether it varies to first
        // order in the pose, each joint's Coulomb and viscous friction, and the handle's point
        // mass (docs/discrepancy.md §2.4).
        let b = &fit.base;
        let friction = |first: usize| [0, 2, 4].map(|j| b[ARM_FRICTION + first + j]);
        json!({
            "joint_inertia_kg_m2": &b[..6],
            "joint_inertia_in_pose": inertia.name(),
            "joint_coulomb_friction_n_m": friction(0),
            "joint_viscous_friction_n_m_s": friction(1),
            "handle_mass_kg": b[ARM_HANDLE_MASS],
        })
    } else {
        json!({ "moving_mass_kg": [m.x, m.y, m.z] })
    };
    for effect in &fit.effects {
        if let (serde_json::Value::Object(map), Some(all)) =
            (effect_parameters(fit, *effect, up).0, p.as_object_mut())
        {
            all.extend(map);
        }
    }
    p
}

/// The metric the error figures measure.
const METRIC: &str = "rms_force_residual_n: root mean square over the held-out samples (the last \
                      40 % of the log) of |F − F_model|, F the command and F_model the force the \
                      model needs for the measured motion, both smoothed alike (N)";

/// Write everything into `request.out`.
pub(super) fn write(
    request: &AnalyzeRequest,
    file: &GridFile,
    signals: &Signals,
    a: &Analysis,
) -> Result<(), AnalyzeError> {
    let out = &request.out;
    let up = a.up;
    // Nothing is written for a parameter no device shows (the model file's ranges).
    for effect in &a.effects {
        effect_record(&a.augmented, *effect, &up)
            .check()
            .map_err(|why| AnalyzeError::AbsurdParameter {
                why,
                log: request.log.clone(),
            })?;
    }
    let write = |name: &str, text: String| {
        let path = out.join(name);
        std::fs::write(&path, text).map_err(|source| OutError { path, source })
    };
    let (before, after) = a.errors();
    let d = &a.diagnostics;
    let candidates: Vec<_> = a
        .candidates
        .iter()
        .map(|c| {
            json!({
                "effect": c.effects.last().map_or("none", |e| e.name()),
                "parameters": parameters(c, &up),
                "error_train": c.train_error,
                "error_heldout": c.heldout_error,
            })
        })
        .collect();
    let effects: Vec<_> = a
        .effects
        .iter()
        .map(|e| {
            let (parameters, sd) = effect_parameters(&a.augmented, *e, &up);
            json!({ "name": e.name(), "parameters": parameters, "standard_error": sd })
        })
        .collect();
    let steps: Vec<_> = a
        .steps
        .iter()
        .map(|s| {
            json!({
                "added": s.added.name(),
                "effects": s.fit.effects.iter().map(|e| e.name()).collect::<Vec<_>>(),
                "error_heldout": s.fit.heldout_error,
            })
        })
        .collect();
    let limits: Vec<_> = a
        .limits
        .iter()
        .map(|l| {
            json!({
                "check": l.check,
                "effects": l.effects.iter().map(|e| e.name()).collect::<Vec<_>>(),
                "message": l.message,
            })
        })
        .collect();
    let summary = json!({
        "grid": request.grid.display().to_string(),
        "log": request.log.display().to_string(),
        "effect": a.effect().name(),
        "effects": effects,
        "parameters": parameters(&a.augmented, &up),
        "steps": steps,
        "noise_floor_n": a.noise_floor.force,
        "noise_floor": {
            "from_position_n": a.noise_floor.from_position,
            "from_command_n": a.noise_floor.from_command,
            "position_noise_m": xyz(&a.noise_floor.position_noise),
            "command_noise_n": xyz(&a.noise_floor.command_noise),
        },
        "unexplained": a.unexplained,
        "unexplained_factor": evidence::UNEXPLAINED_FACTOR,
        "unexplained_where": {
            "by": a.ordering.by,
            "share": a.ordering.share,
            "shares": a.ordering.shares.iter().map(|(n, v)| (n.to_string(), json!(v))).collect::<serde_json::Map<_, _>>(),
        },
        "limits": limits,
        "metric": METRIC,
        "error_before": before,
        "error_after": after,
        "position_error_before_m": a.position_error.map(|p| p.0),
        "position_error_after_m": a.position_error.map(|p| p.1),
        "naming": {
            "shrink": analysis::NAMING_SHRINK,
            "step_shrink": analysis::STEP_SHRINK,
            "complexity_margin": analysis::COMPLEXITY_MARGIN,
        },
        "candidates": candidates,
        "where": {
            "axis_rms_n": xyz(&d.axis_rms),
            "speed_bands_m_per_s": SPEED_BANDS,
            "speed_rms_n": d.speed_rms.map(finite),
            "octant_rms_n": d.octant_rms.map(finite),
            "velocity_correlation": xyz(&d.velocity_correlation),
            "position_correlation": xyz(&d.position_correlation),
            "acceleration_correlation": xyz(&d.acceleration_correlation),
            "strongest_command_lag_s": strongest(&d.command_lags).0,
            "spectrum_peak_hz": strongest(&d.spectrum).0,
            "whiteness_outside_share": {
                "nominal": d.whiteness.0,
                "augmented": d.whiteness.1,
            },
            "input_correlation_outside_share": {
                "nominal": d.input_correlation.0,
                "augmented": d.input_correlation.1,
            },
        },
        "samples": signals.len(),
        "heldout_from_s": signals.time[signals.split().1.start],
        "wall_time_s": a.wall_time,
    });
    let mut text = serde_json::to_string_pretty(&summary).expect("JSON values serialise");
    text.push('\n');
    write("summary.json", text)?;

    // The augmented model: the grid, and the effect beside it.
    let grid_path = out.join("grid.toml");
    file.save_atomic(&grid_path).map_err(|e| OutError {
        path: grid_path.clone(),
        source: std::io::Error::other(e.to_string()),
    })?;
    let model = ModelFile {
        format: MODEL_FORMAT.into(),
        grid: "grid.toml".into(),
        effect: effect_record(&a.augmented, a.effect(), &up),
        effects: if a.effects.len() > 1 {
            a.effects
                .iter()
                .map(|e| effect_record(&a.augmented, *e, &up))
                .collect()
        } else {
            vec![]
        },
    };
    let model_path = out.join("model.toml");
    model.save(&model_path).map_err(|e| OutError {
        path: model_path.clone(),
        source: std::io::Error::other(e.to_string()),
    })?;

    figures(out, signals, a)?;
    write("report.md", report_md(request, a))?;
    Ok(())
}

fn xyz(v: &Vector3<f64>) -> [f64; 3] {
    [v.x, v.y, v.z]
}

fn finite(v: f64) -> Option<f64> {
    v.is_finite().then_some(v)
}

/// The entry with the largest |value|.
fn strongest(series: &[(f64, f64)]) -> (f64, f64) {
    series
        .iter()
        .copied()
        .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
        .unwrap_or((f64::NAN, f64::NAN))
}

/// Effect `effect` of `fit` as `model.toml` holds it (docs/discrepancy.md §5).
fn effect_record(fit: &Fit, effect: Effect, up: &Vector3<f64>) -> EffectRecord {
    let t = fit.theta_of(effect);
    match effect {
        Effect::None => EffectRecord::None,
        Effect::Payload => EffectRecord::Payload { mass_kg: t[0] },
        Effect::CoulombFriction => EffectRecord::CoulombFriction { force_n: t[0] },
        Effect::ViscousDamping => EffectRecord::ViscousDamping {
            damping_n_s_per_m: t[0],
        },
        Effect::TimeDelay => EffectRecord::TimeDelay { delay_s: fit.delay },
        Effect::GravityTilt => {
            let delta = fit.tilt(up).0;
            let angle = delta.norm();
            let axis = if angle > 0.0 { delta / angle } else { delta };
            EffectRecord::GravityTilt {
                angle_rad: angle,
                rotation_axis: axis.into(),
            }
        }
        Effect::Spring => EffectRecord::Spring {
            stiffness_n_per_m: t[0],
            anchor_m: (-Vector3::new(t[1], t[2], t[3]) / t[0]).into(),
        },
    }
}

/// The figures (SVG and PNG), names without extension.
const FIGURES: [(&str, &str); 6] = [
    (
        "residual_velocity",
        "Nominal residual against velocity (held-out part)",
    ),
    (
        "residual_position",
        "Nominal residual against position (held-out part)",
    ),
    (
        "residual_lagged_command",
        "Correlation of the nominal residual with the lagged command",
    ),
    (
        "residual_spectrum",
        "Amplitude spectrum of the nominal residual",
    ),
    (
        "before_after",
        "Held-out force residual, nominal and augmented model",
    ),
    (
        "unexplained",
        "What is left: the augmented residual against what orders it best",
    ),
];

/// The effects' names, joined for a line of text.
pub fn names(effects: &[Effect]) -> String {
    if effects.is_empty() {
        "none".into()
    } else {
        effects
            .iter()
            .map(|e| e.name())
            .collect::<Vec<_>>()
            .join(", ")
    }
}

fn report_md(request: &AnalyzeRequest, a: &Analysis) -> String {
    let (before, after) = a.errors();
    let mut s = format!(
        "# hgcd analyze\n\nLog `{}` against grid `{}`.\n\n**Effects: {}.** Held-out RMS force \
         residual {:.4} N with the nominal model, {:.4} N with the augmented one ({:+.0} %); \
         the log's noise floor {:.4} N.\n\n",
        request.log.display(),
        request.grid.display(),
        names(&a.effects),
        before,
        after,
        (after / before - 1.0) * 1e2,
        a.noise_floor.force,
    );
    if !a.steps.is_empty() {
        s.push_str("| step | effects | held-out error, N |\n| --- | --- | --- |\n");
        let _ = writeln!(s, "| nominal | none | {before:.4} |");
        for (i, step) in a.steps.iter().enumerate() {
            let _ = writeln!(
                s,
                "| {} | {} | {:.4} |",
                i + 1,
                names(&step.fit.effects),
                step.fit.heldout_error
            );
        }
        s.push('\n');
    }
    if a.unexplained {
        let _ = writeln!(
            s,
            "**Unexplained:** the residual stays {:.1} times the noise floor (above {}): a force \
             in no candidate is there. It is ordered best by {} ({:.0} % of its variance), \
             figure `unexplained`.\n",
            after / a.noise_floor.force,
            evidence::UNEXPLAINED_FACTOR,
            a.ordering.by,
            a.ordering.share * 1e2
        );
    }
    for limit in &a.limits {
        let _ = writeln!(s, "- What the log cannot show: {}", limit.message);
    }
    if !a.limits.is_empty() {
        s.push('\n');
    }
    if let Some((pb, pa)) = a.position_error {
        let _ = writeln!(
            s,
            "Closed-loop simulation of the excitation, held-out RMS position error: {:.3} mm \
             nominal, {:.3} mm augmented.\n",
            pb * 1e3,
            pa * 1e3
        );
    }
    s.push_str("| candidate | parameters | held-out error, N | against nominal |\n");
    s.push_str("| --- | --- | --- | --- |\n");
    for c in &a.candidates {
        let mut p = parameters(c, &a.up);
        if let Some(map) = p.as_object_mut() {
            for key in [
                "moving_mass_kg",
                "joint_inertia_kg_m2",
                "joint_inertia_in_pose",
                "joint_coulomb_friction_n_m",
                "joint_viscous_friction_n_m_s",
                "handle_mass_kg",
            ] {
                map.remove(key);
            }
        }
        let _ = writeln!(
            s,
            "| {} | `{p}` | {:.4} | {:+.0} % |",
            names(&c.effects),
            c.heldout_error,
            (c.heldout_error / before - 1.0) * 1e2
        );
    }
    let d = &a.diagnostics;
    let _ = writeln!(
        s,
        "\nWhere the nominal residual lives: RMS per axis {:.4} / {:.4} / {:.4} N; at speeds \
         below 5 mm/s {:.4} N, 5–30 mm/s {:.4} N, above {:.4} N; strongest correlation with the \
         command at a lag of {:.1} ms; spectrum peak at {:.2} Hz. Autocorrelation outside the \
         white-noise band on {:.0} % of lags (nominal) and {:.0} % (augmented; white noise: \
         about 5 %).\n",
        d.axis_rms.x,
        d.axis_rms.y,
        d.axis_rms.z,
        d.speed_rms[0],
        d.speed_rms[1],
        d.speed_rms[2],
        strongest(&d.command_lags).0 * 1e3,
        strongest(&d.spectrum).0,
        d.whiteness.0 * 1e2,
        d.whiteness.1 * 1e2
    );
    for (name, title) in FIGURES {
        let _ = writeln!(
            s,
            "## {title}\n\n![{title}]({name}.svg) ([PNG]({name}.png))\n"
        );
    }
    s
}

/// One series of a plot.
struct Series {
    label: String,
    colour: RGBColor,
    points: Vec<(f64, f64)>,
    dots: bool,
}

/// A plain x–y plot.
struct Plot {
    title: String,
    x_label: String,
    y_label: String,
    series: Vec<Series>,
}

const AXIS_COLOURS: [RGBColor; 3] = [
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(31, 119, 180),
];

impl Figure for Plot {
    fn plot<DB: DrawingBackend>(
        &self,
        root: &DrawingArea<DB, Shift>,
    ) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
        root.fill(&WHITE)?;
        let all = self.series.iter().flat_map(|s| s.points.iter());
        let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        for &(x, y) in all.filter(|(x, y)| x.is_finite() && y.is_finite()) {
            x0 = x0.min(x);
            x1 = x1.max(x);
            y0 = y0.min(y);
            y1 = y1.max(y);
        }
        if x0 >= x1 {
            (x0, x1) = (x0 - 1.0, x0 + 1.0);
        }
        if y0 >= y1 {
            (y0, y1) = (y0 - 1.0, y0 + 1.0);
        }
        let pad = (y1 - y0) * 0.25;
        let mut chart = ChartBuilder::on(root)
            .caption(&self.title, ("sans-serif", 20))
            .margin(15)
            .x_label_area_size(50)
            .y_label_area_size(70)
            .build_cartesian_2d(x0..x1, (y0 - pad * 0.2)..(y1 + pad))?;
        chart
            .configure_mesh()
            .x_desc(self.x_label.as_str())
            .y_desc(self.y_label.as_str())
            .label_style(("sans-serif", 14))
            .axis_desc_style(("sans-serif", 15))
            .light_line_style(WHITE.mix(0.0))
            .draw()?;
        for s in &self.series {
            let colour = s.colour;
            let series = if s.dots {
                chart.draw_series(
                    s.points
                        .iter()
                        .map(|&(x, y)| Circle::new((x, y), 1, colour.mix(0.5).filled())),
                )?
            } else {
                chart.draw_series(LineSeries::new(s.points.clone(), colour.stroke_width(2)))?
            };
            series.label(s.label.as_str()).legend(move |(x, y)| {
                PathElement::new([(x, y), (x + 20, y)], colour.stroke_width(2))
            });
        }
        figure::legend(&mut chart)
    }
}

/// Every `step`-th held-out sample, for scatter plots.
const SCATTER_STEP: usize = 10;

fn figures(out: &Path, signals: &Signals, a: &Analysis) -> Result<(), AnalyzeError> {
    let (_, heldout) = signals.split();
    let r = a.nominal.residuals(signals);
    let after = a.augmented.residuals(signals);
    let axes = ["x", "y", "z"];
    let scatter = |field: &dyn Fn(usize) -> Vector3<f64>, scale: f64| -> Vec<Series> {
        (0..3)
            .map(|axis| Series {
                label: format!("along {}", axes[axis]),
                colour: AXIS_COLOURS[axis],
                points: heldout
                    .clone()
                    .step_by(SCATTER_STEP)
                    .map(|k| (field(k)[axis] * scale, r[k][axis]))
                    .collect(),
                dots: true,
            })
            .collect()
    };
    let centre = signals
        .samples
        .iter()
        .map(|s| s.position)
        .sum::<Vector3<f64>>()
        / signals.len() as f64;
    let plots = [
        Plot {
            title: FIGURES[0].1.into(),
            x_label: "velocity along the axis, mm/s".into(),
            y_label: "residual F − F_model, N".into(),
            series: scatter(&|k| signals.samples[k].velocity, 1e3),
        },
        Plot {
            title: FIGURES[1].1.into(),
            x_label: "position along the axis, from the log's mean, mm".into(),
            y_label: "residual F − F_model, N".into(),
            series: scatter(&|k| signals.samples[k].position - centre, 1e3),
        },
        Plot {
            title: FIGURES[2].1.into(),
            x_label: "lag of the command, ms".into(),
            y_label: "correlation (mean over axes)".into(),
            series: vec![Series {
                label: "nominal residual".into(),
                colour: AXIS_COLOURS[2],
                points: a
                    .diagnostics
                    .command_lags
                    .iter()
                    .map(|&(l, c)| (l * 1e3, c))
                    .collect(),
                dots: false,
            }],
        },
        Plot {
            title: FIGURES[3].1.into(),
            x_label: "frequency, Hz".into(),
            y_label: "amplitude, N".into(),
            series: vec![Series {
                label: "nominal residual".into(),
                colour: AXIS_COLOURS[2],
                points: a.diagnostics.spectrum.clone(),
                dots: false,
            }],
        },
        Plot {
            title: FIGURES[4].1.into(),
            x_label: "time, s".into(),
            y_label: "|F − F_model|, N".into(),
            series: vec![
                Series {
                    label: format!("nominal: RMS {:.4} N", a.nominal.heldout_error),
                    colour: RGBColor(128, 128, 128),
                    points: heldout
                        .clone()
                        .step_by(SCATTER_STEP)
                        .map(|k| (signals.time[k], r[k].norm()))
                        .collect(),
                    dots: false,
                },
                Series {
                    label: format!(
                        "with {}: RMS {:.4} N",
                        names(&a.effects),
                        a.augmented.heldout_error
                    ),
                    colour: AXIS_COLOURS[0],
                    points: heldout
                        .clone()
                        .step_by(SCATTER_STEP)
                        .map(|k| (signals.time[k], after[k].norm()))
                        .collect(),
                    dots: false,
                },
            ],
        },
        Plot {
            title: FIGURES[5].1.into(),
            x_label: format!("{}, {}", a.ordering.by, a.ordering.unit),
            y_label: "augmented residual, N (amplitude for frequency)".into(),
            // The spectrum is summed over the axes: one series.
            series: (0..if a.ordering.by == "frequency" { 1 } else { 3 })
                .map(|axis| Series {
                    label: if a.ordering.by == "frequency" {
                        "all axes".into()
                    } else {
                        format!("along {}", axes[axis])
                    },
                    colour: AXIS_COLOURS[axis],
                    points: a.ordering.points[axis].clone(),
                    dots: a.ordering.by != "frequency",
                })
                .collect(),
        },
    ];
    for ((name, _), plot) in FIGURES.iter().zip(&plots) {
        figure::draw(
            plot,
            (1000, 600),
            &out.join(format!("{name}.svg")),
            &out.join(format!("{name}.png")),
        )?;
    }
    Ok(())
}
