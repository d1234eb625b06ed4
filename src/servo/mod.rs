//! The servo loop: once per input report, decode → state estimate → controller → safety → encode.
//! Decoding and encoding are the device profile's ([`Codec`]): protocol v1 carries positions and
//! forces, a joint-space device's profile does its kinematics here, on the servo thread.
//!
//! The loop is paced by the device's input reports (as a USB interrupt endpoint paces the host)
//! and guarded by a deadline watchdog. Inside the loop nothing allocates, locks, logs or blocks on
//! anything but the device; events leave through a bounded channel with `try_send`.

pub mod rt;
pub mod safety;
pub mod stats;
pub mod thread;

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crossbeam_channel::Sender;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use thiserror::Error;

use crate::config::{Config, EstimateConfig, SafetyConfig};
use crate::control::{Controller, DeviceState};
use crate::estimate::{Foaw, FoawError};
use crate::profile::Codec;
use crate::protocol::MAX_REPORT_LEN;
use crate::protocol::{DeviceClock, ProtocolError, Status, OUTPUT_REPORT_LEN};
use crate::transport::{Transport, TransportError};
use safety::SafetyLayer;
pub use stats::TimingStats;

/// How the loop runs.
#[derive(Clone, Debug)]
pub struct ServoOptions {
    /// Nominal report period, s.
    pub period: f64,
    /// No report for this long is a fault, s.
    pub watchdog: f64,
    /// Stop after this much time on the transport's clock, s: device time where the device sets
    /// the pace (virtual time, a lock-step socket device), wall-clock time otherwise
    /// ([`Transport::now`]).
    pub duration: Option<f64>,
    /// End the run at a fault (calibration) instead of waiting for the device (daemon): at once
    /// for a fault the device reports, after `silence_limit` for a device that falls silent.
    pub stop_on_fault: bool,
    /// With `stop_on_fault`: how long a silent device may take to report again, s, on the
    /// transport's clock. The watchdog fault zeroes the force at once either way; reports that
    /// resume within this time let the run carry on (a calibration goes on with the vertex it was
    /// on), a longer silence ends it ([`Fault::DeviceSilent`]). 0 ends it at the watchdog fault.
    pub silence_limit: f64,
    pub safety: SafetyConfig,
    pub estimate: EstimateConfig,
    /// Incremented on every loop iteration (reports or timeouts): a supervisor sees the loop is
    /// alive without any lock.
    pub heartbeat: Option<Arc<AtomicU64>>,
}

impl ServoOptions {
    pub fn from_config(config: &Config) -> Self {
        Self {
            period: config.servo_period(),
            watchdog: config.servo.watchdog(),
            duration: None,
            stop_on_fault: false,
            silence_limit: 0.0,
            safety: config.safety.clone(),
            estimate: config.estimate.clone(),
            heartbeat: None,
        }
    }
}

/// Something the loop wants logged; sent with `try_send`, dropped if the channel is full.
#[derive(Clone, Debug, PartialEq)]
pub enum ServoEvent {
    /// No report within the watchdog deadline; force zeroed.
    WatchdogFault {
        silent_for: f64,
    },
    /// Reports are arriving again after a watchdog fault.
    ReportsResumed {
        after: f64,
    },
    /// The device raised its fault flag; force zeroed.
    DeviceFault,
    DeviceFaultCleared,
    /// An input report failed to decode.
    GarbledReport(ProtocolError),
    /// The controller produced a non-finite force; zero was sent.
    NonFiniteForce,
    /// The device clock stepped back (sent once per run; [`TimingStats::clock_jumps_back`]
    /// counts them all).
    ClockJumpedBack,
    /// The loop fell behind and skipped `missed` reports.
    Overrun {
        missed: u16,
    },
    /// Counters, every [`STATS_EVERY`] ticks (for status displays; not logged).
    Stats(StatsSnapshot),
}

/// Ticks between two [`ServoEvent::Stats`].
pub const STATS_EVERY: u64 = 500;

/// The loop's counters at one moment; `status` carries them flattened (`docs/app-protocol.md` §5).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StatsSnapshot {
    pub ticks: u64,
    pub late: u64,
    pub missed: u64,
    pub overruns: u64,
    pub garbled: u64,
    pub watchdog_faults: u64,
    /// Worst tick compute time so far, µs.
    pub worst_compute_us: f64,
    /// Longest interval between two reports so far, µs.
    pub worst_period_us: f64,
    /// Reports received more than one period after they were due.
    #[serde(default)]
    pub late_wakeups: u64,
    /// Largest lateness of a report against its timestamp so far, µs.
    #[serde(default)]
    pub worst_lateness_us: f64,
}

impl TimingStats {
    pub fn snapshot(&self) -> StatsSnapshot {
        StatsSnapshot {
            ticks: self.ticks,
            late: self.late,
            missed: self.missed,
            overruns: self.overruns,
            garbled: self.garbled,
            watchdog_faults: self.watchdog_faults,
            worst_compute_us: self.compute.max_us(),
            worst_period_us: self.period.max_us(),
            late_wakeups: self.late_wakeups,
            worst_lateness_us: self.lateness.max_us(),
        }
    }
}

/// Why the loop ended.
#[derive(Clone, Debug, PartialEq)]
pub enum ExitReason {
    /// The stop flag was set (Ctrl-C, SIGTERM, shutdown request).
    Stopped,
    /// The requested duration elapsed.
    DurationReached,
    /// The controller said it was done.
    ControllerDone,
    /// A fault ended the run (`stop_on_fault`, or a device clock that runs backwards).
    Fault(Fault),
}

/// A fault that ends a run: the first two with `stop_on_fault`, the last always.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Error)]
pub enum Fault {
    #[error("device reported a fault")]
    DeviceReported,
    #[error("device stopped reporting")]
    DeviceSilent,
    #[error(
        "the device clock ran backwards for {CLOCK_BACKWARDS_LIMIT} reports in a row: \
         its reports cannot be timed"
    )]
    ClockBackwards,
}

/// Consecutive reports whose device clock steps back before the run ends
/// ([`Fault::ClockBackwards`]); a device reset steps back once.
pub const CLOCK_BACKWARDS_LIMIT: u32 = 100;

/// What a finished run reports.
#[derive(Clone, Debug)]
pub struct ServoReport {
    pub exit: ExitReason,
    pub stats: TimingStats,
    pub last_state: Option<DeviceState>,
}

#[derive(Debug, Error)]
pub enum ServoError {
    #[error(transparent)]
    Transport(#[from] TransportError),
    #[error("velocity estimator: {0}")]
    Estimator(#[from] FoawError),
}

fn emit(events: Option<&Sender<ServoEvent>>, event: ServoEvent) {
    if let Some(tx) = events {
        let _ = tx.try_send(event);
    }
}

/// What one tick decided.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum TickOutcome {
    /// An output report is ready in [`ServoCore::output`].
    Continue,
    /// The controller is done; the output report is ready.
    Done,
    /// A fault that ends the run (a device fault with `stop_on_fault`, a clock that runs
    /// backwards); zero force is ready.
    Fault(Fault),
}

/// The hot path of one tick, without I/O: decode → state estimate → controller → safety → encode.
/// Everything it needs is allocated when it is built.
pub struct ServoCore {
    /// The device profile's side of the wire.
    codec: Codec,
    foaw: Foaw,
    safety: SafetyLayer,
    clock: DeviceClock,
    /// Reports in a row whose clock stepped back.
    clock_backwards: u32,
    last_sequence: Option<u16>,
    last_report_at: f64,
    device_fault: bool,
    stop_on_fault: bool,
    out_sequence: u16,
    output: [u8; OUTPUT_REPORT_LEN],
    /// Length of the report in `output`.
    output_len: usize,
    /// Restart the velocity filter at the next report (after a silence or missed reports).
    resync: bool,
    pub stats: TimingStats,
    pub last_state: Option<DeviceState>,
}

impl ServoCore {
    /// A core for `options` and a protocol v1 device ([`ServoCore::speaking`] for another), with
    /// everything the loop needs allocated.
    ///
    /// # Errors
    /// [`FoawError`] for estimator parameters out of range.
    pub fn new(options: &ServoOptions) -> Result<Self, FoawError> {
        let est = &options.estimate;
        Ok(Self {
            codec: Codec::Cartesian,
            foaw: Foaw::new(
                est.foaw_variant,
                est.noise_bound(),
                est.max_window,
                options.period,
            )?,
            safety: SafetyLayer::new(&options.safety, options.period),
            clock: DeviceClock::default(),
            clock_backwards: 0,
            last_sequence: None,
            last_report_at: 0.0,
            device_fault: false,
            stop_on_fault: options.stop_on_fault,
            out_sequence: 0,
            output: [0; OUTPUT_REPORT_LEN],
            output_len: OUTPUT_REPORT_LEN,
            resync: false,
            stats: TimingStats::new(options.period),
            last_state: None,
        })
    }

    /// This core speaking `codec`, the device profile's ([`crate::transport::Transport::codec`]).
    pub fn speaking(mut self, codec: Codec) -> Self {
        self.codec = codec;
        self
    }

    /// The output report the last call prepared.
    pub fn output(&self) -> &[u8] {
        &self.output[..self.output_len]
    }

    /// Prepare a zero-force report (faults) and forget the last force.
    pub fn prepare_zero(&mut self) -> &[u8] {
        self.safety.reset();
        self.encode(&Vector3::zeros(), true);
        self.output()
    }

    /// Prepare the last report of a run: zero force, motors disabled.
    pub fn prepare_shutdown(&mut self) -> &[u8] {
        self.safety.reset();
        self.encode(&Vector3::zeros(), false);
        self.output()
    }

    fn encode(&mut self, force: &Vector3<f64>, enable: bool) {
        // The safety layer keeps forces finite and far inside the protocol's range.
        self.output_len = self
            .codec
            .encode(self.out_sequence, force, enable, &mut self.output);
        self.out_sequence = self.out_sequence.wrapping_add(1);
    }

    /// The device went silent and is back: the velocity filter restarts at the next report.
    pub fn resume_after_silence(&mut self) {
        self.resync = true;
        // The device may have reset meanwhile: its clock and the host's are compared afresh.
        self.stats.restart_lateness();
    }

    /// Handle one input report that arrived at `arrived` (transport clock, s).
    ///
    /// # Errors
    /// The [`ProtocolError`] of a report that does not decode.
    pub fn tick(
        &mut self,
        bytes: &[u8],
        arrived: f64,
        controller: &mut dyn Controller,
        events: Option<&Sender<ServoEvent>>,
    ) -> Result<TickOutcome, ProtocolError> {
        let report = self.codec.decode(bytes)?;
        if let Some(prev) = self.last_sequence {
            self.stats.record_period(arrived - self.last_report_at);
            let gap = report.sequence.wrapping_sub(prev).wrapping_sub(1);
            if gap != 0 && gap < u16::MAX / 2 {
                self.stats.missed += u64::from(gap);
                self.stats.overruns += 1;
                emit(events, ServoEvent::Overrun { missed: gap });
                // FOAW assumes evenly spaced samples: across a gap it would see a false jump.
                self.resync = true;
            }
        }
        self.last_sequence = Some(report.sequence);
        self.last_report_at = arrived;

        let faulted = report.status.contains(Status::FAULT);
        if faulted != self.device_fault {
            self.device_fault = faulted;
            let event = if faulted {
                ServoEvent::DeviceFault
            } else {
                // What the device reported during the fault may not continue into what it
                // reports now (a joint-space device's counters homed): the filter restarts.
                self.resync = true;
                ServoEvent::DeviceFaultCleared
            };
            emit(events, event);
        }
        if faulted {
            self.stats.device_fault_ticks += 1;
            if self.stop_on_fault {
                self.prepare_zero();
                return Ok(TickOutcome::Fault(Fault::DeviceReported));
            }
        }

        if self.resync {
            self.foaw.reset();
            self.resync = false;
        }
        // A device without a clock is timed by the host's: its reports are never late.
        let time = match report.timestamp_us {
            Some(raw) => {
                let (time, jumped_back) = self.clock.seconds(raw);
                if jumped_back {
                    // A device reset: the time it lost is not lateness. A clock that keeps
                    // running backwards cannot time anything: the run ends.
                    self.stats.restart_lateness();
                    self.stats.clock_jumps_back += 1;
                    if self.stats.clock_jumps_back == 1 {
                        emit(events, ServoEvent::ClockJumpedBack);
                    }
                    self.clock_backwards += 1;
                    if self.clock_backwards >= CLOCK_BACKWARDS_LIMIT {
                        self.prepare_zero();
                        return Ok(TickOutcome::Fault(Fault::ClockBackwards));
                    }
                } else {
                    self.clock_backwards = 0;
                }
                self.stats.record_lateness(arrived, time);
                time
            }
            None => arrived,
        };
        let state = DeviceState {
            time,
            host_time: arrived,
            position: report.position,
            velocity: self.foaw.update(&report.position),
            status: report.status,
            tick: self.stats.ticks,
        };
        controller.before_tick(&state);
        let output = controller.tick(&state);
        let (force, limited) = self.safety.limit(&output.force, faulted);
        if limited.non_finite {
            self.stats.non_finite_forces += 1;
            emit(events, ServoEvent::NonFiniteForce);
        }
        self.encode(&force, true);
        controller.after_tick(&state, &force);
        self.stats.ticks += 1;
        self.last_state = Some(state);
        Ok(if output.done {
            TickOutcome::Done
        } else {
            TickOutcome::Continue
        })
    }
}

/// Run the loop on the calling thread until `stop` is set, the duration elapses, the controller is
/// done, or (with `stop_on_fault`) a fault occurs. Always ends by writing a zero-force report
/// with motors disabled, even when the controller panics (the panic then continues).
///
/// # Errors
/// [`ServoError::Estimator`] for estimator parameters out of range, [`ServoError::Transport`] when
/// the device cannot be read or written.
pub fn run(
    transport: &mut dyn Transport,
    controller: &mut dyn Controller,
    options: &ServoOptions,
    stop: &AtomicBool,
    events: Option<&Sender<ServoEvent>>,
) -> Result<ServoReport, ServoError> {
    let mut core = ServoCore::new(options)?.speaking(transport.codec());
    core.stats.clock_drift = transport.clock_drift();
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        run_loop(
            &mut *transport,
            controller,
            options,
            stop,
            events,
            &mut core,
        )
    }));
    // Whatever happened, the last thing the device hears is zero force with motors disabled.
    let zeroed = transport.write_output(core.prepare_shutdown());
    let exit = match result {
        Ok(exit) => exit?,
        Err(panic) => std::panic::resume_unwind(panic),
    };
    zeroed?;
    Ok(ServoReport {
        exit,
        stats: core.stats,
        last_state: core.last_state,
    })
}

fn run_loop(
    transport: &mut dyn Transport,
    controller: &mut dyn Controller,
    options: &ServoOptions,
    stop: &AtomicBool,
    events: Option<&Sender<ServoEvent>>,
    core: &mut ServoCore,
) -> Result<ExitReason, TransportError> {
    let mut buf = [0u8; MAX_REPORT_LEN];
    let start = transport.now();
    // Time of the last *valid* report: garbage does not count as the device being alive.
    let mut last_report_at = start;
    let mut silent = false;
    loop {
        if let Some(beat) = &options.heartbeat {
            beat.fetch_add(1, Ordering::Relaxed);
        }
        if stop.load(Ordering::Relaxed) {
            return Ok(ExitReason::Stopped);
        }
        let now = transport.now();
        if options.duration.is_some_and(|d| now - start >= d) {
            return Ok(ExitReason::DurationReached);
        }
        let wait = if silent {
            options.watchdog
        } else {
            (last_report_at + options.watchdog - now).max(0.0)
        };
        let read = transport.read_input(&mut buf, Duration::from_secs_f64(wait))?;
        core.stats.garbled += transport.take_garbled_skipped();
        if let Some(n) = read {
            let received = Instant::now();
            let arrived = transport.now();
            if silent {
                core.resume_after_silence();
            }
            match core.tick(&buf[..n.min(MAX_REPORT_LEN)], arrived, controller, events) {
                Ok(outcome) => {
                    if silent {
                        silent = false;
                        emit(
                            events,
                            ServoEvent::ReportsResumed {
                                after: arrived - last_report_at,
                            },
                        );
                    }
                    last_report_at = arrived;
                    transport.write_output(core.output())?;
                    core.stats
                        .compute
                        .record_ns(received.elapsed().as_nanos() as u64);
                    if core.stats.ticks % STATS_EVERY == 0 {
                        emit(events, ServoEvent::Stats(core.stats.snapshot()));
                    }
                    match outcome {
                        TickOutcome::Continue => continue,
                        TickOutcome::Done => return Ok(ExitReason::ControllerDone),
                        TickOutcome::Fault(fault) => return Ok(ExitReason::Fault(fault)),
                    }
                }
                Err(e) => {
                    core.stats.garbled += 1;
                    emit(events, ServoEvent::GarbledReport(e));
                }
            }
        }
        // No valid report: a device that is silent, or only babbles, for too long is a fault.
        let silent_for = transport.now() - last_report_at;
        if !silent && silent_for >= options.watchdog {
            silent = true;
            core.stats.watchdog_faults += 1;
            emit(events, ServoEvent::WatchdogFault { silent_for });
            transport.write_output(core.prepare_zero())?;
        }
        if silent && options.stop_on_fault && silent_for >= options.silence_limit {
            return Ok(ExitReason::Fault(Fault::DeviceSilent));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::{InputReport, OutputReport};

    /// Asks for a large force and remembers what `after_tick` says was sent.
    struct Pushy {
        sent: Vec<Vector3<f64>>,
    }

    impl Controller for Pushy {
        fn tick(&mut self, _: &DeviceState) -> crate::control::ControlOutput {
            crate::control::ControlOutput::force(Vector3::new(20.0, 0.0, 0.0))
        }
        fn after_tick(&mut self, _: &DeviceState, sent: &Vector3<f64>) {
            self.sent.push(*sent);
        }
    }

    fn report(sequence: u16, status: Status) -> [u8; crate::protocol::INPUT_REPORT_LEN] {
        let mut out = [0; crate::protocol::INPUT_REPORT_LEN];
        InputReport {
            sequence,
            timestamp_us: u32::from(sequence) * 1000,
            position: Vector3::zeros(),
            status,
        }
        .encode(&mut out)
        .unwrap();
        out
    }

    #[test]
    fn after_tick_sees_the_force_the_output_report_carries() {
        let options = ServoOptions::from_config(&Config::default());
        let mut core = ServoCore::new(&options).unwrap();
        let mut c = Pushy { sent: Vec::new() };
        for k in 0..100u16 {
            core.tick(
                &report(k, Status::default()),
                f64::from(k) * 1e-3,
                &mut c,
                None,
            )
            .unwrap();
            let carried = OutputReport::decode(core.output()).unwrap().force;
            assert!((carried - c.sent[usize::from(k)]).norm() < 1e-6);
        }
        // Rate-limited to 4 N/ms, then clamped to 8 N: never the 20 N asked for.
        assert!((c.sent[0].x - 4.0).abs() < 1e-9);
        assert!((c.sent[99].x - 8.0).abs() < 1e-9);
        // During a device fault the report carries zero, and so does what is published.
        let fault = Status::default().with(Status::FAULT, true);
        core.tick(&report(100, fault), 0.1, &mut c, None).unwrap();
        assert_eq!(c.sent[100], Vector3::zeros());
    }
}
