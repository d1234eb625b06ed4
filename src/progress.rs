//! Calibration progress for the terminal (a progress bar) or for logs (plain lines), and the
//! closing summary. Part of the binary: the library only emits events.

use std::io::IsTerminal;

use indicatif::{ProgressBar, ProgressStyle};
use tracing::info;

use hgcd::calibrate::check::{Check, Reverted, Verdict};
use hgcd::calibrate::{CalibrationRun, TimeLeft};
use hgcd::config::{Config, DeviceSpec};
use hgcd::control::calibration::{unreachable_note, CalibrationEvent, CalibrationParams, GridPlan};
use hgcd::grid::AppliedRecord;
use hgcd::validate::ValidateEvent;

pub struct Display {
    bar: Option<ProgressBar>,
    time_left: TimeLeft,
}

impl Display {
    /// A bar over `vertices` vertices when stderr is a terminal, log lines otherwise.
    pub fn new(vertices: usize) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = ProgressBar::new(vertices as u64);
            bar.set_style(
                ProgressStyle::with_template(
                    "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} vertices  {prefix}  {msg}",
                )
                .expect("valid template"),
            );
            bar.set_message("initialising");
            bar
        });
        Self {
            bar,
            time_left: TimeLeft::default(),
        }
    }

    pub fn show(&mut self, event: &CalibrationEvent) {
        let mut line = match event {
            CalibrationEvent::InitStarted => {
                "initialisation: holding the handle with k_init, then pushing it to measure its \
                 load, friction and moving mass"
                    .to_string()
            }
            CalibrationEvent::InitDone {
                gravity_direction: v,
                initial_mass,
                friction: f,
                inertia: m,
            } => {
                format!(
                "load along ({:.4}, {:.4}, {:.4}) of {:.1} g; friction ({:.3}, {:.3}, {:.3}) N; \
                 moving mass ({:.0}, {:.0}, {:.0}) g",
                v.x,
                v.y,
                v.z,
                initial_mass * 1e3,
                f.x,
                f.y,
                f.z,
                m.x * 1e3,
                m.y * 1e3,
                m.z * 1e3
            )
            }
            CalibrationEvent::VertexStarted { vertex, of, at, .. } => {
                // The plan the device's workspace gave (the bar began with the config's).
                if let Some(bar) = &self.bar {
                    bar.set_length(*of as u64);
                }
                format!("vertex {}/{}: moving to {at}", vertex + 1, of)
            }
            CalibrationEvent::Iteration {
                vertex,
                iteration,
                force: f,
                error,
            } => format!(
                "vertex {}: iteration {iteration}, F = ({:.4}, {:.4}, {:.4}) N, error {:.1} µm",
                vertex + 1,
                f.x,
                f.y,
                f.z,
                error * 1e6
            ),
            CalibrationEvent::GainsReduced { vertex, scale } => format!(
                "vertex {}: no steady state yet, PD gains scaled by {scale}",
                vertex + 1
            ),
            CalibrationEvent::VertexDone {
                vertex,
                of,
                force: f,
                iterations,
                ..
            } => {
                if let Some(bar) = &self.bar {
                    bar.set_position(*vertex as u64 + 1);
                }
                format!(
                    "vertex {}/{} done: F = ({:.4}, {:.4}, {:.4}) N after {iterations} updates",
                    vertex + 1,
                    of,
                    f.x,
                    f.y,
                    f.z
                )
            }
            CalibrationEvent::VertexUnreachable {
                vertex,
                of,
                at,
                distance,
                failure,
                retried,
                ..
            } => {
                if let Some(bar) = &self.bar {
                    bar.set_position(*vertex as u64 + 1);
                }
                format!(
                    "vertex {}/{}: {}",
                    vertex + 1,
                    of,
                    unreachable_note(at, *distance, failure.as_ref(), *retried),
                )
            }
            CalibrationEvent::VertexRetried {
                vertex,
                at,
                failure,
                beside,
            } => {
                let why = match failure {
                    None => "the handle did not yield to a push toward it".to_string(),
                    Some(failure) => failure.to_string(),
                };
                let b = beside * 1e3;
                format!(
                    "vertex {}: {at} once more, by way of ({:.1}, {:.1}, {:.1}) mm beside it \
                     ({why})",
                    vertex + 1,
                    b.x,
                    b.y,
                    b.z
                )
            }
            CalibrationEvent::Probed {
                probe,
                from,
                direction: d,
                run,
                stopped,
            } => {
                let f = from * 1e3;
                format!(
                    "exploring, move {}: from ({:.0}, {:.0}, {:.0}) mm along ({:.0}, {:.0}, {:.0}) \
                     the handle {} after {:.1} mm",
                    probe + 1,
                    f.x,
                    f.y,
                    f.z,
                    d.x,
                    d.y,
                    d.z,
                    if *stopped {
                        "met a stop"
                    } else {
                        "reached the next vertex"
                    },
                    run * 1e3
                )
            }
            CalibrationEvent::Explored {
                probes,
                stopped,
                reached,
                vertices,
                extrapolated,
                dims,
            } => {
                if let Some(bar) = &self.bar {
                    bar.set_length(*vertices as u64);
                }
                format!(
                    "explored: {reached} vertices reached in {probes} moves, {stopped} of them \
                     ended by a stop; the grid is {}×{}×{}: {vertices} vertices to calibrate, \
                     {extrapolated} outside the explored workspace or too near a stop to \
                     extrapolate",
                    dims[0], dims[1], dims[2]
                )
            }
            CalibrationEvent::Finished => "calibration finished".to_string(),
            CalibrationEvent::Failed(f) => format!("calibration failed: {f}"),
        };
        if let Some(left) = self.time_left.update(event) {
            match &self.bar {
                Some(bar) => bar.set_prefix(left),
                None => line = format!("{line}; {left}"),
            }
        }
        match &self.bar {
            Some(bar) => bar.set_message(line),
            None => {
                // Iterations are chatty; logs get the milestones.
                if !matches!(event, CalibrationEvent::Iteration { .. }) {
                    info!("{line}");
                }
            }
        }
    }

    pub fn finish(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
    }
}

/// Progress of `hgcd validate`: the calibration's display while it calibrates, then a bar over
/// the repetitions on a terminal, or a log line every tenth of the experiment.
pub struct ValidationDisplay {
    /// Made at the first calibration event (there is none with `--grid`).
    calibration: Option<Display>,
    vertices: usize,
    bar: Option<ProgressBar>,
    terminal: bool,
}

impl ValidationDisplay {
    pub fn new(config: &Config, device: &DeviceSpec) -> Self {
        Self {
            calibration: None,
            vertices: vertex_count(config, device),
            bar: None,
            terminal: std::io::stderr().is_terminal(),
        }
    }

    pub fn show(&mut self, event: ValidateEvent) {
        match event {
            ValidateEvent::Calibration(e) => {
                let vertices = self.vertices;
                self.calibration
                    .get_or_insert_with(|| Display::new(vertices))
                    .show(e)
            }
            ValidateEvent::Started { of } => {
                if let Some(mut c) = self.calibration.take() {
                    c.finish();
                }
                if self.terminal {
                    let bar = ProgressBar::new(of as u64);
                    bar.set_style(
                        ProgressStyle::with_template(
                            "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} repetitions  {msg}",
                        )
                        .expect("valid template"),
                    );
                    self.bar = Some(bar);
                } else {
                    info!("experiment: {of} repetitions");
                }
            }
            ValidateEvent::Rest {
                done,
                of,
                mode,
                penalty,
            } => match &self.bar {
                Some(bar) => {
                    bar.set_position(done as u64);
                    bar.set_message(format!("{}: ΔX = {:.3} mm", mode.name(), penalty * 1e3));
                }
                None => {
                    if done * 10 / of != (done - 1) * 10 / of {
                        info!(
                            "experiment: {done}/{of} repetitions ({}: last ΔX = {:.3} mm)",
                            mode.name(),
                            penalty * 1e3
                        );
                    }
                }
            },
        }
    }

    pub fn finish(&mut self) {
        if let Some(mut c) = self.calibration.take() {
            c.finish();
        }
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
    }
}

/// Progress of `hgcd record`: a bar over the share recorded on a terminal, a log line every
/// tenth otherwise.
pub struct RecordDisplay {
    bar: Option<ProgressBar>,
    tenths: u64,
}

impl RecordDisplay {
    pub fn new(seconds: f64) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = ProgressBar::new(1000);
            bar.set_style(
                ProgressStyle::with_template(&format!(
                    "{{spinner}} [{{elapsed_precise}}] {{bar:30}} recording {seconds} s of device \
                     time  {{percent}} %"
                ))
                .expect("valid template"),
            );
            bar
        });
        Self { bar, tenths: 0 }
    }

    pub fn show(&mut self, share: f64) {
        match &self.bar {
            Some(bar) => bar.set_position((share.clamp(0.0, 1.0) * 1e3) as u64),
            None => {
                let tenths = (share.clamp(0.0, 1.0) * 10.0) as u64;
                if tenths > self.tenths {
                    self.tenths = tenths;
                    info!("recording: {} % done", tenths * 10);
                }
            }
        }
    }

    pub fn finish(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
    }
}

/// Vertices a calibration with `config` visits on `device` (for the bar's length).
pub fn vertex_count(config: &Config, device: &DeviceSpec) -> usize {
    GridPlan::new(&CalibrationParams::for_device(config, device))
        .map(|p| p.path.len())
        .unwrap_or(0)
}

/// What `hgcd check` found, for people: the verdict, what explains it, and the holds.
pub fn check_summary(check: &Check) -> String {
    let mut out = match check.verdict {
        Verdict::Unchanged => "unchanged: the model fits both holds\n".to_string(),
        Verdict::Apply => format!(
            "changed: a payload of {:+.1} g and a tilt of {:.2}° about ({:.3}, {:.3}, {:.3}) \
             explain it{}\n",
            check.payload_g,
            check.tilt_deg,
            check.tilt_axis[0],
            check.tilt_axis[1],
            check.tilt_axis[2],
            match &check.applied {
                Some(kept) => format!(
                    "\napplied to the grid; the model before is kept as {} (hgcd check --revert \
                     puts it back)",
                    kept.display()
                ),
                None => " (hgcd check --apply takes it in)".to_string(),
            }
        ),
        Verdict::Recalibrate => format!(
            "recalibrate: a payload and a tilt do not explain what changed (the closest: {:+.1} g, \
             {:.2}°); a spring, a cable, another arm? run hgcd calibrate\n",
            check.payload_g, check.tilt_deg
        ),
    };
    if let Some(warning) = &check.warning {
        out.push_str(&format!("warning: {warning}\n"));
    }
    out.push_str("hold at (mm)                  measured (N)                  model (N)                     left (mN)  allowed (mN)\n");
    for h in &check.holds {
        let v =
            |a: [f64; 3], k: f64| format!("({:7.3}, {:7.3}, {:7.3})", a[0] * k, a[1] * k, a[2] * k);
        out.push_str(&format!(
            "{}  {}  {}  {:9.2}  {:12.2}\n",
            v(h.position_m, 1e3),
            v(h.measured_n, 1.0),
            v(h.model_n, 1.0),
            h.unexplained_n * 1e3,
            h.tolerance_n * 1e3
        ));
    }
    out.push_str(&format!(
        "{:.1} s of device time; grid {}\n",
        check.device_time_s,
        check.grid.display()
    ));
    out
}

/// What `hgcd check --revert` prints: the model put back, and the changes each model holds.
pub fn revert_summary(reverted: &Reverted) -> String {
    let changes = |applied: &[AppliedRecord]| match applied {
        [] => "no change applied since its calibration".to_string(),
        records => records
            .iter()
            .map(|a| {
                format!(
                    "{:+.1} g, {:.2}° ({})",
                    a.payload_g,
                    a.tilt_deg,
                    a.at.map_or("undated".to_string(), |t| t.to_string())
                )
            })
            .collect::<Vec<_>>()
            .join("; "),
    };
    format!(
        "put back the model kept beside {}: {}\nthe model it replaced is kept in its turn: {}\n",
        reverted.grid.display(),
        changes(&reverted.applied_now),
        changes(&reverted.applied_before)
    )
}

/// What `hgcd calibrate` prints when it succeeds.
pub fn summary(run: &CalibrationRun) -> String {
    let r = &run.result;
    let v = r.gravity_direction;
    let i = &r.initial;
    let mut out = format!(
        "grid written to {}\n\
         gravity direction v_G = ({:.4}, {:.4}, {:.4}); rough mass |load| / g = {:.1} g\n\
         at the start: load ({:.4}, {:.4}, {:.4}) N, friction ({:.3}, {:.3}, {:.3}) N, moving \
         mass ({:.0}, {:.0}, {:.0}) g, noise {:.1} µm; hold stiffness ({:.3}, {:.3}, {:.3}) N/mm\n\
         {} vertices ({}×{}×{}), {:.1} s device time, {:.2} s wall time\n",
        run.path.display(),
        v.x,
        v.y,
        v.z,
        r.initial_mass * 1e3,
        i.load.x,
        i.load.y,
        i.load.z,
        i.friction.x,
        i.friction.y,
        i.friction.z,
        i.inertia.x * 1e3,
        i.inertia.y * 1e3,
        i.inertia.z * 1e3,
        i.noise * 1e6,
        i.stiffness.x * 1e-3,
        i.stiffness.y * 1e-3,
        i.stiffness.z * 1e-3,
        r.vertices.len(),
        r.dims[0],
        r.dims[1],
        r.dims[2],
        r.duration,
        run.wall_time
    );
    out.push_str(&format!("time: {}\n", r.time_spent));
    out.push_str(
        "  vertex (n, m, p)   position mm              mass g   force N                       \
         friction N  updates  final error µm\n",
    );
    for vr in &r.vertices {
        let p = vr.vertex.position * 1e3;
        let f = vr.force;
        out.push_str(&format!(
            "  ({:>2}, {:>2}, {:>2})       ({:>6.1}, {:>6.1}, {:>6.1})   {:>7.2}   ({:>7.4}, {:>7.4}, {:>7.4})   \
             {:>8.3}   {:>6}   {:>8.1}{}\n",
            vr.vertex.index[0],
            vr.vertex.index[1],
            vr.vertex.index[2],
            p.x,
            p.y,
            p.z,
            vr.mass * 1e3,
            f.x,
            f.y,
            f.z,
            vr.friction.max(),
            vr.iterations,
            vr.final_error * 1e6,
            if vr.reached {
                ""
            } else if r.extrapolated.contains(&vr.vertex) && r.workspace.is_some() {
                "  outside the explored workspace: extrapolated"
            } else if r.extrapolated.contains(&vr.vertex) {
                "  not held (sparse holds): filled from the held ones"
            } else {
                "  unreachable: filled from neighbours"
            }
        ));
    }
    for lo in &r.left_out {
        out.push_str(&format!("  left out (outside the workspace): {lo}\n"));
    }
    out.push_str(&model_summary(run));
    out
}

/// The holds and the gravity model chosen from them (docs/calibration.md §13), for a grid with
/// an arm model; nothing otherwise.
fn model_summary(run: &CalibrationRun) -> String {
    let Some(model) = &run.grid.model else {
        return String::new();
    };
    let r = &run.result;
    let held = r.vertices.iter().filter(|v| v.reached).count();
    let mut out = if r.extrapolated.is_empty() || r.workspace.is_some() {
        format!("holds: {held} vertices\n")
    } else {
        format!(
            "holds: {held} of the {} vertices, the cube's corners: the farthest apart \
             in joint angles the cube offers, for the arm model's few parameters \
             (calibration.holds = \"all\" holds every vertex)\n",
            r.vertices.len()
        )
    };
    let s = &model.held_out_pct;
    let pct = |v: Option<f64>| v.map_or("not fitted".to_string(), |v| format!("{v:.2} %"));
    out.push_str(&format!(
        "model: {} (held-out holds: {}; scores: arm {}, arm + residual {}, vector lattice {}, \
         scalar lattice {})\n",
        model.chosen,
        model.held_out_holds,
        pct(s.arm),
        pct(s.arm_residual),
        pct(s.vector),
        pct(s.scalar)
    ));
    if let Some(arm) = &run.grid.arm {
        out.push_str(&format!(
            "arm ({}): v_G ({:.4}, {:.4}, {:.4}), {:.2}° from the arm's up; {} of {} parameters \
             identified{}; fit residual {:.2} mN RMS, {:.2} × the holds' noise\n",
            arm.profile,
            arm.gravity_direction[0],
            arm.gravity_direction[1],
            arm.gravity_direction[2],
            arm.tilt_deg,
            arm.rank,
            arm.parameters.len(),
            if arm.unidentified.is_empty() {
                String::new()
            } else {
                format!(" (left unconstrained: {})", arm.unidentified.join(", "))
            },
            arm.rms_residual_mn,
            arm.normalised_residual
        ));
        if let (Some(before), Some(change)) = (arm.profile_rms_residual_mn, &arm.geometry_change) {
            out.push_str(&format!(
                "geometry: the unit's own, within its tolerances of the profile's ({change}); \
                 the holds' residual with the profile's was {before:.2} mN RMS\n"
            ));
        }
    }
    if let Some(warning) = &model.warning {
        out.push_str(&format!("warning: {warning}\n"));
    }
    out
}
