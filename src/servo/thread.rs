//! Running the loop on a dedicated real-time thread, with its events logged on another.

use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::thread::{self, JoinHandle};
use std::time::Duration;

use crossbeam_channel::{Receiver, Sender, TryRecvError};
use tracing::{error, info, warn};

use super::{rt, run, ServoError, ServoEvent, ServoOptions, ServoReport};
use crate::config::ServoConfig;
use crate::control::Controller;
use crate::transport::Transport;

/// Log one servo event; `garbled` counts garbled reports so a babbling device cannot flood the
/// log (the first few, then every 1000th).
pub fn log_event(event: &ServoEvent, garbled: &mut u64) {
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
            *garbled += 1;
            if *garbled <= 5 || *garbled % 1000 == 0 {
                warn!("garbled input report #{garbled} ignored: {e}")
            }
        }
        ServoEvent::NonFiniteForce => error!("controller produced a non-finite force; sent zero"),
        ServoEvent::Overrun { missed } => warn!("servo loop overrun: skipped {missed} report(s)"),
        ServoEvent::Stats(_) => {}
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
            let mut garbled = 0u64;
            loop {
                match events.try_recv() {
                    Ok(event) => log_event(&event, &mut garbled),
                    Err(TryRecvError::Empty) => thread::sleep(POLL),
                    Err(TryRecvError::Disconnected) => break,
                }
            }
        })
        .expect("spawning the event logger thread")
}

/// Run `controller` on `transport` on a new thread set up for real time (`servo_config`). Loop
/// events go to `events`, or to a logger thread when None. Joining gives the loop's result and
/// the controller back.
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
