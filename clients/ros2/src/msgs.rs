//! The ROS 2 message and service types the bridge speaks, laid out field for field as their
//! `.msg`/`.srv` files define them, so that their CDR encoding is the one every ROS 2 node (and
//! any DDS implementation given the same IDL) reads. The DDS type names follow from the package
//! and type names: `geometry_msgs::msg::dds_::PoseStamped_`.

use std::time::{SystemTime, UNIX_EPOCH};

use ros2_client::Message;
use serde::{Deserialize, Serialize};

/// builtin_interfaces/Time.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// The system clock now, as ROS 2 stamps messages (seconds since the Unix epoch).
    pub fn now() -> Self {
        let since = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .unwrap_or_default();
        Self {
            sec: i32::try_from(since.as_secs()).unwrap_or(i32::MAX),
            nanosec: since.subsec_nanos(),
        }
    }
}

/// std_msgs/Header.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// geometry_msgs/Vector3 (also the layout of geometry_msgs/Point).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl From<[f64; 3]> for Vector3 {
    fn from([x, y, z]: [f64; 3]) -> Self {
        Self { x, y, z }
    }
}

/// geometry_msgs/Quaternion.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Quaternion {
    pub const IDENTITY: Self = Self {
        x: 0.0,
        y: 0.0,
        z: 0.0,
        w: 1.0,
    };
}

/// geometry_msgs/Pose.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub position: Vector3,
    pub orientation: Quaternion,
}

/// geometry_msgs/PoseStamped.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Pose,
}
impl Message for PoseStamped {}

/// geometry_msgs/Twist.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Twist {
    pub linear: Vector3,
    pub angular: Vector3,
}

/// geometry_msgs/TwistStamped.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TwistStamped {
    pub header: Header,
    pub twist: Twist,
}
impl Message for TwistStamped {}

/// geometry_msgs/Wrench.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Wrench {
    pub force: Vector3,
    pub torque: Vector3,
}

/// geometry_msgs/WrenchStamped.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WrenchStamped {
    pub header: Header,
    pub wrench: Wrench,
}
impl Message for WrenchStamped {}

/// std_msgs/String.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StringMsg {
    pub data: String,
}
impl Message for StringMsg {}

/// std_srvs/Trigger request. The request has no field; ROS 2's IDL gives every empty structure
/// this one byte.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TriggerRequest {
    pub structure_needs_at_least_one_member: u8,
}
impl Message for TriggerRequest {}

/// std_srvs/Trigger response.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TriggerResponse {
    pub success: bool,
    pub message: String,
}
impl Message for TriggerResponse {}
