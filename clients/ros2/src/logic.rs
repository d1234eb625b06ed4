//! The bridge's decisions, without DDS or sockets: ROS names from device ids, which `servo_cf`
//! wrenches are taken, when a silent stream is released, how often a refusal is logged.

use std::time::{Duration, Instant};

use nalgebra::Vector3;

use crate::msgs::WrenchStamped;

/// A device id made a ROS 2 name token: letters, digits and single underscores, not starting
/// with a digit (`sim-point-mass` → `sim_point_mass`, `1209-4847` → `_1209_4847`).
pub fn name_token(device_id: &str) -> String {
    let mut token = String::with_capacity(device_id.len() + 1);
    for c in device_id.chars() {
        let c = if c.is_ascii_alphanumeric() { c } else { '_' };
        if !(c == '_' && token.ends_with('_')) {
            token.push(c);
        }
    }
    if token.is_empty() || token.starts_with(|c: char| c.is_ascii_digit()) {
        token.insert(0, '_');
    }
    token
}

/// The default namespace of a device's topics: `/hgcd/<device id as a name token>`.
pub fn default_namespace(device_id: &str) -> String {
    format!("/hgcd/{}", name_token(device_id))
}

/// Why a `servo_cf` wrench was refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum Refusal {
    #[error(
        "servo_cf refused: frame {got:?}, but this bridge takes wrenches in the device frame \
         {want:?} only (set header.frame_id)"
    )]
    Frame { got: String, want: String },
    #[error("servo_cf refused: a component is not finite (NaN or infinite)")]
    NotFinite,
    #[error(
        "servo_cf refused: force component {value} N beyond the daemon's limit of {limit} N per \
         axis"
    )]
    TooLarge { value: f64, limit: f64 },
}

impl Refusal {
    /// The kind of refusal, for counting them apart.
    pub fn kind(&self) -> usize {
        match self {
            Refusal::Frame { .. } => 0,
            Refusal::NotFinite => 1,
            Refusal::TooLarge { .. } => 2,
        }
    }
}

/// The force offset a `servo_cf` message asks for, N, or why it is refused: its frame must be
/// `frame_id`, every component finite, and each force component at most `max_force` (the
/// daemon's per-axis limit, which it would otherwise answer by closing the connection). The
/// torque of a 3-DoF device is not rendered: it is checked to be finite and otherwise ignored.
pub fn wrench_offset(
    msg: &WrenchStamped,
    frame_id: &str,
    max_force: f64,
) -> Result<Vector3<f64>, Refusal> {
    if msg.header.frame_id != frame_id {
        return Err(Refusal::Frame {
            got: msg.header.frame_id.clone(),
            want: frame_id.to_string(),
        });
    }
    let (f, t) = (msg.wrench.force, msg.wrench.torque);
    let force = Vector3::new(f.x, f.y, f.z);
    if !(force.iter().all(|v| v.is_finite()) && [t.x, t.y, t.z].iter().all(|v| v.is_finite())) {
        return Err(Refusal::NotFinite);
    }
    if let Some(&value) = force.iter().find(|v| v.abs() > max_force) {
        return Err(Refusal::TooLarge {
            value,
            limit: max_force,
        });
    }
    Ok(force)
}

/// What to send the daemon now.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Send {
    /// This offset (a new one, or the held one again so the daemon does not take it as stale).
    Offset(Vector3<f64>),
    /// Zero: the stream went silent for longer than the timeout.
    Release,
}

/// The offset a `servo_cf` stream holds: the newest wrench taken, until the stream is silent for
/// `timeout`; meanwhile it is sent again every `refresh` so that the daemon's own staleness
/// limit (`app.stale_offset_ms`) never ramps a live stream down.
#[derive(Debug)]
pub struct Hold {
    timeout: Duration,
    refresh: Duration,
    /// The offset held, when it was received and when it was last sent.
    held: Option<(Vector3<f64>, Instant, Instant)>,
}

impl Hold {
    pub fn new(timeout: Duration, refresh: Duration) -> Self {
        Self {
            timeout,
            refresh,
            held: None,
        }
    }

    /// A wrench taken at `now`: send it.
    pub fn received(&mut self, force: Vector3<f64>, now: Instant) -> Send {
        self.held = Some((force, now, now));
        Send::Offset(force)
    }

    /// What is due at `now` without a new wrench: the release once the stream has been silent
    /// for the timeout, the held offset again after `refresh`, else nothing.
    pub fn due(&mut self, now: Instant) -> Option<Send> {
        let (force, received, sent) = self.held?;
        if now.duration_since(received) >= self.timeout {
            self.held = None;
            Some(Send::Release)
        } else if now.duration_since(sent) >= self.refresh {
            self.held = Some((force, received, now));
            Some(Send::Offset(force))
        } else {
            None
        }
    }

    /// When [`Hold::due`] next has something to do (None: nothing held).
    pub fn next_due(&self) -> Option<Instant> {
        let (_, received, sent) = self.held?;
        Some((received + self.timeout).min(sent + self.refresh))
    }
}

/// At most one log line per `period` for one kind of event; the lines in between are counted
/// and the count given with the next one.
#[derive(Debug)]
pub struct Throttle {
    period: Duration,
    last: Option<Instant>,
    suppressed: u64,
}

impl Throttle {
    pub fn new(period: Duration) -> Self {
        Self {
            period,
            last: None,
            suppressed: 0,
        }
    }

    /// Some(number suppressed since the last line) when a line may be logged at `now`.
    pub fn allow(&mut self, now: Instant) -> Option<u64> {
        match self.last {
            Some(last) if now.duration_since(last) < self.period => {
                self.suppressed += 1;
                None
            }
            _ => {
                self.last = Some(now);
                Some(std::mem::take(&mut self.suppressed))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{Header, Vector3 as V3, Wrench};

    fn wrench(frame: &str, force: [f64; 3], torque: [f64; 3]) -> WrenchStamped {
        WrenchStamped {
            header: Header {
                frame_id: frame.into(),
                ..Default::default()
            },
            wrench: Wrench {
                force: V3::from(force),
                torque: V3::from(torque),
            },
        }
    }

    #[test]
    fn names_are_ros_tokens() {
        assert_eq!(name_token("sim-point-mass"), "sim_point_mass");
        assert_eq!(name_token("Omega-SN0042"), "Omega_SN0042");
        assert_eq!(name_token("1209-4847"), "_1209_4847");
        assert_eq!(name_token("a--b__c"), "a_b_c");
        assert_eq!(default_namespace("sim-point-mass"), "/hgcd/sim_point_mass");
        for id in ["sim-point-mass", "1209-4847", "a--b__c", "x"] {
            let ns = default_namespace(id);
            assert!(
                ros2_client::Name::new(&ns, "measured_cp").is_ok(),
                "{ns} is a namespace ROS 2 takes"
            );
        }
    }

    #[test]
    fn only_finite_bounded_wrenches_in_the_device_frame() {
        let ok = wrench("dev", [0.5, -1.0, 8.0], [0.1, 0.0, 0.0]);
        assert_eq!(
            wrench_offset(&ok, "dev", 8.0),
            Ok(Vector3::new(0.5, -1.0, 8.0))
        );
        for frame in ["", "world", "dev "] {
            let bad = wrench(frame, [0.0; 3], [0.0; 3]);
            assert!(matches!(
                wrench_offset(&bad, "dev", 8.0),
                Err(Refusal::Frame { .. })
            ));
        }
        for bad in [
            wrench("dev", [f64::NAN, 0.0, 0.0], [0.0; 3]),
            wrench("dev", [0.0, f64::INFINITY, 0.0], [0.0; 3]),
            wrench("dev", [0.0; 3], [0.0, 0.0, f64::NAN]),
        ] {
            assert_eq!(wrench_offset(&bad, "dev", 8.0), Err(Refusal::NotFinite));
        }
        let huge = wrench("dev", [0.0, 0.0, -8.001], [0.0; 3]);
        assert_eq!(
            wrench_offset(&huge, "dev", 8.0),
            Err(Refusal::TooLarge {
                value: -8.001,
                limit: 8.0
            })
        );
        assert!(Refusal::NotFinite
            .to_string()
            .starts_with("servo_cf refused"));
    }

    #[test]
    fn a_silent_stream_is_released_after_the_timeout_and_refreshed_before() {
        let t0 = Instant::now();
        let ms = |n: u64| t0 + Duration::from_millis(n);
        let f = Vector3::new(0.0, 0.0, 1.0);
        let mut hold = Hold::new(Duration::from_millis(50), Duration::from_millis(20));
        assert_eq!(hold.due(ms(0)), None, "nothing held");
        assert_eq!(hold.next_due(), None);
        assert_eq!(hold.received(f, ms(0)), Send::Offset(f));
        assert_eq!(hold.next_due(), Some(ms(20)));
        assert_eq!(hold.due(ms(10)), None);
        assert_eq!(hold.due(ms(20)), Some(Send::Offset(f)), "refreshed");
        assert_eq!(hold.next_due(), Some(ms(40)));
        assert_eq!(hold.due(ms(40)), Some(Send::Offset(f)));
        assert_eq!(hold.next_due(), Some(ms(50)), "the timeout comes first");
        assert_eq!(hold.due(ms(49)), None);
        assert_eq!(hold.due(ms(50)), Some(Send::Release));
        assert_eq!(hold.due(ms(60)), None, "released once");
        assert_eq!(hold.next_due(), None);
        // A new wrench starts a new hold.
        hold.received(f, ms(70));
        assert!(hold.due(ms(119)).is_some_and(|s| s != Send::Release));
        assert_eq!(hold.due(ms(120)), Some(Send::Release));
    }

    #[test]
    fn throttled_lines_are_counted() {
        let t0 = Instant::now();
        let mut t = Throttle::new(Duration::from_secs(1));
        assert_eq!(t.allow(t0), Some(0));
        assert_eq!(t.allow(t0 + Duration::from_millis(1)), None);
        assert_eq!(t.allow(t0 + Duration::from_millis(999)), None);
        assert_eq!(t.allow(t0 + Duration::from_millis(1000)), Some(2));
        assert_eq!(t.allow(t0 + Duration::from_millis(2500)), Some(0));
    }
}
