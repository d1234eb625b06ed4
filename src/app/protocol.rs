//! Application wire protocol v1 (`docs/app-protocol.md`): newline-delimited JSON over a Unix
//! stream socket. Every request and reply is one JSON object on one line, with a `type` field.
//! Units are SI: metres, newtons, seconds.

use serde::{Deserialize, Serialize};

use crate::mailbox::PublishedState;
use crate::servo::StatsSnapshot;

/// Version a client must name in its `hello`.
pub const APP_PROTOCOL_VERSION: u32 = 1;
/// Longest request line accepted, bytes (newline excluded). Longer lines close the client.
pub const MAX_LINE_LEN: usize = 1024;

/// What a client asks to be.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    /// Wants to render forces (one client at a time).
    Control,
    /// Reads state and status only.
    Observe,
}

/// Client → daemon.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum Request {
    /// Must be the first message.
    Hello {
        version: u32,
        role: Role,
        #[serde(default)]
        name: String,
    },
    /// Set the force offset Z_E, N. `seq` starts at 1 and must increase strictly from one message
    /// to the next.
    SetForce { seq: u64, force: [f64; 3] },
    /// Stream the device state at `rate_hz` (at most the servo rate; 0 stops the stream).
    Subscribe { rate_hz: f64 },
    /// Run the autocalibration now and switch to the new grid when it finishes.
    Calibrate {},
    /// One status reply.
    Status {},
}

/// Daemon → client.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Reply {
    Welcome {
        version: u32,
        /// The role granted (observe when another client already owns the force).
        role: Role,
        client_id: u64,
        device: String,
        device_id: String,
        rate_hz: f64,
    },
    /// One servo tick.
    State(StateSample),
    Status(Box<Status>),
    /// Calibration progress: `event` is started, init_done, vertex_done, finished or failed.
    Calibration {
        event: String,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        vertex: Option<usize>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        of: Option<usize>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        mass_kg: Option<f64>,
        #[serde(default, skip_serializing_if = "String::is_empty")]
        message: String,
    },
    /// The request was refused; the daemon closes the connection after a fatal one.
    Error {
        message: String,
        fatal: bool,
    },
}

/// The device state at one servo tick.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StateSample {
    /// Servo tick number.
    pub tick: u64,
    /// Device time, s.
    pub time: f64,
    /// m.
    pub position: [f64; 3],
    /// FOAW estimate, m/s.
    pub velocity: [f64; 3],
    /// Force the output report carried this tick, N: after the safety layer's magnitude and rate
    /// limits, and zero during a fault.
    pub force: [f64; 3],
    /// Device status flags (HID protocol v1 bits).
    pub flags: u16,
    /// `seq` of the last force offset the servo applied (0: none).
    pub offset_seq: u64,
}

impl From<&PublishedState> for StateSample {
    fn from(p: &PublishedState) -> Self {
        Self {
            tick: p.state.tick,
            time: p.state.time,
            position: p.state.position.into(),
            velocity: p.state.velocity.into(),
            force: p.force.into(),
            flags: p.state.status.bits(),
            offset_seq: p.offset_seq,
        }
    }
}

/// What `hgcd status` shows.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Status {
    pub device: String,
    pub device_id: String,
    /// Grid file in use, if any.
    pub grid: Option<String>,
    /// "scalar", "vector" or "none" (no compensation).
    pub mode: String,
    pub calibrating: bool,
    pub clients: usize,
    /// Name of the client that owns the force, if any.
    pub owner: Option<String>,
    pub uptime_s: f64,
    /// The servo loop's counters (ticks, late, missed, overruns, garbled, watchdog_faults,
    /// worst_compute_us), flattened into the status object.
    #[serde(flatten)]
    pub servo: StatsSnapshot,
}

/// Why a request line was refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RequestError {
    #[error("request is not valid protocol JSON: {0}")]
    Malformed(String),
    #[error("force must be finite and at most {limit} N per axis")]
    ForceOutOfRange { limit: f64 },
    #[error("rate_hz must be between 0 and {limit}")]
    RateOutOfRange { limit: f64 },
}

/// Parse and validate one request line (without its newline).
pub fn parse_request(line: &str, max_force: f64, max_rate: f64) -> Result<Request, RequestError> {
    let request: Request =
        serde_json::from_str(line).map_err(|e| RequestError::Malformed(e.to_string()))?;
    match &request {
        Request::SetForce { seq: 0, .. } => {
            Err(RequestError::Malformed("set_force seq starts at 1".into()))
        }
        Request::SetForce { force, .. }
            if !force.iter().all(|f| f.is_finite() && f.abs() <= max_force) =>
        {
            Err(RequestError::ForceOutOfRange { limit: max_force })
        }
        Request::Subscribe { rate_hz }
            if !(rate_hz.is_finite() && (0.0..=max_rate).contains(rate_hz)) =>
        {
            Err(RequestError::RateOutOfRange { limit: max_rate })
        }
        _ => Ok(request),
    }
}

/// One reply as a line, newline included.
pub fn encode_reply(reply: &Reply) -> String {
    let mut line = serde_json::to_string(reply).expect("replies always serialise");
    line.push('\n');
    line
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn requests_parse_and_validate() {
        assert_eq!(
            parse_request(
                r#"{"type":"hello","version":1,"role":"control","name":"wall"}"#,
                8.0,
                1000.0
            ),
            Ok(Request::Hello {
                version: 1,
                role: Role::Control,
                name: "wall".into()
            })
        );
        assert_eq!(
            parse_request(
                r#"{"type":"set_force","seq":3,"force":[0.1,0,-1]}"#,
                8.0,
                1000.0
            ),
            Ok(Request::SetForce {
                seq: 3,
                force: [0.1, 0.0, -1.0]
            })
        );
        assert!(matches!(
            parse_request(
                r#"{"type":"set_force","seq":3,"force":[100,0,0]}"#,
                8.0,
                1000.0
            ),
            Err(RequestError::ForceOutOfRange { .. })
        ));
        assert!(matches!(
            parse_request(r#"{"type":"subscribe","rate_hz":5000}"#, 8.0, 1000.0),
            Err(RequestError::RateOutOfRange { .. })
        ));
        for bad in [
            "",
            "{",
            r#"{"type":"nope"}"#,
            r#"{"type":"status","extra":1}"#,
            r#"{"type":"set_force","seq":-1,"force":[0,0,0]}"#,
            r#"{"type":"set_force","seq":1,"force":[0,0]}"#,
            r#"{"type":"set_force","seq":0,"force":[0,0,0]}"#,
        ] {
            assert!(
                matches!(
                    parse_request(bad, 8.0, 1000.0),
                    Err(RequestError::Malformed(_))
                ),
                "{bad}"
            );
        }
    }

    #[test]
    fn replies_are_one_line_and_round_trip() {
        let reply = Reply::State(StateSample {
            tick: 7,
            time: 0.007,
            position: [0.0, 0.01, -0.02],
            velocity: [0.0; 3],
            force: [0.0, 0.0, 1.2],
            flags: 1,
            offset_seq: 3,
        });
        let line = encode_reply(&reply);
        assert_eq!(line.matches('\n').count(), 1);
        assert_eq!(serde_json::from_str::<Reply>(line.trim()).unwrap(), reply);
    }
}
