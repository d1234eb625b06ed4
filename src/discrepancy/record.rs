//! `hgcd record`: an identification run with compensation on. A PD law tracks a reference inside
//! the calibrated grid and every tick is logged: the measured position, the force the output
//! report carried and the reference (docs/discrepancy.md §1 describes the excitation).

use nalgebra::Vector3;
use std::f64::consts::PI;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use super::log::{Excitation, Log};
use crate::control::compensation::GravityModel;
use crate::control::{minimum_jerk, ControlOutput, Controller, DeviceState};

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

/// The excitation's loop has gone unstable when the safety layer changed the command (clamped
/// its magnitude or its rate) on this share of a [`LIMIT_WINDOW`]: a healthy run stays far
/// from the limits (a clean log of the simulated PHANToM peaks at 0.75 N of the 8 N), and a loop
/// that rings into them is limited on 15 % of the window at a loop delay of 10 ms there, 44 % at 20.
const UNSTABLE_SHARE: f64 = 0.1;
/// Device time over which the limited ticks are counted, s.
pub const LIMIT_WINDOW: f64 = 0.5;
/// How many times the excitation softens; unstable once more, it stops the run (zero force).
pub const MAX_SOFTENINGS: usize = 3;
/// After it softens, the excitation holds the handle where its reference was for this long,
/// s, so the run starts again from rest (and the ringing the old gains left is not taken for
/// the new gains' own).
const SETTLE: f64 = 1.0;

/// The excitation softened once: its loop went unstable `at` s after the run (last) started,
/// under `from`, the safety layer having changed the command on `limited_share` of the last
/// [`LIMIT_WINDOW`]; the run started again under `to`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Softening {
    pub at: f64,
    pub limited_share: f64,
    pub from: Excitation,
    pub to: Excitation,
}

/// The gains after softening `e` for the `n`th time (from 1): the damping halves first, then
/// the stiffness falls to a quarter, then the damping halves again. On a light handle the PD's
/// crossover is about D / m, and a loop delay τ leaves it a phase margin of about π/2 − D τ / m
/// (radians); but the delayed spring also damps negatively by about K τ, which D must outweigh.
/// So a moderate delay needs less damping (on the simulated PHANToM, 10 ms of loop delay: D from
/// 9 to 4.5 N·s/m), a longer one a softer spring too (12 ms: K = 200 N/m, D = 4.5 N·s/m still rang
/// into the limit).
/// The stiffness goes last: a softer spring lets joint friction stick the handle (K = 100 N/m
/// left a clean PHANToM log 15 % more residual than 200 N/m).
pub fn softer(e: &Excitation, n: usize) -> Excitation {
    if n % 2 == 0 {
        Excitation {
            stiffness: e.stiffness / 4.0,
            damping: e.damping,
        }
    } else {
        Excitation {
            stiffness: e.stiffness,
            damping: e.damping / 2.0,
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
    /// The force this tick asked for, before the safety layer.
    asked: Vector3<f64>,
    /// The current [`LIMIT_WINDOW`]: when it began (s into the run), its ticks and those the
    /// safety layer changed.
    window: (f64, u32, u32),
    softenings: [Option<Softening>; MAX_SOFTENINGS],
    /// After softening: until when (device time, s) the handle is held, and where.
    settling: Option<(f64, Vector3<f64>)>,
    /// Unstable at the softest gains, the share of limited commands that said so: the run ends.
    unstable: Option<f64>,
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
            asked: Vector3::zeros(),
            window: (0.0, 0, 0),
            softenings: [None; MAX_SOFTENINGS],
            settling: None,
            unstable: None,
        }
    }

    /// The gains the log was recorded with (the last, if the excitation softened).
    pub fn excitation(&self) -> Excitation {
        self.params.excitation
    }

    /// Each time the excitation softened and started again ([`Softening`]), in order.
    pub fn softenings(&self) -> impl Iterator<Item = &Softening> {
        self.softenings.iter().flatten()
    }

    /// Whether the loop was still unstable after [`MAX_SOFTENINGS`] (the share of the last
    /// window's commands the safety layer limited): the run stopped there, and its rows are not
    /// a log of the excitation.
    pub fn unstable(&self) -> Option<f64> {
        self.unstable
    }

    /// Count tick `u` s into the run (device time `now`), `limited` if the safety layer changed
    /// its command; at the end of a window whose share of limited ticks says the loop is
    /// unstable, soften the excitation, hold the handle for [`SETTLE`] and start the run again
    /// (allocation-free: the rows keep their room).
    fn watch_the_limits(&mut self, u: f64, now: f64, limited: bool) {
        let (since, ticks, changed) = &mut self.window;
        *ticks += 1;
        *changed += u32::from(limited);
        if u - *since < LIMIT_WINDOW {
            return;
        }
        let share = f64::from(*changed) / f64::from(*ticks);
        self.window = (u, 0, 0);
        if share < UNSTABLE_SHARE {
            return;
        }
        let Some(n) = self.softenings.iter().position(Option::is_none) else {
            self.unstable = Some(share);
            return;
        };
        let from = self.params.excitation;
        self.params.excitation = softer(&from, n + 1);
        self.softenings[n] = Some(Softening {
            at: u,
            limited_share: share,
            from,
            to: self.params.excitation,
        });
        self.settling = Some((now + SETTLE, self.reference));
        self.start = None;
        self.reference_time = f64::NEG_INFINITY;
        self.window = (0.0, 0, 0);
        self.rows.clear();
    }

    /// The excitation's law at `s`, tracking `reference` moving at `velocity`:
    /// F = F_G(X) + K (X_r − X) + D (Ẋ_r − Ẋ).
    fn pd(
        &self,
        s: &DeviceState,
        reference: &Vector3<f64>,
        velocity: &Vector3<f64>,
    ) -> Vector3<f64> {
        let e = &self.params.excitation;
        self.model.force(&s.position)
            + (reference - s.position) * e.stiffness
            + (velocity - s.velocity) * e.damping
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
            return previous + (hold - previous) * minimum_jerk(c / MOVE_END).0;
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

impl Controller for Recorder {
    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        if self.unstable.is_some() {
            self.asked = Vector3::zeros();
            return ControlOutput::done(self.asked);
        }
        if let Some((until, point)) = self.settling {
            if s.time < until {
                self.asked = self.pd(s, &point, &Vector3::zeros());
                return ControlOutput::force(self.asked);
            }
            self.settling = None;
        }
        let (t0, from) = *self.start.get_or_insert((s.time, s.position));
        let u = s.time - t0;
        self.elapsed_ms.store((u * 1e3) as u64, Ordering::Relaxed);
        if u >= self.params.duration {
            // The run's last tick: zero force, asked for (not a limit the loop ran into).
            self.asked = Vector3::zeros();
            return ControlOutput::done(self.asked);
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
        self.asked = self.pd(s, &self.reference, &velocity);
        ControlOutput::force(self.asked)
    }

    fn after_tick(&mut self, s: &DeviceState, sent: &Vector3<f64>) {
        let Some((t0, _)) = self.start else {
            return;
        };
        let limited = (sent - self.asked).norm() > 1e-9 * (1.0 + self.asked.norm());
        self.watch_the_limits(s.time - t0, s.time, limited);
        if self.start.is_none() {
            return;
        }
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
