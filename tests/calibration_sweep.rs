//! Calibration that always finishes (issue 35): the paper's 27-vertex cube on every simulated
//! device, units 1–3, Coulomb friction 0.02, 0.04 and 0.08 N at the handle, 20 noise seeds each.
//! Every run must calibrate at the first try with every vertex within 0.5 % of the plant's own
//! holding force (|F − F_plant| / |F_plant|, the whole vector). Judged against the plant, in
//! virtual time. About 10 minutes on two cores; docs/calibration.md §7.1 has its summary. Run with
//!
//! ```text
//! cargo test --release --test calibration_sweep -- --ignored --nocapture
//! ```
//!
//! and narrow it with `SWEEP_DEVICES=phantom,delta`, `SWEEP_FRICTION=0.04`, `SWEEP_UNITS=1,2`,
//! `SWEEP_SEEDS=5` (seeds 1 to 5) or `SWEEP_SEED=8` (seed 8 alone); `SWEEP_VERBOSE=1` prints
//! every vertex's error.

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Mutex;

use hgcd::config::{Config, HoldPlan};
use hgcd::control::calibration::{Calibration, CalibrationParams};
use hgcd::servo::{self, ServoOptions};
use hgcd::sim::SimDevice;
use hgcd::transport::sim::SimTransport;
use hgcd::transport::Pacing;

mod common;
use common::env_list;

/// One calibration of the sweep.
#[derive(Clone, Debug)]
struct Case {
    model: &'static str,
    unit: u64,
    friction: f64,
    seed: u64,
}

impl Case {
    fn config(&self) -> Config {
        let mut config = if self.model == "woodenhaptics" {
            // The shipped validation config names the arm's profile and encoder bound.
            let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("config/validate-woodenhaptics-unit-2.toml");
            Config::load(&path).unwrap()
        } else {
            Config::default()
        };
        config.sim.unit_seed = self.unit;
        config.sim.seed = self.seed;
        config.sim.coulomb_friction_n = self.friction;
        // The paper's cube, every vertex held, as `hgcd calibrate` holds it with this setting
        // (the strokes along the profile's arm where there is one).
        config.calibration.holds = HoldPlan::All;
        config
    }
}

/// What one run gave: the worst vertex's relative error and the device time, or the failure.
type Outcome = Result<(f64, f64), String>;

fn calibrate(case: &Case) -> Outcome {
    let config = case.config();
    let device = SimDevice::from_config(case.model, &config).map_err(|e| e.to_string())?;
    let spec = format!("sim:{}", case.model).parse().unwrap();
    let mut calibration = Calibration::new(CalibrationParams::for_device(&config, &spec), None)
        .map_err(|e| e.to_string())?;
    let mut transport = SimTransport::new(device, Pacing::Virtual);
    let mut options = ServoOptions::from_config(&config);
    options.stop_on_fault = true;
    servo::run(
        &mut transport,
        &mut calibration,
        &options,
        &AtomicBool::new(false),
        None,
    )
    .map_err(|e| e.to_string())?;
    let result = match calibration.outcome() {
        Some(Ok(result)) => result,
        Some(Err(failure)) => return Err(failure.to_string()),
        None => return Err("did not finish".into()),
    };
    if !result.unreachable.is_empty() {
        return Err(format!("{} vertices unreachable", result.unreachable.len()));
    }
    let mut worst: f64 = 0.0;
    for v in &result.vertices {
        let mut at = config.clone();
        at.sim.start_position_mm = (v.vertex.position * 1e3).into();
        let truth = SimDevice::from_config(case.model, &at)
            .unwrap()
            .plant()
            .holding_force();
        worst = worst.max((v.force - truth).norm() / truth.norm());
        if std::env::var("SWEEP_VERBOSE").is_ok() {
            let e = (v.force - truth) * 1e3;
            let off = (v.measured_at - v.vertex.position) * 1e3;
            println!(
                "  {}: error ({:.1}, {:.1}, {:.1}) mN of {:.1} mN; measured {:.2} mm off ({:.2}, {:.2}, {:.2})",
                v.vertex, e.x, e.y, e.z, truth.norm() * 1e3, off.norm(), off.x, off.y, off.z
            );
        }
    }
    Ok((worst, result.duration))
}

/// The runs the sweep once found over 0.5 %, all on the delta at 0.02 N at the handle, at its
/// bottom corners (40, ±40, −40) mm: the joints' friction (0.24 N at the handle there) held the
/// handle 0.6 mm apart on the stroke's two passes, and their mean kept what J⁻ᵀ changes over
/// that distance (docs/calibration.md §4.6). Unit 1, seed 14 read 0.514 %; now about 0.2 %.
#[test]
fn the_deltas_bottom_corners_read_within_half_a_percent() {
    let case = Case {
        model: "delta",
        unit: 1,
        friction: 0.02,
        seed: 14,
    };
    let (worst, _) = calibrate(&case).unwrap();
    assert!(
        worst < 0.005,
        "{case:?}: worst vertex {:.3} %",
        worst * 100.0
    );
}

#[test]
#[ignore]
fn every_device_unit_friction_and_seed_calibrates_first_time_within_half_a_percent() {
    let models: Vec<String> = env_list(
        "SWEEP_DEVICES",
        &["point-mass", "phantom", "delta", "woodenhaptics"].map(String::from),
    );
    let units: Vec<u64> = env_list("SWEEP_UNITS", &[1, 2, 3]);
    let frictions: Vec<f64> = env_list("SWEEP_FRICTION", &[0.02, 0.04, 0.08]);
    let seeds: u64 = env_list("SWEEP_SEEDS", &[20])[0];
    let seeds: Vec<u64> = env_list("SWEEP_SEED", &(1..=seeds).collect::<Vec<_>>());
    let mut cases = Vec::new();
    for model in &models {
        let model: &'static str = Box::leak(model.clone().into_boxed_str());
        // The point mass has no unit variation: one unit stands for all.
        let units = if model == "point-mass" {
            &units[..1]
        } else {
            &units[..]
        };
        for &unit in units {
            for &friction in &frictions {
                for &seed in &seeds {
                    cases.push(Case {
                        model,
                        unit,
                        friction,
                        seed,
                    });
                }
            }
        }
    }
    let next = AtomicUsize::new(0);
    let outcomes = Mutex::new(vec![None; cases.len()]);
    std::thread::scope(|scope| {
        for _ in 0..2 {
            scope.spawn(|| loop {
                let n = next.fetch_add(1, Ordering::Relaxed);
                let Some(case) = cases.get(n) else { break };
                let outcome = calibrate(case);
                match &outcome {
                    Ok((worst, time)) => println!(
                        "{case:?}: worst {:.3} %, {time:.1} s device time",
                        100.0 * worst
                    ),
                    Err(e) => println!("{case:?}: FAILED {e}"),
                }
                outcomes.lock().unwrap()[n] = Some(outcome);
            });
        }
    });
    let outcomes: Vec<Outcome> = outcomes
        .into_inner()
        .unwrap()
        .into_iter()
        .flatten()
        .collect();
    let mut bad = Vec::new();
    println!("\ndevice         friction N  runs  failed  worst %  median s  max s");
    for model in &models {
        for &friction in &frictions {
            let runs: Vec<(&Case, &Outcome)> = cases
                .iter()
                .zip(&outcomes)
                .filter(|(c, _)| c.model == model && c.friction == friction)
                .collect();
            let failed = runs.iter().filter(|(_, o)| o.is_err()).count();
            let worst = runs
                .iter()
                .filter_map(|(_, o)| o.as_ref().ok())
                .map(|o| o.0)
                .fold(0.0, f64::max);
            let mut times: Vec<f64> = runs
                .iter()
                .filter_map(|(_, o)| o.as_ref().ok())
                .map(|o| o.1)
                .collect();
            times.sort_by(f64::total_cmp);
            let median = times.get(times.len() / 2).copied().unwrap_or(f64::NAN);
            let max = times.last().copied().unwrap_or(f64::NAN);
            println!(
                "{model:<14} {friction:>10.2}  {:>4}  {failed:>6}  {:>7.3}  {median:>8.1}  {max:>5.1}",
                runs.len(),
                100.0 * worst
            );
            for (case, outcome) in runs {
                match outcome {
                    Err(e) => bad.push(format!("{case:?}: {e}")),
                    Ok((worst, _)) if *worst > 0.005 => {
                        bad.push(format!("{case:?}: {:.3} %", 100.0 * worst))
                    }
                    Ok(_) => {}
                }
            }
        }
    }
    assert!(
        bad.is_empty(),
        "{} runs out of bounds:\n{}",
        bad.len(),
        bad.join("\n")
    );
}
