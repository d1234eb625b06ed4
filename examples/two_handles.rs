//! Two devices, one application: a virtual spring and damper between the handles of two daemons,
//! the simplest teleoperation. Each handle is pulled toward the other with
//! F_a = k (x_b − x_a) + b (v_b − v_a) and F_b = −F_a; move one and the other follows. Gravity
//! compensation, where a daemon has a grid, comes from underneath.
//!
//! Two daemons, one per device (`docs/install.md` §4), then this example naming both:
//!
//! ```text
//! cargo run --release --example two_handles -- --device hid:1209:4847:SN1 --device hid:1209:4847:SN2
//! cargo run --release --example two_handles -- --socket /tmp/a.sock --socket /tmp/b.sock
//! ```
//!
//! It prints the distance between the handles at the start and at the end.

use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{bail, ensure, Context, Result};
use clap::Parser;
use nalgebra::Vector3;

use hgcd::client::{Client, Role};

#[derive(Parser)]
struct Args {
    /// A daemon's device (a device id or spec); give two, or two --socket, or one of each.
    #[arg(long, value_name = "SPEC")]
    device: Vec<String>,
    /// A daemon's application socket.
    #[arg(long, value_name = "PATH")]
    socket: Vec<PathBuf>,
    /// Spring stiffness k, N/mm.
    #[arg(long, default_value_t = 0.2)]
    stiffness: f64,
    /// Damping b on the handles' relative velocity, N·s/m.
    #[arg(long, default_value_t = 5.0)]
    damping: f64,
    /// How long to couple, s of the first device's time.
    #[arg(long, default_value_t = 5.0)]
    duration: f64,
}

/// The daemon at `socket`, or else of `device`, with the force owned.
fn open(socket: Option<&PathBuf>, device: Option<&str>) -> Result<Client> {
    let name = "two_handles";
    let client = match socket {
        Some(path) => Client::connect(path, Role::Control, name)?,
        None => Client::connect_to(device, Role::Control, name)?,
    };
    if client.role != Role::Control {
        bail!(
            "another application owns the force on {} (the daemon lets this one only observe)",
            client.device_id
        );
    }
    Ok(client)
}

/// The coupling force on handle a at `xa`, `va` from handle b at `xb`, `vb` (SI units).
fn spring(k: f64, b: f64, xa: [f64; 3], va: [f64; 3], xb: [f64; 3], vb: [f64; 3]) -> Vector3<f64> {
    let v = Vector3::from;
    k * (v(xb) - v(xa)) + b * (v(vb) - v(va))
}

fn run(args: &Args) -> Result<()> {
    ensure!(
        args.socket.len() + args.device.len() == 2,
        "name two daemons: two --device SPEC, two --socket PATH, or one of each"
    );
    ensure!(
        args.stiffness.is_finite() && args.stiffness > 0.0,
        "--stiffness must be a positive number of N/mm"
    );
    ensure!(
        args.damping.is_finite() && args.damping >= 0.0,
        "--damping must be a number of N·s/m, 0 or more"
    );
    ensure!(
        args.duration.is_finite() && args.duration > 0.0,
        "--duration must be a positive number of seconds"
    );
    let mut clients = Vec::new();
    for socket in &args.socket {
        clients.push(open(Some(socket), None)?);
    }
    for device in &args.device {
        clients.push(open(None, Some(device))?);
    }
    let [mut a, mut b]: [Client; 2] = clients.try_into().ok().context("two daemons")?;
    ensure!(
        a.device_id != b.device_id,
        "both names lead to the same device {}",
        a.device_id
    );
    let (k, damping) = (args.stiffness * 1e3, args.damping);
    // The force each may send is the smaller limit, so that the two stay equal and opposite.
    let limit = a.max_force.min(b.max_force);
    a.subscribe(a.rate_hz)?;
    b.subscribe(b.rate_hz)?;
    let (mut start, mut first_gap) = (None, None);
    // One state from each, answered at once: each handle feels the other's latest position.
    let gap = loop {
        let (sa, sb) = (a.next_state()?, b.next_state()?);
        let elapsed = sa.time - *start.get_or_insert(sa.time);
        let gap = (Vector3::from(sb.position) - Vector3::from(sa.position)).norm();
        first_gap.get_or_insert(gap);
        if elapsed >= args.duration {
            break gap;
        }
        let mut f = spring(
            k,
            damping,
            sa.position,
            sa.velocity,
            sb.position,
            sb.velocity,
        );
        if f.norm() > limit {
            f *= limit / f.norm();
        }
        a.set_force(f)?;
        b.set_force(-f)?;
    };
    a.set_force(Vector3::zeros())?;
    b.set_force(Vector3::zeros())?;
    let mut stdout = std::io::stdout().lock();
    writeln!(
        stdout,
        "coupled {} and {} for {} s with {} N/mm, {} N·s/m: distance between the handles {:.3} mm \
         at the start, {:.3} mm at the end",
        a.device_id,
        b.device_id,
        args.duration,
        args.stiffness,
        args.damping,
        first_gap.unwrap_or(0.0) * 1e3,
        gap * 1e3
    )
    .or_else(|e| match e.kind() {
        std::io::ErrorKind::BrokenPipe => Ok(()),
        _ => Err(e),
    })
    .context("writing to standard output")
}

fn main() -> ExitCode {
    let args = Args::parse();
    match run(&args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            let _ = writeln!(std::io::stderr(), "two_handles: {e:#}");
            ExitCode::FAILURE
        }
    }
}
