//! `hgcd run`: owns the device and the servo thread, logs loop events, stops on a signal.

use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::thread;

use anyhow::{Context, Result};
use crossbeam_channel::Receiver;
use tracing::{error, info, warn};

use crate::config::{Config, DeviceSpec};
use crate::control::{Controller, ZeroForce};
use crate::servo::{self, ServoEvent, ServoOptions, ServoReport};
use crate::transport::{self, Pacing};

/// What `hgcd run` was asked to do.
#[derive(Clone, Debug)]
pub struct RunRequest {
    pub device: DeviceSpec,
    /// Stop after this many seconds; None runs until a signal.
    pub duration: Option<f64>,
    /// Pacing of simulated devices.
    pub pacing: Pacing,
}

/// Log servo events on a thread of their own, so the loop never waits for a log line.
pub fn spawn_event_logger(events: Receiver<ServoEvent>) -> thread::JoinHandle<()> {
    thread::Builder::new()
        .name("hgcd-events".into())
        .spawn(move || {
            let mut garbled = 0u64;
            for event in events.iter() {
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
                        garbled += 1;
                        // Log the first few and then every 1000th, so a babbling device cannot flood the log.
                        if garbled <= 5 || garbled % 1000 == 0 {
                            warn!("garbled input report #{garbled} ignored: {e}")
                        }
                    }
                    ServoEvent::NonFiniteForce => {
                        error!("controller produced a non-finite force; sent zero")
                    }
                    ServoEvent::Overrun { missed } => {
                        warn!("servo loop overrun: skipped {missed} report(s)")
                    }
                }
            }
        })
        .expect("spawning the event logger thread")
}

/// Run the servo loop with `controller` on a dedicated real-time thread until `stop` is set or
/// the duration elapses. Returns the loop's report (timing statistics included).
pub fn run_servo_thread(
    config: &Config,
    request: &RunRequest,
    mut controller: Box<dyn Controller>,
    stop: Arc<AtomicBool>,
) -> Result<ServoReport> {
    let mut transport = transport::open(&request.device, config, request.pacing)
        .with_context(|| format!("opening {}", request.device))?;
    info!("device {} opened: {}", request.device, transport.describe());
    let mut options = ServoOptions::from_config(config);
    options.duration = request.duration;
    let servo_config = config.servo.clone();
    let (tx, rx) = crossbeam_channel::bounded(1024);
    let logger = spawn_event_logger(rx);
    let handle = thread::Builder::new()
        .name("hgcd-servo".into())
        .spawn(move || {
            let setup = servo::rt::prepare_current_thread(&servo_config);
            for w in &setup.warnings {
                warn!("{w}");
            }
            info!(
                "servo thread: SCHED_FIFO {:?}, CPU {:?}, memory locked {}",
                setup.fifo_priority, setup.pinned_cpu, setup.memory_locked
            );
            servo::run(
                transport.as_mut(),
                controller.as_mut(),
                &options,
                &stop,
                Some(&tx),
            )
        })
        .context("spawning the servo thread")?;
    let result = handle
        .join()
        .map_err(|_| anyhow::anyhow!("the servo thread panicked"))?;
    let _ = logger.join();
    let report = result.context("servo loop")?;
    info!("servo loop ended: {:?}", report.exit);
    Ok(report)
}

/// `hgcd run`: the loop with whatever compensation exists (none yet: zero force).
pub fn run(config: &Config, request: &RunRequest, stop: Arc<AtomicBool>) -> Result<ServoReport> {
    run_servo_thread(config, request, Box::new(ZeroForce), stop)
}
