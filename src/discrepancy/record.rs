//! `hgcd record`: an identification run with compensation on. A PD law tracks a reference inside
//! the calibrated grid and every tick is logged: the measured position, the force the output
//! report carried and the reference (docs/discrepancy.md §1 describes the excitation).

use nalgebra::Vector3;
use std::f64::consts::PI;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use super::log::{Excitation, Log};
use crate::control::compensation::GravityModel;
use crate::control::{ControlOutput, Controller, DeviceState};

/// One excitation cycle, s: a move to a new hold point, a hold, slow then fast multisines around
/// it, a hold.
pub const CYCLE: f64 = 10.0;
const MOVE_END: f64 = 1.0;
const SLOW: (f64, f64) = (2.0, 5.5);
const FAST: (f64, f64) = (5.5, 9.0);
/// Fade-in and fade-out of a multisine segment, s.
const TAPER: f64 = 0.5;
/// Multisine frequencies, Hz (per axis scaled by 1, 1.07, 1.14 so the axes decorrelate).
const SLOW_HZ: [f64; 4] = [0.17, 0.29, 0.43, 0.61];
const FAST_HZ: [f64; 4] = [1.3, 2.3, 3.7, 5.3];
/// Shares of the grid's half-size: hold points, slow and fast multisine amplitudes (together
/// at most 0.9, inside the grid).
const HOLD_SHARE: f64 = 0.45;
const SLOW_SHARE: f64 = 0.3;
const FAST_SHARE: f64 = 0.15;
/// Hold points, as signs of the half-size, one per cycle in turn: the corners of a cube, so the
/// log covers the grid's volume (position-dependent effects show).
const HOLDS: [[f64; 3]; 8] = [
    [-1.0, -1.0, -1.0],
    [1.0, 1.0, -1.0],
    [1.0, -1.0, 1.0],
    [-1.0, 1.0, 1.0],
    [1.0, -1.0, -1.0],
    [-1.0, 1.0, -1.0],
    [-1.0, -1.0, 1.0],
    [1.0, 1.0, 1.0],
];

/// The excitation's parameters, SI.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RecordParams {
    /// Centre and half-size of the box the reference stays in (the grid's), m.
    pub centre: Vector3<f64>,
    pub half: Vector3<f64>,
    /// Device time to record, s.
    pub duration: f64,
    /// The PD law's gains.
    pub excitation: Excitation,
}

impl RecordParams {
    /// Default gains: K = 200 N/m, D = 9 N·s/m (critically damped near 100 g).
    pub const STIFFNESS: f64 = 200.0;
    pub const DAMPING: f64 = 9.0;

    /// Excitation inside the grid of `model`, for `duration` s.
    pub fn inside(model: &GravityModel, duration: f64) -> Self {
        let grid = &model.grid;
        let centre = (grid.origin + grid.far_corner()) / 2.0;
        Self {
            centre,
            half: (grid.far_corner() - grid.origin) / 2.0,
            duration,
            excitation: Excitation {
                stiffness: Self::STIFFNESS,
                damping: Self::DAMPING,
            },
        }
    }
}

/// One logged tick.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Row {
    pub time: f64,
    pub position: Vector3<f64>,
    pub force: Vector3<f64>,
    pub reference: Vector3<f64>,
}

/// The excitation as a controller: F = F_G(X) + K (X_r − X) + D (Ẋ_r − Ẋ). Rows go into a
/// vector with room for the whole run, filled in `after_tick` with the force actually sent.
pub struct Recorder {
    params: RecordParams,
    model: GravityModel,
    /// Device time and position of the first tick.
    start: Option<(f64, Vector3<f64>)>,
    reference: Vector3<f64>,
    /// When `reference` was computed, s into the run (−∞ before the first tick).
    reference_time: f64,
    rows: Vec<Row>,
    /// Device time recorded so far, ms: for a progress display on another thread.
    elapsed_ms: Arc<AtomicU64>,
}

impl Recorder {
    /// `period`: the report period, s (sizes the log).
    pub fn new(params: RecordParams, model: GravityModel, period: f64) -> Self {
        let capacity = (params.duration / period * 1.05) as usize + 1024;
        Self {
            params,
            model,
            start: None,
            reference: Vector3::zeros(),
            reference_time: f64::NEG_INFINITY,
            rows: Vec::with_capacity(capacity),
            elapsed_ms: Arc::new(AtomicU64::new(0)),
        }
    }

    /// Device time recorded so far, ms, readable from any thread.
    pub fn elapsed_ms(&self) -> Arc<AtomicU64> {
        self.elapsed_ms.clone()
    }

    pub fn into_rows(self) -> Vec<Row> {
        self.rows
    }

    /// Hold point of cycle `k`, m.
    fn hold(&self, k: usize) -> Vector3<f64> {
        let s = HOLDS[k % HOLDS.len()];
        self.params.centre + self.params.half.component_mul(&Vector3::from(s)) * HOLD_SHARE
    }

    /// The reference `u` s into the run, from `from` (where the handle started).
    pub fn reference_at(&self, u: f64, from: &Vector3<f64>) -> Vector3<f64> {
        let k = (u / CYCLE).floor().max(0.0) as usize;
        let c = u - k as f64 * CYCLE;
        let hold = self.hold(k);
        if c < MOVE_END {
            let previous = if k == 0 { *from } else { self.hold(k - 1) };
            return previous + (hold - previous) * min_jerk(c / MOVE_END);
        }
        let taper = |(a, b): (f64, f64)| {
            let edge = ((c - a) / TAPER).min((b - c) / TAPER).clamp(0.0, 1.0);
            (edge * PI / 2.0).sin().powi(2)
        };
        let multisine = |hz: &[f64; 4], share: f64| {
            Vector3::from_fn(|a, _| {
                let scale = 1.0 + 0.07 * a as f64;
                let sum: f64 = hz
                    .iter()
                    .enumerate()
                    .map(|(j, f)| {
                        (2.0 * PI * f * scale * u + 1.3 * j as f64 + 2.1 * a as f64).sin()
                    })
                    .sum();
                sum / hz.len() as f64 * share * self.params.half[a]
            })
        };
        hold + multisine(&SLOW_HZ, SLOW_SHARE) * taper(SLOW)
            + multisine(&FAST_HZ, FAST_SHARE) * taper(FAST)
    }
}

fn min_jerk(u: f64) -> f64 {
    let u = u.clamp(0.0, 1.0);
    u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)
}

impl Controller for Recorder {
    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        let (t0, from) = *self.start.get_or_insert((s.time, s.position));
        let u = s.time - t0;
        self.elapsed_ms.store((u * 1e3) as u64, Ordering::Relaxed);
        if u >= self.params.duration {
            return ControlOutput::done(Vector3::zeros());
        }
        // The reference's velocity from the previous tick's (one evaluation per tick; it lags
        // half a period, which the damping term does not feel).
        let previous = (self.reference, self.reference_time);
        self.reference = self.reference_at(u, &from);
        self.reference_time = u;
        let velocity = if u > previous.1 {
            (self.reference - previous.0) / (u - previous.1)
        } else {
            Vector3::zeros()
        };
        let e = &self.params.excitation;
        let force = self.model.force(&s.position)
            + (self.reference - s.position) * e.stiffness
            + (velocity - s.velocity) * e.damping;
        ControlOutput::force(force)
    }

    fn after_tick(&mut self, s: &DeviceState, sent: &Vector3<f64>) {
        if self.rows.len() < self.rows.capacity() {
            self.rows.push(Row {
                time: s.time,
                position: s.position,
                force: *sent,
                reference: self.reference,
            });
        }
    }
}

/// The rows as a [`Log`] of `device` (its grid id).
pub fn log_of(rows: &[Row], device: String, excitation: Excitation) -> Log {
    Log {
        time: rows.iter().map(|r| r.time).collect(),
        position: rows.iter().map(|r| r.position).collect(),
        force: rows.iter().map(|r| r.force).collect(),
        reference: Some(rows.iter().map(|r| r.reference).collect()),
        device: Some(device),
        excitation: Some(excitation),
    }
}
