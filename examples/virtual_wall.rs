//! A horizontal virtual surface rendered through hgcd, as in the paper's validation experiment:
//! below the plane z = height the end effector is pushed up with F_z = k (height − z); above it,
//! no force. Gravity compensation comes from the daemon underneath.
//!
//! Run a daemon, then this example:
//!
//! ```text
//! hgcd --socket /tmp/hgcd.sock --state-dir /tmp/hgcd-state run --device sim:point-mass &
//! cargo run --example virtual_wall -- --socket /tmp/hgcd.sock --stiffness 1.0 --height 0 --duration 5
//! ```
//!
//! It prints the mean penetration ("penalty") over the last second: with exact compensation and a
//! probe mass m_p it tends to m_p g / k (0.29 mm for 30 g on 1 N/mm, paper §5).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Parser;
use nalgebra::Vector3;

use hgcd::client::{Client, Role};

#[derive(Parser)]
struct Args {
    /// The daemon's application socket.
    #[arg(long, default_value = hgcd::config::DEFAULT_SOCKET)]
    socket: PathBuf,
    /// Surface stiffness, N/mm.
    #[arg(long, default_value_t = 1.0)]
    stiffness: f64,
    /// Height of the surface, mm (device frame).
    #[arg(long, default_value_t = 0.0)]
    height: f64,
    /// How long to render, s.
    #[arg(long, default_value_t = 5.0)]
    duration: f64,
}

/// The wall's force at position z (m) for a plane at `height` (m) of stiffness `k` (N/m).
fn wall_force(z: f64, height: f64, k: f64) -> Vector3<f64> {
    Vector3::new(0.0, 0.0, (k * (height - z)).max(0.0))
}

fn main() -> Result<()> {
    let args = Args::parse();
    let (k, height) = (args.stiffness * 1e3, args.height * 1e-3);
    let mut client = Client::connect(&args.socket, Role::Control, "virtual_wall")
        .context("connecting to hgcd")?;
    anyhow::ensure!(
        client.role == Role::Control,
        "another application owns the force"
    );
    client.subscribe(client.rate_hz)?;
    let first = client.next_state()?;
    let (mut sum, mut count) = (0.0, 0u64);
    loop {
        let s = client.next_state()?;
        let elapsed = s.time - first.time;
        if elapsed >= args.duration {
            break;
        }
        client.set_force(wall_force(s.position[2], height, k))?;
        if elapsed >= args.duration - 1.0 {
            sum += (height - s.position[2]).max(0.0);
            count += 1;
        }
    }
    client.set_force(Vector3::zeros())?;
    if count > 0 {
        println!(
            "mean penetration over the last second: {:.3} mm",
            sum / count as f64 * 1e3
        );
    }
    Ok(())
}
