//! The calibration's controller on the servo thread: how long each of its ticks takes, over a
//! whole default calibration of `sim:phantom` and `sim:delta` (their profiles' arm models, so the
//! running arm fit of `fit::predict` runs as each hold comes in) with 0.04 N of friction at the
//! handle, and of `sim:point-mass`.
//!
//! `cargo bench --bench calibration_tick`. A tick is timed around `Controller::tick` alone (the
//! simulated device and the servo core are not in it); the distribution over the run's ticks is
//! printed: median, 99th and 99.9th percentiles, the longest, and how many took longer than
//! 100 µs (a tenth of the 1 kHz period). The calibration's state machine changes phase as the
//! device answers, so its ticks cannot be replayed one at a time under criterion: the whole run is
//! the sample. docs/performance.md has the numbers.

use std::sync::atomic::AtomicBool;
use std::time::Instant;

use hgcd::config::Config;
use hgcd::control::calibration::{Calibration, CalibrationParams};
use hgcd::control::{ControlOutput, Controller, DeviceState};
use hgcd::servo::{self, ServoOptions};
use hgcd::sim::SimDevice;
use hgcd::transport::sim::SimTransport;
use hgcd::transport::Pacing;

/// Times each tick of the controller it wraps, ns, into storage reserved before the run.
struct Timed<'a> {
    inner: &'a mut Calibration,
    ticks: Vec<u32>,
}

impl Controller for Timed<'_> {
    fn before_tick(&mut self, state: &DeviceState) {
        self.inner.before_tick(state);
    }

    fn tick(&mut self, state: &DeviceState) -> ControlOutput {
        let start = Instant::now();
        let output = self.inner.tick(state);
        let ns = start.elapsed().as_nanos().min(u128::from(u32::MAX)) as u32;
        if self.ticks.len() < self.ticks.capacity() {
            self.ticks.push(ns);
        }
        output
    }

    fn after_tick(&mut self, state: &DeviceState, sent: &nalgebra::Vector3<f64>) {
        self.inner.after_tick(state, sent);
    }
}

fn main() {
    // `cargo bench` passes `--bench`; a filter, if any, picks the devices by name.
    let filter: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    println!("| device | ticks | median | p99 | p99.9 | longest | over 100 µs |");
    println!("| --- | --- | --- | --- | --- | --- | --- |");
    for (model, friction) in [("point-mass", 0.0), ("phantom", 0.04), ("delta", 0.04)] {
        if !filter.is_empty() && !filter.iter().any(|f| model.contains(f.as_str())) {
            continue;
        }
        let mut config = Config::default();
        config.sim.coulomb_friction_n = friction;
        let device = SimDevice::from_config(model, &config).expect("a simulated device");
        let spec = format!("sim:{model}").parse().expect("a device spec");
        let mut calibration = Calibration::new(CalibrationParams::for_device(&config, &spec), None)
            .expect("the default plan");
        let mut timed = Timed {
            inner: &mut calibration,
            ticks: Vec::with_capacity(2_000_000),
        };
        let mut transport = SimTransport::new(device, Pacing::Virtual);
        let mut options = ServoOptions::from_config(&config);
        options.stop_on_fault = true;
        servo::run(
            &mut transport,
            &mut timed,
            &options,
            &AtomicBool::new(false),
            None,
        )
        .expect("the calibration runs");
        let mut ticks = std::mem::take(&mut timed.ticks);
        assert!(
            matches!(calibration.outcome(), Some(Ok(_))),
            "{model}: the calibration did not finish"
        );
        ticks.sort_unstable();
        let at = |p: f64| f64::from(ticks[((ticks.len() - 1) as f64 * p).round() as usize]);
        let over = ticks.iter().filter(|&&ns| ns > 100_000).count();
        println!(
            "| `sim:{model}`{} | {} | {:.2} µs | {:.2} µs | {:.1} µs | {:.1} µs | {over} |",
            if friction > 0.0 { ", 0.04 N" } else { "" },
            ticks.len(),
            at(0.5) / 1e3,
            at(0.99) / 1e3,
            at(0.999) / 1e3,
            at(1.0) / 1e3,
        );
    }
}
