//! `hgcd calibrate`: run Algorithm 1 on a device inside the servo loop and persist the grid.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Instant, SystemTime};

use anyhow::{bail, Context, Result};
use tracing::{info, warn};

use crate::config::{Config, DeviceSpec};
use crate::control::calibration::{
    Calibration, CalibrationEvent, CalibrationParams, CalibrationResult,
};
use crate::grid::MassGrid;
use crate::servo::{self, ExitReason, ServoOptions, TimingStats};
use crate::transport::{self, Pacing};

/// What `hgcd calibrate` was asked to do.
#[derive(Clone, Debug)]
pub struct CalibrateRequest {
    pub device: DeviceSpec,
    /// Pacing of simulated devices (virtual time for batch work).
    pub pacing: Pacing,
    /// Where to write the grid: this file, or `<state_dir>/<device-id>.toml`.
    pub output: Option<PathBuf>,
    pub state_dir: PathBuf,
}

impl CalibrateRequest {
    /// The file the grid goes to.
    pub fn output_path(&self) -> PathBuf {
        self.output
            .clone()
            .unwrap_or_else(|| grid_path(&self.state_dir, &self.device))
    }
}

/// Where the grid of `device` lives in `state_dir`.
pub fn grid_path(state_dir: &Path, device: &DeviceSpec) -> PathBuf {
    state_dir.join(format!("{}.toml", device.device_id()))
}

/// A finished, saved calibration.
#[derive(Clone, Debug)]
pub struct CalibrationRun {
    pub result: CalibrationResult,
    pub grid: MassGrid,
    pub path: PathBuf,
    pub stats: TimingStats,
    /// Wall-clock duration, s.
    pub wall_time: f64,
}

/// Check before calibrating that the output directory exists (creating it) and takes a file,
/// so a long calibration does not end in an unwritable directory.
pub fn check_writable(path: &Path) -> Result<()> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&dir).with_context(|| {
        format!(
            "cannot create the state directory {} (use --state-dir or --output)",
            dir.display()
        )
    })?;
    let probe = dir.join(format!(".hgcd-probe-{}", std::process::id()));
    let written = std::fs::write(&probe, b"probe");
    let _ = std::fs::remove_file(&probe);
    written.with_context(|| {
        format!(
            "cannot write to {} (read-only, full or no permission; use --state-dir or --output)",
            dir.display()
        )
    })
}

/// The grid a calibration produced, with its provenance and per-vertex quality as extra keys.
pub fn grid_from_result(
    result: &CalibrationResult,
    config: &Config,
    device: &DeviceSpec,
) -> MassGrid {
    let c = &config.calibration;
    let mut grid = MassGrid {
        g: c.g,
        gravity_direction: result.gravity_direction,
        origin: result.origin,
        spacing: c.spacing(),
        dims: result.dims,
        masses: result.vertices.iter().map(|v| v.mass).collect(),
        extra: toml::Table::new(),
    };
    let float = toml::Value::Float;
    let array = |v: Vec<toml::Value>| toml::Value::Array(v);
    let vec3 = |x: &nalgebra::Vector3<f64>| array(x.iter().map(|c| float(*c)).collect());

    let mut dev = toml::Table::new();
    dev.insert("id".into(), device.device_id().into());
    dev.insert("spec".into(), device.to_string().into());
    grid.extra.insert("device".into(), toml::Value::Table(dev));

    let mut cal = toml::Table::new();
    let created = humantime::format_rfc3339_seconds(SystemTime::now()).to_string();
    cal.insert(
        "created".into(),
        created
            .parse::<toml::value::Datetime>()
            .map(toml::Value::Datetime)
            .unwrap_or_else(|_| created.clone().into()),
    );
    cal.insert("hgcd_version".into(), env!("CARGO_PKG_VERSION").into());
    cal.insert("spacing_mm".into(), float(c.spacing_mm));
    cal.insert("half_size".into(), i64::from(c.half_size).into());
    cal.insert(
        "centre_mm".into(),
        array(c.centre_mm.iter().map(|v| float(*v)).collect()),
    );
    cal.insert("k_init_n_per_mm".into(), float(c.k_init_n_per_mm));
    cal.insert(
        "init_damping_n_s_per_m".into(),
        float(c.init_damping_n_s_per_m),
    );
    cal.insert("n_init".into(), (c.n_init as i64).into());
    cal.insert("eps_init_mm".into(), float(c.eps_init_mm));
    cal.insert("n_m".into(), (c.n_m as i64).into());
    cal.insert("eps_m_mm".into(), float(c.eps_m_mm));
    cal.insert("rise_time_ms".into(), float(c.rise_time_ms));
    cal.insert("damping_ratio".into(), float(c.damping_ratio));
    cal.insert("initial_mass_kg".into(), float(result.initial_mass));
    cal.insert("rest_point_mm".into(), vec3(&(result.rest_point * 1e3)));
    cal.insert("move_time_ms".into(), float(c.move_time_ms));
    cal.insert("vertex_timeout_s".into(), float(c.vertex_timeout_s));
    cal.insert("max_iterations".into(), i64::from(c.max_iterations).into());
    let mm3 = |v: [f64; 3]| array(v.iter().map(|c| float(*c)).collect());
    cal.insert(
        "workspace_min_mm".into(),
        mm3(config.device.workspace_min_mm),
    );
    cal.insert(
        "workspace_max_mm".into(),
        mm3(config.device.workspace_max_mm),
    );
    cal.insert("duration_s".into(), float(result.duration));
    cal.insert(
        "left_out_vertices".into(),
        array(
            result
                .left_out
                .iter()
                .map(|v| array(v.index.iter().map(|&k| i64::from(k).into()).collect()))
                .collect(),
        ),
    );
    grid.extra
        .insert("calibration".into(), toml::Value::Table(cal));

    let mut vertices = toml::Table::new();
    vertices.insert(
        "force_vectors".into(),
        array(result.vertices.iter().map(|v| vec3(&v.force)).collect()),
    );
    vertices.insert(
        "iterations".into(),
        array(
            result
                .vertices
                .iter()
                .map(|v| i64::from(v.iterations).into())
                .collect(),
        ),
    );
    vertices.insert(
        "final_error_mm".into(),
        array(
            result
                .vertices
                .iter()
                .map(|v| float(v.final_error * 1e3))
                .collect(),
        ),
    );
    grid.extra
        .insert("vertices".into(), toml::Value::Table(vertices));
    grid
}

/// Run the calibration on the device and save the grid atomically. `progress` sees every event
/// (on the calling thread). Nothing is written unless the calibration finishes.
pub fn calibrate(
    config: &Config,
    request: &CalibrateRequest,
    stop: Arc<AtomicBool>,
    progress: &mut dyn FnMut(&CalibrationEvent),
) -> Result<CalibrationRun> {
    config.validate()?;
    let transport = transport::open(&request.device, config, request.pacing)
        .with_context(|| format!("opening {}", request.device))?;
    // Name the grid after the device actually opened (a HID serial number the spec left out).
    let mut request = request.clone();
    if let Some(spec) = transport.resolved_spec() {
        request.device = spec;
    }
    let request = &request;
    let path = request.output_path();
    check_writable(&path)?;
    let params = CalibrationParams::from_config(config);
    let (tx, rx) = crossbeam_channel::bounded(4096);
    let calibration = Calibration::new(params, Some(tx))?;
    let plan = calibration.plan();
    if !plan.left_out.is_empty() {
        let names: Vec<String> = plan.left_out.iter().map(|v| v.to_string()).collect();
        warn!(
            "{} vertices lie outside the workspace (device.workspace_*_mm) and are left out; the \
             grid shrinks to {}×{}×{}: {}",
            plan.left_out.len(),
            plan.dims[0],
            plan.dims[1],
            plan.dims[2],
            names.join("; ")
        );
    }
    info!(
        "calibrating {} vertices ({}×{}×{}) on {}",
        plan.path.len(),
        plan.dims[0],
        plan.dims[1],
        plan.dims[2],
        request.device
    );
    let mut options = ServoOptions::from_config(config);
    options.stop_on_fault = true;
    let mut servo_config = config.servo.clone();
    if request.pacing == Pacing::Virtual && matches!(request.device, DeviceSpec::Sim { .. }) {
        // A virtual-time loop runs flat out: never let it take a core at real-time priority.
        servo_config.realtime_priority = 0;
    }
    let started = Instant::now();
    let handle = servo::thread::spawn(transport, calibration, options, servo_config, stop, None)
        .context("starting the servo thread")?;
    // The controller (holding the sender) comes back through the join handle, so watch the thread
    // rather than wait for the channel to close.
    while !handle.is_finished() {
        for event in rx.try_iter() {
            progress(&event);
        }
        std::thread::sleep(servo::thread::POLL);
    }
    let (result, calibration) = handle
        .join()
        .map_err(|_| anyhow::anyhow!("the servo thread panicked"))?;
    for event in rx.try_iter() {
        progress(&event);
    }
    let report = result.context("calibration stopped; nothing was written")?;
    let result = match (&report.exit, calibration.outcome()) {
        (_, Some(Ok(result))) => result,
        (_, Some(Err(failure))) => bail!("calibration failed: {failure}; nothing was written"),
        (ExitReason::Stopped, None) => bail!("calibration aborted; nothing was written"),
        (ExitReason::Fault(why), None) => {
            bail!("calibration stopped by a fault: {why}; nothing was written")
        }
        (exit, None) => bail!("calibration ended early ({exit:?}); nothing was written"),
    };
    let grid = grid_from_result(&result, config, &request.device);
    grid.save_atomic(&path)?;
    info!("grid written to {}", path.display());
    Ok(CalibrationRun {
        result,
        grid,
        path,
        stats: report.stats,
        wall_time: started.elapsed().as_secs_f64(),
    })
}
