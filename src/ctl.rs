//! Commands that talk to a running daemon over its socket: `hgcd status` and
//! `hgcd calibrate --via-daemon`.

use std::path::Path;

use anyhow::{bail, Result};

use hgcd::client::{CalibrationStage, Client, Reply, Role};

/// Print the daemon's status.
///
/// Errors: the client's, when no daemon listens on `socket` or it refuses.
pub fn status(socket: &Path) -> Result<()> {
    let mut client = Client::connect(socket, Role::Observe, "hgcd status")?;
    let s = client.status()?;
    println!("device        {} ({})", s.device, s.device_id);
    println!(
        "compensation  {}{}",
        s.mode,
        s.grid.map(|g| format!(" from {g}")).unwrap_or_default()
    );
    println!("calibrating   {}", if s.calibrating { "yes" } else { "no" });
    println!(
        "clients       {} (force owned by {})",
        s.clients,
        s.owner.as_deref().unwrap_or("nobody")
    );
    println!(
        "servo loop    {} ticks in {:.1} s; late {}, missed {}, overruns {}, garbled {}, watchdog faults {}; worst tick {:.1} µs, longest period {:.0} µs",
        s.servo.ticks,
        s.uptime_s,
        s.servo.late,
        s.servo.missed,
        s.servo.overruns,
        s.servo.garbled,
        s.servo.watchdog_faults,
        s.servo.worst_compute_us,
        s.servo.worst_period_us
    );
    println!(
        "lateness      worst {:.0} µs after the report's timestamp; {} report(s) more than a period late",
        s.servo.worst_lateness_us, s.servo.late_wakeups
    );
    Ok(())
}

/// Ask the daemon to calibrate and follow its progress until it finishes.
///
/// Errors: the client's, a refusal, or the calibration's failure as the daemon reports it.
pub fn calibrate_via_daemon(socket: &Path) -> Result<()> {
    let mut client = Client::connect(socket, Role::Observe, "hgcd calibrate")?;
    client.request_calibration()?;
    loop {
        let reply = client.next_reply()?;
        if let Reply::Error { message, .. } = &reply {
            bail!("the daemon refused: {message}");
        }
        if let Reply::Calibration {
            event,
            vertex,
            of,
            mass_kg,
            message,
        } = reply
        {
            match event {
                CalibrationStage::Started => eprintln!("calibration started on {}", client.device),
                CalibrationStage::InitDone => eprintln!(
                    "gravity direction found; rough mass {:.1} g",
                    mass_kg.unwrap_or(0.0) * 1e3
                ),
                CalibrationStage::VertexDone => eprintln!(
                    "vertex {}/{}: {:.2} g",
                    vertex.unwrap_or(0) + 1,
                    of.unwrap_or(0),
                    mass_kg.unwrap_or(0.0) * 1e3
                ),
                CalibrationStage::Finished => {
                    println!("calibration finished; the daemon now uses {message}");
                    return Ok(());
                }
                CalibrationStage::Failed => bail!("calibration failed: {message}"),
            }
        }
    }
}
