//! Running the loop on a dedicated real-time thread, with its events logged on another.

use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender, TryRecvError};
use tracing::{error, info, warn};

use super::{rt, run, ServoError, ServoEvent, ServoOptions, ServoReport, CLOCK_BACKWARDS_LIMIT};
use crate::config::ServoConfig;
use crate::control::Controller;
use crate::transport::Transport;

/// One line per this much time, at most, for a kind of event that can repeat every tick.
pub const SUMMARY_EVERY: Duration = Duration::from_secs(10);

/// Counts of one repeating kind of event since its last log line.
#[derive(Debug, Default)]
struct Repeats {
    total: u64,
    pending: u64,
    /// Reports skipped (overruns only).
    pending_missed: u64,
    last_line: Option<Instant>,
}

impl Repeats {
    /// Count one event; true when a line is due (the first one, or a summary after
    /// [`SUMMARY_EVERY`]).
    fn count(&mut self, missed: u64, now: Instant) -> bool {
        self.total += 1;
        self.pending += 1;
        self.pending_missed += missed;
        self.due(now)
    }

    fn due(&self, now: Instant) -> bool {
        self.pending > 0
            && self
                .last_line
                .is_none_or(|t| now.duration_since(t) >= SUMMARY_EVERY)
    }

    /// The pending counts, reset for the next line.
    fn take(&mut self, now: Instant) -> (u64, u64) {
        self.last_line = Some(now);
        let taken = (self.pending, self.pending_missed);
        self.pending = 0;
        self.pending_missed = 0;
        taken
    }
}

/// Turns servo events into log lines without letting a misbehaving device or a loaded machine
/// flood the log: garbled reports and overruns are logged the first time, then as one summary
/// line per [`SUMMARY_EVERY`].
#[derive(Debug, Default)]
pub struct EventLog {
    garbled: Repeats,
    overruns: Repeats,
}

impl EventLog {
    pub fn new() -> Self {
        Self::default()
    }

    /// Log `event` now.
    pub fn log(&mut self, event: &ServoEvent) {
        self.log_at(event, Instant::now());
    }

    /// Log summaries that are due although no new event came (call it now and then).
    pub fn flush(&mut self) {
        for line in self.flush_at(Instant::now()) {
            warn!("{line}");
        }
    }

    fn flush_at(&mut self, now: Instant) -> Vec<String> {
        let mut lines = Vec::new();
        if self.garbled.due(now) {
            lines.push(self.garbled_line(now));
        }
        if self.overruns.due(now) {
            lines.push(self.overrun_line(now));
        }
        lines
    }

    fn garbled_line(&mut self, now: Instant) -> String {
        let first = self.garbled.last_line.is_none();
        let (n, _) = self.garbled.take(now);
        if first {
            "garbled input report ignored (more are summarised every 10 s)".into()
        } else {
            format!(
                "{n} garbled input report(s) ignored in the last {} s ({} in all)",
                SUMMARY_EVERY.as_secs(),
                self.garbled.total
            )
        }
    }

    fn overrun_line(&mut self, now: Instant) -> String {
        let first = self.overruns.last_line.is_none();
        let (n, missed) = self.overruns.take(now);
        if first {
            format!(
                "servo loop overrun: skipped {missed} report(s) (more are summarised every 10 s)"
            )
        } else {
            format!(
                "servo loop: {n} overrun(s), {missed} report(s) skipped in the last {} s ({} in all)",
                SUMMARY_EVERY.as_secs(),
                self.overruns.total
            )
        }
    }

    fn log_at(&mut self, event: &ServoEvent, now: Instant) {
        match event {
            ServoEvent::WatchdogFault { silent_for } => error!(
                "device silent for {:.1} ms: watchdog fault, force zeroed",
                silent_for * 1e3
            ),
            ServoEvent::ReportsResumed { after } => {
                warn!("device reporting again after {:.1} ms", after * 1e3)
            }
            ServoEvent::DeviceFault => error!("device reports a fault: force zeroed"),
            ServoEvent::DeviceFaultCleared => warn!("device fault cleared"),
            ServoEvent::GarbledReport(e) => {
                if self.garbled.count(0, now) {
                    let line = self.garbled_line(now);
                    warn!("{line}: {e}");
                }
            }
            ServoEvent::NonFiniteForce => {
                error!("controller produced a non-finite force; sent zero")
            }
            ServoEvent::Overrun { missed } => {
                if self.overruns.count(u64::from(*missed), now) {
                    let line = self.overrun_line(now);
                    warn!("{line}");
                }
            }
            ServoEvent::ClockJumpedBack => warn!(
                "device clock stepped back (a reset?): counted in the loop's statistics; \
                 {CLOCK_BACKWARDS_LIMIT} steps back in a row end the run"
            ),
            ServoEvent::Stats(_) => {}
        }
    }
}

/// How often threads that read channels fed by the servo thread look at them. They poll rather
/// than block: a receiver blocked on a crossbeam channel makes every `try_send` take a lock to
/// wake it, and the servo thread must never lock.
pub const POLL: Duration = Duration::from_millis(5);

/// Log servo events on a thread of their own, so the loop never waits for a log line. The thread
/// ends when every sender is gone.
pub fn spawn_event_logger(events: Receiver<ServoEvent>) -> JoinHandle<()> {
    thread::Builder::new()
        .name("hgcd-events".into())
        .spawn(move || {
            let mut log = EventLog::new();
            loop {
                match events.try_recv() {
                    Ok(event) => log.log(&event),
                    Err(TryRecvError::Empty) => {
                        log.flush();
                        thread::sleep(POLL)
                    }
                    Err(TryRecvError::Disconnected) => break,
                }
            }
            log.flush();
        })
        .expect("spawning the event logger thread")
}

/// Why a watched run ([`run_watched`]) gave nothing back.
#[derive(Debug, thiserror::Error)]
pub enum ThreadError {
    #[error("starting the servo thread")]
    Spawn(#[source] std::io::Error),
    #[error("the servo thread panicked")]
    Panicked,
}

/// [`spawn`] the run (its events to the logger thread) and wait for it on this thread, calling
/// `watch` every [`POLL`] and once more after the run ends, to take what the servo thread sent.
/// A loop the device paces (`device_paces`: [`crate::transport::Pacing::set_by_device`]) runs
/// flat out and never at real-time priority. The loop's result and the controller come back.
///
/// # Errors
/// [`ThreadError`]: the thread could not be spawned, or it panicked.
pub fn run_watched<C: Controller + 'static>(
    transport: Box<dyn Transport>,
    controller: C,
    options: ServoOptions,
    mut servo_config: ServoConfig,
    device_paces: bool,
    stop: Arc<AtomicBool>,
    watch: &mut dyn FnMut(),
) -> Result<(Result<ServoReport, ServoError>, C), ThreadError> {
    if device_paces {
        servo_config.realtime_priority = 0;
    }
    let handle = spawn(transport, controller, options, servo_config, stop, None)
        .map_err(ThreadError::Spawn)?;
    while !handle.is_finished() {
        watch();
        thread::sleep(POLL);
    }
    let ended = handle.join().map_err(|_| ThreadError::Panicked)?;
    watch();
    Ok(ended)
}

/// Run `controller` on `transport` on a new thread set up for real time (`servo_config`). Loop
/// events go to `events`, or to a logger thread when None. Joining gives the loop's result and
/// the controller back.
///
/// # Errors
/// The [`std::io::Error`] of a thread that cannot be spawned.
pub fn spawn<C: Controller + 'static>(
    mut transport: Box<dyn Transport>,
    mut controller: C,
    options: ServoOptions,
    servo_config: ServoConfig,
    stop: Arc<AtomicBool>,
    events: Option<Sender<ServoEvent>>,
) -> std::io::Result<JoinHandle<(Result<ServoReport, ServoError>, C)>> {
    let (tx, logger) = match events {
        Some(tx) => (tx, None),
        None => {
            let (tx, rx) = crossbeam_channel::bounded(1024);
            (tx, Some(spawn_event_logger(rx)))
        }
    };
    thread::Builder::new()
        .name("hgcd-servo".into())
        .spawn(move || {
            let setup = rt::prepare_current_thread(&servo_config);
            for w in &setup.warnings {
                warn!("{w}");
            }
            info!(
                "servo thread on {}: {}, {}, memory {}",
                transport.describe(),
                setup
                    .fifo_priority
                    .map_or("normal scheduling".into(), |p| format!(
                        "SCHED_FIFO priority {p}"
                    )),
                setup
                    .pinned_cpu
                    .map_or("not pinned".into(), |c| format!("pinned to CPU {c}")),
                if setup.memory_locked {
                    "locked"
                } else {
                    "not locked"
                }
            );
            let result = run(
                transport.as_mut(),
                &mut controller,
                &options,
                &stop,
                Some(&tx),
            );
            drop(tx);
            if let Some(logger) = logger {
                let _ = logger.join();
            }
            (result, controller)
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn overruns_on_a_busy_machine_give_a_few_summary_lines_not_one_each() {
        // 439 overruns spread over 30 s (what a quiet run on a loaded VM once printed a line each).
        let start = Instant::now();
        let mut log = EventLog::new();
        let mut lines = 0;
        for k in 0..439u64 {
            let now = start + Duration::from_millis(k * 30_000 / 439);
            let was = log.overruns.last_line;
            log.log_at(&ServoEvent::Overrun { missed: 2 }, now);
            if log.overruns.last_line != was {
                lines += 1;
            }
        }
        let end = start + Duration::from_secs(41);
        lines += log.flush_at(end).len();
        // The first at once, then one per 10 s: at most 5 lines for 30 s, and no overrun lost.
        assert!(lines <= 5, "{lines} lines");
        assert_eq!(log.overruns.total, 439);
        assert_eq!(log.overruns.pending, 0);
    }

    #[test]
    fn a_summary_counts_what_happened_since_the_last_line() {
        let start = Instant::now();
        let mut log = EventLog::new();
        log.log_at(&ServoEvent::Overrun { missed: 3 }, start);
        for k in 1..=10 {
            log.log_at(
                &ServoEvent::Overrun { missed: 1 },
                start + Duration::from_millis(k * 100),
            );
        }
        let lines = log.flush_at(start + SUMMARY_EVERY);
        assert_eq!(
            lines,
            vec!["servo loop: 10 overrun(s), 10 report(s) skipped in the last 10 s (11 in all)"]
        );
        assert!(log.flush_at(start + SUMMARY_EVERY * 3).is_empty());
    }
}
