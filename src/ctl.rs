//! Commands that talk to a running daemon over its socket: `hgcd status` and
//! `hgcd calibrate --via-daemon`.

use std::path::{Path, PathBuf};

use anyhow::{bail, Result};

use hgcd::calibrate::check::{Check, Reverted};
use hgcd::client::{CalibrationStage, Client, ModelStale, Reply, Role, StaleEvidence};

use crate::{err, out};

/// Print the status of the daemon at each of `sockets`, a blank line between two.
///
/// Errors: the client's, when no daemon listens on a socket or it refuses.
pub fn status(sockets: &[PathBuf]) -> Result<()> {
    for (n, socket) in sockets.iter().enumerate() {
        if n > 0 {
            out("\n")?;
        }
        one_status(socket)?;
    }
    Ok(())
}

fn one_status(socket: &Path) -> Result<()> {
    let mut client = Client::connect(socket, Role::Observe, "hgcd status")?;
    let s = client.status()?;
    out(&format!(
        "device        {} ({})\n\
         socket        {}\n\
         compensation  {}{}{}: {}\n\
         calibrating   {}\n\
         clients       {} (force owned by {})\n\
         servo loop    {} ticks in {:.1} s; late {}, missed {}, overruns {}, garbled {}, watchdog \
         faults {}; worst tick {:.1} µs, longest period {:.0} µs\n\
         lateness      worst {:.0} µs after the report's timestamp; {} report(s) more than a period \
         late\n{}",
        s.device,
        s.device_id,
        socket.display(),
        s.mode,
        s.grid.map(|g| format!(" from {g}")).unwrap_or_default(),
        s.held_out_pct
            .map(|p| format!(" (held-out score {p:.2} %)"))
            .unwrap_or_default(),
        s.mode.meaning(),
        if s.calibrating { "yes" } else { "no" },
        s.clients,
        s.owner.as_deref().unwrap_or("nobody"),
        s.servo.ticks,
        s.uptime_s,
        s.servo.late,
        s.servo.missed,
        s.servo.overruns,
        s.servo.garbled,
        s.servo.watchdog_faults,
        s.servo.worst_compute_us,
        s.servo.worst_period_us,
        s.servo.worst_lateness_us,
        s.servo.late_wakeups,
        s.model_stale.as_ref().map_or(String::new(), stale_line)
    ))
}

/// `hgcd status`'s line for a model the daemon found stale in use.
fn stale_line(m: &ModelStale) -> String {
    format!(
        "model         STALE: {} at {:.1} s; a payload of {:+.1} g{} it ({:.1} mN \
             across gravity){}\n",
        match m.evidence {
            StaleEvidence::Released => "a released handle drifted",
            StaleEvidence::HeldStill => "an application held the handle with the same force",
        },
        m.device_time_s,
        m.payload_g,
        if m.tilt_deg >= ModelStale::NAMED_TILT_DEG {
            format!(" and a tilt of {:.2}° explain", m.tilt_deg)
        } else {
            " explains".into()
        },
        m.sideways_n * 1e3,
        if m.auto_updated {
            "; taken into the compensation (compensation.auto_update)"
        } else {
            "; run hgcd check, or calibrate"
        }
    )
}

/// `hgcd calibrate --via-daemon`: the daemon calibrates its device; progress on stderr.
pub fn calibrate_via_daemon(socket: &Path) -> Result<()> {
    let mut client = Client::connect(socket, Role::Observe, "hgcd calibrate")?;
    client.request_calibration()?;
    match follow(&mut client, "calibration", "vertex")? {
        Reply::Calibration { message, .. } => out(&format!(
            "calibration finished; the daemon now uses {message}\n"
        )),
        other => bail!("the daemon answered a calibration with {other:?}"),
    }
}

/// `hgcd check --via-daemon`: the daemon checks its device against its grid (and with `apply`
/// takes a change found into it); progress on stderr, the answer returned.
pub fn check_via_daemon(socket: &Path, apply: bool) -> Result<Check> {
    let mut client = Client::connect(socket, Role::Observe, "hgcd check")?;
    client.request_check(apply)?;
    match follow(&mut client, "check", "hold")? {
        Reply::Checked(found) => Ok(*found),
        other => bail!("the daemon answered a check with {other:?}"),
    }
}

/// `hgcd check --revert --via-daemon`: the daemon puts back the model kept beside its grid and
/// compensates with it; what it put back.
pub fn revert_via_daemon(socket: &Path) -> Result<Reverted> {
    let mut client = Client::connect(socket, Role::Observe, "hgcd check --revert")?;
    client.request_revert()?;
    loop {
        match client.next_reply()? {
            Reply::Reverted(reverted) => return Ok(*reverted),
            Reply::Error { message, .. } => bail!("the daemon refused: {message}"),
            _ => continue,
        }
    }
}

/// Print the progress of the daemon's calibration or check (`what`, whose holds are each a
/// `unit`) on stderr until it ends: its last reply (`finished`, or `checked`).
fn follow(client: &mut Client, what: &str, unit: &str) -> Result<Reply> {
    loop {
        let reply = client.next_reply()?;
        let (event, vertex, of, mass_kg, message) = match &reply {
            Reply::Error { message, .. } => bail!("the daemon refused: {message}"),
            Reply::Checked(_) => return Ok(reply),
            Reply::Calibration {
                event,
                vertex,
                of,
                mass_kg,
                message,
            } => (*event, vertex, of, mass_kg, message),
            _ => continue,
        };
        let position = || format!("{unit} {}/{}", vertex.unwrap_or(0) + 1, of.unwrap_or(0));
        match event {
            CalibrationStage::Started => err(&format!("{what} started on {}\n", client.device)),
            CalibrationStage::InitDone => err(&format!(
                "gravity direction found; rough mass {:.1} g\n",
                mass_kg.unwrap_or(0.0) * 1e3
            )),
            CalibrationStage::VertexDone => err(&format!(
                "{}: {:.2} g{}{}\n",
                position(),
                mass_kg.unwrap_or(0.0) * 1e3,
                if message.is_empty() { "" } else { "; " },
                message
            )),
            CalibrationStage::VertexUnreachable => err(&format!("{}: {message}\n", position())),
            CalibrationStage::TimeSpent => err(&format!("time: {message}\n")),
            CalibrationStage::Stale | CalibrationStage::Other => {}
            CalibrationStage::Finished => return Ok(reply),
            CalibrationStage::Failed => bail!("{what} failed: {message}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The status line names what showed the stale model, the payload, and a tilt where there
    /// is one, in a sentence that agrees with itself.
    #[test]
    fn a_stale_model_is_one_line_naming_its_evidence_payload_and_tilt() {
        let stale = ModelStale {
            payload_g: 30.2,
            sideways_n: 0.0005,
            tilt_deg: 0.0,
            tilt_axis: [0.0; 3],
            device_time_s: 1.2,
            evidence: StaleEvidence::HeldStill,
            auto_updated: false,
        };
        assert_eq!(
            stale_line(&stale),
            "model         STALE: an application held the handle with the same force at 1.2 s; \
             a payload of +30.2 g explains it (0.5 mN across gravity); run hgcd check, or \
             calibrate\n"
        );
        let tilted = ModelStale {
            payload_g: -0.03,
            sideways_n: 0.0616,
            tilt_deg: 3.05,
            tilt_axis: [1.0, 0.0, 0.0],
            evidence: StaleEvidence::Released,
            auto_updated: true,
            ..stale
        };
        assert_eq!(
            stale_line(&tilted),
            "model         STALE: a released handle drifted at 1.2 s; a payload of -0.0 g and a \
             tilt of 3.05° explain it (61.6 mN across gravity); taken into the compensation \
             (compensation.auto_update)\n"
        );
    }
}
