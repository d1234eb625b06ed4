//! A horizontal virtual surface rendered through hgcd, as in the paper's validation experiment
//! (§5): below the plane z = height the handle is pushed up by a spring and a damper,
//! F_z = max(0, k (height − z) − b v_z); above it, no force. The force is kept within the limit
//! the daemon publishes. Gravity compensation, if the daemon has a grid, comes from underneath.
//!
//! Run a daemon, then this example (as a normal user, give both the same socket; with several
//! daemons running, name one with `--device SPEC`):
//!
//! ```text
//! hgcd --socket /tmp/hgcd.sock run --device sim:point-mass &
//! cargo run --release --example virtual_wall -- --socket /tmp/hgcd.sock
//! ```
//!
//! It shows the handle's height and the wall's force while it runs (on a terminal), then the
//! mean penetration over the last second, and why. Resting on the wall, the spring carries the
//! load that gravity compensation leaves, so the penetration is load / k:
//!
//! - with a grid (compensation `scalar` or `vector`) the handle floats, and only a load the grid
//!   does not know sinks in: the paper's 30 g probe on 1 N/mm, 0.29 mm (the simulated device
//!   carries one with `sim.probe_mass_kg = 0.03`); with no load, about 0 mm;
//! - without a grid (compensation `none`) the handle's own weight rests on the wall: the simulated
//!   device's 120 g sink 1.18 mm into 1 N/mm.

use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, ensure, Context, Result};
use clap::Parser;
use nalgebra::Vector3;

use hgcd::client::{Client, Compensating, Role};

#[derive(Parser)]
struct Args {
    /// The daemon's application socket (default: that of the daemon of --device).
    #[arg(long)]
    socket: Option<PathBuf>,
    /// The daemon's device, a device id or spec (default: the only daemon running).
    #[arg(long, conflicts_with = "socket")]
    device: Option<String>,
    /// Surface stiffness k, N/mm.
    #[arg(long, default_value_t = 1.0)]
    stiffness: f64,
    /// Surface damping b, N·s/m (pushes only, never pulls the handle into the wall).
    #[arg(long, default_value_t = 10.0)]
    damping: f64,
    /// Height of the surface, mm (device frame).
    #[arg(long, default_value_t = 0.0)]
    height: f64,
    /// How long to render, s of device time.
    #[arg(long, default_value_t = 5.0)]
    duration: f64,
}

/// Standard gravity, m/s², only to say a load in grams.
const G: f64 = 9.81;

/// The wall's force at height `z` (m) moving at `vz` (m/s), for a plane at `height` (m) of
/// stiffness `k` (N/m) and damping `b` (N·s/m).
fn wall_force(z: f64, vz: f64, height: f64, k: f64, b: f64) -> Vector3<f64> {
    let depth = height - z;
    let fz = if depth > 0.0 {
        (k * depth - b * vz).max(0.0)
    } else {
        0.0
    };
    Vector3::new(0.0, 0.0, fz)
}

/// Write `text` to standard output; a reader that went away is not an error.
fn say(text: &str) -> Result<()> {
    let mut stdout = std::io::stdout().lock();
    match stdout
        .write_all(text.as_bytes())
        .and_then(|()| stdout.flush())
    {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        written => written.context("writing to standard output"),
    }
}

fn run(args: &Args) -> Result<()> {
    ensure!(
        args.stiffness.is_finite() && args.stiffness > 0.0,
        "--stiffness must be a positive number of N/mm"
    );
    ensure!(
        args.damping.is_finite() && args.damping >= 0.0,
        "--damping must be a number of N·s/m, 0 or more"
    );
    ensure!(args.height.is_finite(), "--height must be a number of mm");
    ensure!(
        args.duration.is_finite() && args.duration > 0.0,
        "--duration must be a positive number of seconds"
    );
    let (k, b, height) = (args.stiffness * 1e3, args.damping, args.height * 1e-3);
    let mut client = match &args.socket {
        Some(socket) => Client::connect(socket, Role::Control, "virtual_wall")?,
        None => Client::connect_to(args.device.as_deref(), Role::Control, "virtual_wall")?,
    };
    if client.role != Role::Control {
        bail!("another application owns the force (the daemon lets this one only observe): close it and try again");
    }
    let mode = client.status()?.mode;
    say(&format!(
        "wall at z = {:.1} mm, {} N/mm, {} N·s/m, for {} s on {}; gravity compensation: {mode} ({}); \
         forces kept within {} N\n",
        args.height,
        args.stiffness,
        args.damping,
        args.duration,
        client.device,
        mode.meaning(),
        client.max_force
    ))?;
    let live = std::io::stdout().is_terminal();
    // The mean is taken over the last second, or the last half of a shorter run.
    let window = args.duration.min(2.0) / 2.0;
    client.subscribe(client.rate_hz)?;
    let (mut start, mut depth_sum, mut count, mut shown) = (None, 0.0, 0u64, f64::NEG_INFINITY);
    // Every state is answered at once: the force is the wall's at the handle's latest position.
    loop {
        let s = client.next_state()?;
        let elapsed = s.time - *start.get_or_insert(s.time);
        if elapsed >= args.duration {
            break;
        }
        let force = client.within_limit(wall_force(s.position[2], s.velocity[2], height, k, b));
        client.set_force(force)?;
        let depth = (height - s.position[2]).max(0.0);
        if elapsed >= args.duration - window {
            depth_sum += depth;
            count += 1;
        }
        if live && elapsed - shown >= 0.05 {
            shown = elapsed;
            say(&format!(
                "\r  t {elapsed:5.2} s   z {:8.3} mm   depth {:7.3} mm   wall {:5.2} N ",
                s.position[2] * 1e3,
                depth * 1e3,
                force.z
            ))?;
        }
    }
    client.set_force(Vector3::zeros())?;
    if live {
        say("\n")?;
    }
    let depth = depth_sum / count.max(1) as f64;
    let load = k * depth;
    say(&format!(
        "mean penetration over the last {window} s: {:.3} mm: the wall carries {load:.2} N \
         (k × depth), the weight of {:.0} g.\n{}\n",
        depth * 1e3,
        load / G * 1e3,
        explain(mode, args.stiffness)
    ))
}

/// Why the wall carries what it carries, for compensation `mode` and stiffness `k` (N/mm).
fn explain(mode: Compensating, k: f64) -> String {
    let probe = 0.03 * G / (k * 1e3) * 1e3;
    match mode {
        Compensating::None => format!(
            "Without gravity compensation the handle's own weight rests on the wall, with anything \
             it carries. Calibrate (`hgcd calibrate`) and run this again: the handle then floats \
             and only loads the grid does not know sink in (a 30 g probe: {probe:.2} mm)."
        ),
        Compensating::Scalar
        | Compensating::Vector
        | Compensating::Arm
        | Compensating::ArmResidual => format!(
            "Gravity compensation cancels the handle's weight: the wall carries only what the grid \
             does not know, such as a probe or your hand (the paper's 30 g probe: {probe:.2} mm; \
             on the simulated device set sim.probe_mass_kg = 0.03). A handle alone floats: 0 mm."
        ),
    }
}

fn main() -> ExitCode {
    let args = Args::parse();
    match run(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // One line, whatever went wrong; nowhere left to say it if stderr is gone too.
            let _ = writeln!(std::io::stderr(), "virtual_wall: {e:#}");
            ExitCode::FAILURE
        }
    }
}
