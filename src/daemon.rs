//! `hgcd run`: owns the device and the servo thread until a signal or the duration ends.

use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use anyhow::{Context, Result};
use tracing::info;

use crate::config::{Config, DeviceSpec};
use crate::control::ZeroForce;
use crate::servo::{self, ServoOptions, ServoReport};
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

/// `hgcd run`: the loop with whatever compensation exists (none yet: zero force).
pub fn run(config: &Config, request: &RunRequest, stop: Arc<AtomicBool>) -> Result<ServoReport> {
    let transport = transport::open(&request.device, config, request.pacing)
        .with_context(|| format!("opening {}", request.device))?;
    let mut options = ServoOptions::from_config(config);
    options.duration = request.duration;
    let handle = servo::thread::spawn(transport, ZeroForce, options, config.servo.clone(), stop)
        .context("starting the servo thread")?;
    let (result, _) = handle
        .join()
        .map_err(|_| anyhow::anyhow!("the servo thread panicked"))?;
    let report = result.context("servo loop")?;
    info!("servo loop ended: {:?}", report.exit);
    Ok(report)
}
