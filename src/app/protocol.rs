//! Application wire protocol v1 (`docs/app-protocol.md`): newline-delimited JSON over a Unix
//! stream socket. Every request and reply is one JSON object on one line, with a `type` field.
//! Units are SI: metres, newtons, seconds.

use std::path::PathBuf;
use std::time::Duration;

use serde::{Deserialize, Serialize};

use crate::config::CompensationMode;
use crate::grid::AppliedRecord;
use crate::mailbox::PublishedState;
use crate::servo::StatsSnapshot;

/// Version a client must name in its `hello`.
pub const APP_PROTOCOL_VERSION: u32 = 1;
/// Longest request line accepted, bytes (newline excluded). Longer lines close the client.
pub const MAX_LINE_LEN: usize = 1024;
/// Longest reply line a client reads, bytes (newline excluded).
pub const MAX_REPLY_LEN: usize = 64 * 1024;
/// How long a client gives a reply line from its first byte to its newline: the daemon writes a
/// line at once, so one trickling in is cut off rather than waited for byte by byte.
pub const REPLY_LINE_TIME: Duration = Duration::from_secs(1);
/// The largest `welcome.rate_hz` a client accepts, Hz (the top of `servo.rate_hz`'s range).
pub const MAX_RATE_HZ: f64 = 10_000.0;
/// The largest `welcome.max_force_n` a client accepts, N (the top of `safety.max_force_n`'s
/// range).
pub const MAX_FORCE_N: f64 = 50.0;
/// The longest `welcome.device` a client accepts, characters (a `socket:PATH` spec holds a path).
pub const MAX_DEVICE_LEN: usize = 4096;
/// The longest `welcome.device_id` a client accepts, characters (it names files).
pub const MAX_DEVICE_ID_LEN: usize = 255;

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
    /// `hgcd check` on the daemon's device against its grid: two holds, then a `checked`
    /// reply; with `apply`, a payload and tilt found are taken into the grid and compensated.
    Check {
        #[serde(default)]
        apply: bool,
    },
    /// `hgcd check --revert` on the daemon's device: put back the model kept beside its grid
    /// (before the last `check --apply` or calibration) and compensate with it at once; a
    /// `reverted` reply. Nothing moves the handle.
    Revert {},
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
        /// The largest force component `set_force` accepts, N (`safety.max_force_n`); the
        /// safety layer also clamps the magnitude of the total force to it.
        max_force_n: f64,
    },
    /// One servo tick.
    State(StateSample),
    Status(Box<Status>),
    /// The answer of a `check`, after its progress as `calibration` events.
    Checked(Box<Check>),
    /// The answer of a `revert`: the model put back, now compensated.
    Reverted(Box<Reverted>),
    /// Calibration progress.
    Calibration {
        event: CalibrationStage,
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
    /// The gravity compensation in `force`, before the safety layer's limits, N: zero while
    /// the daemon compensates nothing (no grid, a calibration, the hold after it). Absent from
    /// a daemon older than this field.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gravity: Option<[f64; 3]>,
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
            gravity: Some(p.gravity.into()),
            flags: p.state.status.bits(),
            offset_seq: p.offset_seq,
        }
    }
}

/// The compensation a daemon applies now: `"none"`, `"scalar"`, `"vector"`, `"arm"` or
/// `"arm_residual"` on the wire.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Compensating {
    /// No grid: the daemon renders the applications' forces only.
    #[default]
    None,
    /// M(X) g v_G from the grid's masses (the paper's model).
    Scalar,
    /// The grid's per-vertex holding forces, interpolated.
    Vector,
    /// The arm model fitted at calibration: the arm's weight through its kinematics.
    Arm,
    /// The arm model plus a lattice of what it left over at the calibrated vertices.
    ArmResidual,
}

impl From<Option<CompensationMode>> for Compensating {
    fn from(mode: Option<CompensationMode>) -> Self {
        match mode {
            None => Self::None,
            Some(CompensationMode::Scalar) => Self::Scalar,
            Some(CompensationMode::Vector) => Self::Vector,
            Some(CompensationMode::Arm) => Self::Arm,
            Some(CompensationMode::ArmResidual) => Self::ArmResidual,
        }
    }
}

impl Compensating {
    /// What the mode means, in a few words for people.
    pub fn meaning(self) -> &'static str {
        match self {
            Self::Scalar => {
                "the weight M(X)·g of the grid's masses, along gravity (the paper's model)"
            }
            Self::Vector => "the holding forces the calibration measured, interpolated",
            Self::Arm => {
                "the arm's weight through its kinematics, fitted to the calibration's holds"
            }
            Self::ArmResidual => {
                "the arm model plus what it left over at the calibrated vertices, interpolated"
            }
            Self::None => "no grid: the handle's own weight is not compensated",
        }
    }
}

impl std::fmt::Display for Compensating {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::None => "none",
            Self::Scalar => "scalar",
            Self::Vector => "vector",
            Self::Arm => "arm",
            Self::ArmResidual => "arm_residual",
        })
    }
}

/// Where a calibration requested over the socket is (`docs/app-protocol.md`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CalibrationStage {
    /// The servo thread took the calibration over.
    Started,
    /// Gravity direction and first mass found (`mass_kg`).
    InitDone,
    /// Vertex `vertex` of `of` measured (`mass_kg`).
    VertexDone,
    /// Vertex `vertex` of `of` could not be measured (`message` says why): its values are filled
    /// from its neighbours and the calibration goes on.
    VertexUnreachable,
    /// The run is over; `message` says where its device time went.
    TimeSpent,
    /// The grid is saved (`message` is its path) and compensation uses it.
    Finished,
    /// The calibration stopped (`message` says why); the previous grid is untouched.
    Failed,
    /// Not a calibration's: the daemon noticed in use that its gravity model no longer fits
    /// the device (a released handle that keeps sinking or rising); `mass_kg` is the payload
    /// that would explain it, `message` says more (docs/calibration.md §2.3). Once per model.
    Stale,
    /// An event this client does not know (a newer daemon's): to be ignored.
    #[serde(other)]
    Other,
}

/// What `hgcd status` shows.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Status {
    pub device: String,
    pub device_id: String,
    /// Grid file in use, if any.
    pub grid: Option<String>,
    /// The compensation applied now.
    pub mode: Compensating,
    /// Its score on the holds the calibration kept out of every fit, % (null for a grid that
    /// has none: one calibrated without an arm model, or by an older version).
    #[serde(default)]
    pub held_out_pct: Option<f64>,
    pub calibrating: bool,
    pub clients: usize,
    /// Name of the client that owns the force, if any.
    pub owner: Option<String>,
    pub uptime_s: f64,
    /// What the daemon noticed in use against its gravity model, since it loaded it (null:
    /// nothing).
    #[serde(default)]
    pub model_stale: Option<ModelStale>,
    /// The servo loop's counters, flattened into the status object.
    #[serde(flatten)]
    pub servo: StatsSnapshot,
}

/// A force the gravity model misses, as the daemon read it in use (docs/calibration.md §2.3).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelStale {
    /// The payload that explains the force along gravity the model misses, g (negative: the
    /// handle is lighter than the model holds).
    pub payload_g: f64,
    /// What the model misses across gravity, N (a tilt, a spring, a cable).
    pub sideways_n: f64,
    /// That force read as gravity turned: by this angle, degrees, about `tilt_axis` (a unit
    /// vector in the device's frame; zero with no tilt).
    #[serde(default)]
    pub tilt_deg: f64,
    #[serde(default)]
    pub tilt_axis: [f64; 3],
    /// Device time when it was noticed, s.
    pub device_time_s: f64,
    /// What showed it.
    #[serde(default)]
    pub evidence: StaleEvidence,
    /// The payload and tilt were taken into the compensation (`compensation.auto_update`).
    pub auto_updated: bool,
}

impl ModelStale {
    /// A tilt smaller than this is not named where the model is said to be stale, degrees.
    pub const NAMED_TILT_DEG: f64 = 0.05;
}

/// How a force the model misses showed in use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StaleEvidence {
    /// The released handle kept accelerating (sinking, for a payload added).
    #[default]
    Released,
    /// An application's force held the handle still at three places with the same offset.
    HeldStill,
}

// `hgcd check`'s answer, as `--json` prints it and the daemon replies it (`Reply::Checked`).

/// The answer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Verdict {
    /// Every hold agrees with the model.
    Unchanged,
    /// A payload and a tilt explain what changed (`--apply` can take them in).
    Apply,
    /// Something a payload and a tilt do not explain: calibrate again.
    Recalibrate,
}

/// One hold: where, what it measured, what the model says there (N).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Hold {
    pub position_m: [f64; 3],
    pub measured_n: [f64; 3],
    pub model_n: [f64; 3],
    /// What the payload and tilt found leave of the difference, N.
    pub unexplained_n: f64,
    /// The agreement asked of this hold (`calibrate::check::TOLERANCE_SHARE`, `TOLERANCE_MIN`), N.
    pub tolerance_n: f64,
}

/// What a check found.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Check {
    pub verdict: Verdict,
    /// The payload's mass found, g (negative: something was taken off the handle).
    pub payload_g: f64,
    /// The base's tilt found, degrees, about `tilt_axis` (a unit vector of the device frame).
    pub tilt_deg: f64,
    pub tilt_axis: [f64; 3],
    pub holds: Vec<Hold>,
    pub device_time_s: f64,
    /// The grid checked.
    pub grid: PathBuf,
    /// Where the model before `--apply` was kept, once the change was taken in.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub applied: Option<PathBuf>,
    /// What the user should know of the change applied, for people (absent when nothing).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub warning: Option<String>,
}

/// What `hgcd check --revert` put back (the `reverted` reply, or printed).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Reverted {
    pub grid: PathBuf,
    /// The changes taken into the model put back, and into the one it replaced.
    pub applied_now: Vec<AppliedRecord>,
    pub applied_before: Vec<AppliedRecord>,
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
///
/// Errors: [`RequestError::Malformed`] for text that is not a request; `ForceOutOfRange` or
/// `RateOutOfRange` for values beyond `max_force` (N per axis) or `max_rate` (Hz).
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
    use crate::protocol::fuzz;
    use proptest::prelude::*;
    use serde_json::{json, Value};

    /// The names `docs/app-protocol.md` gives the modes and calibration events, and nothing else.
    #[test]
    fn modes_and_calibration_stages_have_their_documented_names() {
        use CalibrationStage::*;
        for (mode, name) in [
            (Compensating::None, "none"),
            (Compensating::Scalar, "scalar"),
            (Compensating::Vector, "vector"),
            (Compensating::Arm, "arm"),
            (Compensating::ArmResidual, "arm_residual"),
        ] {
            assert_eq!(serde_json::to_value(mode).unwrap(), json!(name));
            assert_eq!(mode.to_string(), name);
        }
        for (stage, name) in [
            (Started, "started"),
            (InitDone, "init_done"),
            (VertexDone, "vertex_done"),
            (VertexUnreachable, "vertex_unreachable"),
            (TimeSpent, "time_spent"),
            (Finished, "finished"),
            (Failed, "failed"),
            (Stale, "stale"),
        ] {
            assert_eq!(serde_json::to_value(stage).unwrap(), json!(name));
        }
        // Clients ignore the events they do not know (a newer daemon's).
        let unknown = r#"{"type":"calibration","event":"halfway","message":"x"}"#;
        assert!(matches!(
            serde_json::from_str::<Reply>(unknown).unwrap(),
            Reply::Calibration { event: Other, .. }
        ));
    }

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
            gravity: Some([0.0, 0.0, 1.1]),
            flags: 1,
            offset_seq: 3,
        });
        let line = encode_reply(&reply);
        assert_eq!(line.matches('\n').count(), 1);
        assert_eq!(serde_json::from_str::<Reply>(line.trim()).unwrap(), reply);
    }

    const MAX_FORCE: f64 = 8.0;
    const MAX_RATE: f64 = 1000.0;

    /// Parse `line`; whatever is accepted must be within the daemon's limits.
    fn check_line(line: &str) -> Result<Option<Request>, TestCaseError> {
        let parsed = parse_request(line, MAX_FORCE, MAX_RATE);
        if let Ok(request) = &parsed {
            match request {
                Request::SetForce { seq, force } => {
                    prop_assert!(*seq >= 1);
                    prop_assert!(force.iter().all(|f| f.is_finite() && f.abs() <= MAX_FORCE));
                }
                Request::Subscribe { rate_hz } => {
                    prop_assert!(rate_hz.is_finite() && (0.0..=MAX_RATE).contains(rate_hz));
                }
                Request::Hello { .. }
                | Request::Calibrate {}
                | Request::Check { .. }
                | Request::Revert {}
                | Request::Status {} => {}
            }
        }
        Ok(parsed.ok())
    }

    /// Requests the daemon accepts: every type, every field, values up to the limits.
    fn valid_request() -> impl Strategy<Value = Request> {
        let role = prop_oneof![Just(Role::Control), Just(Role::Observe)];
        let force = prop_oneof![
            -MAX_FORCE..=MAX_FORCE,
            Just(MAX_FORCE),
            Just(-MAX_FORCE),
            Just(0.0),
            Just(-0.0),
            Just(f64::MIN_POSITIVE),
        ];
        prop_oneof![
            (any::<u32>(), role, ".{0,80}").prop_map(|(version, role, name)| Request::Hello {
                version,
                role,
                name
            }),
            (1..=u64::MAX, [force.clone(), force.clone(), force])
                .prop_map(|(seq, force)| Request::SetForce { seq, force }),
            prop_oneof![0.0..=MAX_RATE, Just(0.0), Just(MAX_RATE)]
                .prop_map(|rate_hz| Request::Subscribe { rate_hz }),
            Just(Request::Calibrate {}),
            any::<bool>().prop_map(|apply| Request::Check { apply }),
            Just(Request::Revert {}),
            Just(Request::Status {}),
        ]
    }

    /// Any JSON value, nested a little, with numbers at and beyond the edges of what fits.
    fn json_value() -> impl Strategy<Value = Value> {
        let leaf = prop_oneof![
            Just(Value::Null),
            any::<bool>().prop_map(Value::from),
            any::<i64>().prop_map(Value::from),
            any::<u64>().prop_map(Value::from),
            any::<f64>().prop_map(Value::from),
            prop_oneof![
                Just(-0.0),
                Just(8.0),
                Just(8.000001),
                Just(1000.0),
                Just(1e308)
            ]
            .prop_map(Value::from),
            prop_oneof![
                Just("control"),
                Just("observe"),
                Just("status"),
                Just("set_force")
            ]
            .prop_map(Value::from),
            ".{0,12}".prop_map(Value::from),
        ];
        leaf.prop_recursive(3, 16, 4, |inner| {
            prop_oneof![
                proptest::collection::vec(inner.clone(), 0..5).prop_map(Value::from),
                proptest::collection::btree_map(".{0,8}", inner, 0..3)
                    .prop_map(|m| Value::Object(m.into_iter().collect())),
            ]
        })
    }

    /// A number near the scales and limits of the requests' fields.
    fn number() -> impl Strategy<Value = Value> {
        prop_oneof![
            -10.0..10.0f64,
            -1100.0..1100.0f64,
            prop::sample::select(vec![
                -0.0,
                8.0,
                -8.0,
                8.000001,
                1000.0,
                1000.000001,
                -1e-300
            ]),
        ]
        .prop_map(Value::from)
    }

    /// A value of the type `field` has, mostly in range.
    fn plausible(field: &str) -> BoxedStrategy<Value> {
        match field {
            "version" => prop_oneof![Just(1u64), 0..3u64]
                .prop_map(Value::from)
                .boxed(),
            "role" => prop::sample::select(vec!["control", "observe", "admin"])
                .prop_map(Value::from)
                .boxed(),
            "name" => ".{0,70}".prop_map(Value::from).boxed(),
            "seq" => prop_oneof![0..4u64, Just(u64::MAX)]
                .prop_map(Value::from)
                .boxed(),
            "force" => {
                let axis = prop_oneof![3 => (-8.0..=8.0f64).prop_map(Value::from), 1 => number()];
                prop_oneof![
                    3 => proptest::collection::vec(axis.clone(), 3),
                    1 => proptest::collection::vec(axis, 0..=4),
                ]
                .prop_map(Value::from)
                .boxed()
            }
            _ => number().boxed(),
        }
    }

    /// Objects shaped like requests: mostly a known type with mostly its own fields, values
    /// mostly of the right type and near the limits, and now and then anything at all.
    fn request_shaped() -> impl Strategy<Value = String> {
        const TYPES: [(&str, &[&str]); 5] = [
            ("hello", &["version", "role", "name"]),
            ("set_force", &["seq", "force"]),
            ("subscribe", &["rate_hz"]),
            ("calibrate", &[]),
            ("status", &[]),
        ];
        let all_fields = ["version", "role", "name", "seq", "force", "rate_hz"];
        (0..TYPES.len(), any::<bool>())
            .prop_flat_map(move |(t, unknown_type)| {
                let (name, own) = TYPES[t];
                let kind = if unknown_type {
                    prop_oneof![3 => Just(Value::from(name)), 1 => json_value()].boxed()
                } else {
                    Just(Value::from(name)).boxed()
                };
                let fields: Vec<_> = all_fields
                    .iter()
                    .map(|&field| {
                        let present = if own.contains(&field) { 0.8 } else { 0.05 };
                        let value = prop_oneof![4 => plausible(field), 1 => json_value()];
                        proptest::option::weighted(present, value)
                            .prop_map(move |v| v.map(|v| (field.to_string(), v)))
                    })
                    .collect();
                let stranger = proptest::option::weighted(0.05, (".{0,8}", json_value()));
                (kind, fields, stranger)
            })
            .prop_map(|(kind, fields, stranger)| {
                let mut object = serde_json::Map::new();
                object.insert("type".into(), kind);
                object.extend(fields.into_iter().flatten().chain(stranger));
                Value::Object(object).to_string()
            })
    }

    /// `line` with a few bytes replaced, inserted or removed, biased towards JSON syntax.
    fn mutated(line: impl Strategy<Value = String>) -> impl Strategy<Value = String> {
        let byte = prop_oneof![
            prop::sample::select(b"{}[]\",:.-+eE0123456789 tfn\\u".to_vec()),
            any::<u8>(),
        ];
        let edit = (0u8..3, any::<prop::sample::Index>(), byte);
        (line, proptest::collection::vec(edit, 1..4)).prop_map(|(line, edits)| {
            let mut bytes = line.into_bytes();
            for (kind, at, b) in edits {
                let i = at.index(bytes.len() + 1);
                match kind {
                    0 if i < bytes.len() => bytes[i] = b,
                    1 => bytes.insert(i, b),
                    _ if i < bytes.len() => {
                        bytes.remove(i);
                    }
                    _ => bytes.push(b),
                }
            }
            String::from_utf8_lossy(&bytes).into_owned()
        })
    }

    fn request_line(request: &Request) -> String {
        serde_json::to_string(request).unwrap()
    }

    proptest! {
        #![proptest_config(fuzz::config())]

        #[test]
        fn arbitrary_text_is_refused_or_in_range(line in ".{0,200}") {
            check_line(&line)?;
        }

        #[test]
        fn arbitrary_bytes_are_refused_or_in_range(
            bytes in proptest::collection::vec(any::<u8>(), 0..=MAX_LINE_LEN)
        ) {
            check_line(&String::from_utf8_lossy(&bytes))?;
        }

        #[test]
        fn request_shaped_objects_are_refused_or_in_range(line in request_shaped()) {
            check_line(&line)?;
        }

        #[test]
        fn mutated_requests_are_refused_or_in_range(
            line in mutated(valid_request().prop_map(|r| request_line(&r)))
        ) {
            check_line(&line)?;
        }

        #[test]
        fn valid_requests_round_trip(request in valid_request()) {
            let parsed = check_line(&request_line(&request))?;
            prop_assert_eq!(parsed, Some(request));
        }

        #[test]
        fn forces_and_rates_beyond_the_limits_are_refused(
            seq in 1..=u64::MAX,
            axis in 0usize..3,
            beyond in prop_oneof![
                (MAX_FORCE..1e308).prop_filter("beyond", |f| *f > MAX_FORCE),
                Just(f64::MAX)
            ],
            negative in any::<bool>(),
            rate in (MAX_RATE..1e308).prop_filter("beyond", |r| *r > MAX_RATE),
        ) {
            let mut force = [0.0; 3];
            force[axis] = if negative { -beyond } else { beyond };
            prop_assert_eq!(
                parse_request(&json!({"type": "set_force", "seq": seq, "force": force}).to_string(),
                              MAX_FORCE, MAX_RATE),
                Err(RequestError::ForceOutOfRange { limit: MAX_FORCE })
            );
            for rate_hz in [rate, -rate, -f64::MIN_POSITIVE] {
                prop_assert_eq!(
                    parse_request(&json!({"type": "subscribe", "rate_hz": rate_hz}).to_string(),
                                  MAX_FORCE, MAX_RATE),
                    Err(RequestError::RateOutOfRange { limit: MAX_RATE })
                );
            }
        }
    }
}
