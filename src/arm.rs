//! Arms whose kinematics the host knows, and the force their own weight puts on the handle.
//!
//! For rigid links the potential energy is U(q) = g v_G · Σᵢ mᵢ pᵢ(q) (v_G up, against gravity),
//! and every body's Σ m p is its mass times its joint's position plus its first moment (mass
//! times centre-of-mass offset) turned with the body. Each arm below writes Σ m p as Σₖ θₖ bₖ(q):
//! bₖ a unit direction fixed in one body, θₖ a first moment (kg m) or, for a platform that only
//! translates, a mass (kg). The torque that holds the arm is then linear in θ,
//!
//!   τ(q) = ∂U/∂q = Y(q, v_G) θ,   Y[:, k] = g (∂bₖ/∂q)ᵀ v_G,
//!
//! and the force that holds the handle is F = J⁻ᵀ τ: the base parameters θ and the gravity
//! direction fix the holding force everywhere the handle can go. [`Arm::force_regressor`] gives
//! ∂F/∂θ at a reported position; [`ArmGravity`] evaluates F on the servo thread.
//!
//! Two arms are known:
//! - [`SerialArm`]: a base turning about the vertical (ψ), an upper arm pitching at the shoulder
//!   (α, from the horizontal) and a forearm whose absolute pitch is a joint of its own (β, the
//!   forearm pointing (sin β, −cos β) outward and up from the elbow), as on a PHANToM's
//!   parallelogram or a WoodenHaptics arm's capstans. Six base parameters: the first moments
//!   along and across the upper arm and the forearm, and the base's radial and lateral moments
//!   (these act only when the base is tilted).
//! - [`DeltaArm`]: three rotary arms on a fixed base, each with a parallelogram of rods down to a
//!   platform that only translates (a Falcon or an Omega.3). Seven: each arm's first moment along
//!   and across it (half its rods' mass rides on its elbow) and the platform's mass (the other
//!   halves, the grip and any payload).
//!
//! The host's joint angles are its own: the force at the handle does not depend on how the
//! device numbers its joints. Everything here is plain arithmetic on the stack.

use nalgebra::{Matrix3, SMatrix, Vector3};
use serde::{Deserialize, Serialize};

/// The most base parameters an arm has.
pub const MAX_PARAMETERS: usize = 7;

/// ∂F/∂θ at one position: the holding force per unit of each base parameter, N per kg m
/// (columns past [`Arm::parameter_count`] are zero).
pub type ForceRegressor = SMatrix<f64, 3, MAX_PARAMETERS>;

/// Damping of J⁻ᵀ near singular poses: F = J (JᵀJ + λ² I)⁻¹ τ. The pose's quality is
/// 3√3 |det J| / ‖J‖³ (Frobenius norm): 1 where J's singular values are equal, about
/// 1.8 σ_min / σ_max where one of them vanishes, whichever it is (a stretched serial arm, a serial
/// handle on its yaw axis, a delta's arm in line with its rod). Below [`SINGULAR_QUALITY`] λ grows
/// from 0 to this share of ‖J‖ at the singularity, where it bounds |F| by |τ| / (2 λ); above it
/// F = J⁻ᵀ τ exactly.
const SINGULAR_DAMPING: f64 = 0.05;
const SINGULAR_QUALITY: f64 = 0.05;

/// A yaw–pitch–pitch arm (see the module's doc), in its own frame: z up along the yaw axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SerialArm {
    /// The shoulder: where the upper arm pitches, on the yaw axis, m.
    pub shoulder: Vector3<f64>,
    /// Shoulder to elbow, m.
    pub upper: f64,
    /// Elbow to handle, m.
    pub fore: f64,
}

/// A rotary delta (see the module's doc), in its own frame: z up along its axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DeltaArm {
    /// Pivot to elbow, m.
    pub arm: f64,
    /// Elbow to platform (the parallelogram's rods), m.
    pub rod: f64,
    /// Pivots' radius about the axis, m.
    pub base_radius: f64,
    /// Radius of the rods' platform joints about the platform's centre, m.
    pub platform_radius: f64,
    /// Height of the pivots' plane above the frame's origin, m.
    pub pivot_height: f64,
    /// Each leg's direction in the horizontal plane, rad from x toward y.
    pub legs: [f64; 3],
}

/// The geometry of an arm the host knows.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ArmGeometry {
    Serial(SerialArm),
    Delta(DeltaArm),
}

/// Where the arm's own frame sits in the device's report frame: x_device = axes (x_arm − origin).
/// `axes` is a signed permutation (each row one ±unit vector), so forces turn the same way.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ArmFrame {
    pub axes: Matrix3<f64>,
    /// The arm-frame point that is the device frame's origin, m.
    pub origin: Vector3<f64>,
}

impl ArmFrame {
    /// The same axes, origins apart.
    pub fn offset(origin: Vector3<f64>) -> Self {
        Self {
            axes: Matrix3::identity(),
            origin,
        }
    }

    fn arm_point(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.axes.transpose() * x + self.origin
    }
}

/// An arm placed in the device's frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Arm {
    pub geometry: ArmGeometry,
    pub frame: ArmFrame,
}

/// How far a unit may sit from its profile (a profile's `[geometry_tolerances]`,
/// docs/devices.md). A tolerance of 0 keeps that part of the profile's geometry as it is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GeometryTolerances {
    /// The frame's origin, per axis, m.
    pub origin: f64,
    /// Each link's length, relative.
    pub length: f64,
    /// The delta's pivots' radius about its axis (the base less the platform radius), m.
    pub radius: f64,
}

impl GeometryTolerances {
    /// Where a profile says nothing: a unit made to the published drawings by ordinary
    /// machining and assembly (the simulated units' spread: 1 mm, 0.5 %, 0.5 mm).
    pub const DEFAULT: Self = Self {
        origin: 1e-3,
        length: 5e-3,
        radius: 0.5e-3,
    };

    /// Whether nothing may move: the profile's geometry is the unit's.
    pub fn exact(&self) -> bool {
        self.origin == 0.0 && self.length == 0.0 && self.radius == 0.0
    }
}

impl Default for GeometryTolerances {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// Names of the serial arm's base parameters, in order.
const SERIAL_PARAMETERS: [&str; 6] = [
    "upper arm, along",
    "upper arm, across",
    "forearm, along",
    "forearm, across",
    "base, radial",
    "base, lateral",
];

/// Names of the delta's base parameters, in order.
const DELTA_PARAMETERS: [&str; 7] = [
    "arm 1, along",
    "arm 1, across",
    "arm 2, along",
    "arm 2, across",
    "arm 3, along",
    "arm 3, across",
    "platform mass",
];

impl Arm {
    /// How many base parameters its gravity has.
    pub fn parameter_count(&self) -> usize {
        self.parameter_names().len()
    }

    /// The base parameters' names, in order (first moments in kg m, the platform's mass in kg).
    pub fn parameter_names(&self) -> &'static [&'static str] {
        match self.geometry {
            ArmGeometry::Serial(_) => &SERIAL_PARAMETERS,
            ArmGeometry::Delta(_) => &DELTA_PARAMETERS,
        }
    }

    /// Which arm, in a word (`serial` or `delta`).
    pub fn kind(&self) -> &'static str {
        match self.geometry {
            ArmGeometry::Serial(_) => "serial",
            ArmGeometry::Delta(_) => "delta",
        }
    }

    /// The arm's up (its z axis) in the device frame: the gravity direction of a level base.
    pub fn up(&self) -> Vector3<f64> {
        self.frame.axes * Vector3::z()
    }

    /// Whether the handle can be at `x` (device frame, m).
    pub fn reaches(&self, x: &Vector3<f64>) -> bool {
        self.joints_at(x).is_some()
    }

    /// The host's joint angles with the handle at `x` (device frame, m); None out of reach.
    pub fn joints_at(&self, x: &Vector3<f64>) -> Option<Vector3<f64>> {
        let p = self.frame.arm_point(x);
        match &self.geometry {
            ArmGeometry::Serial(a) => a.joints_at(&p),
            ArmGeometry::Delta(a) => a.joints_at(&p),
        }
    }

    /// The handle's position (device frame, m) at joint angles `q`.
    pub fn handle(&self, q: &Vector3<f64>) -> Vector3<f64> {
        let p = match &self.geometry {
            ArmGeometry::Serial(a) => a.handle(q).0,
            ArmGeometry::Delta(a) => a.platform(q),
        };
        self.frame.axes * (p - self.frame.origin)
    }

    /// ∂x/∂q at `x` (device frame, per radian of each joint); None out of reach or singular.
    pub fn jacobian(&self, x: &Vector3<f64>) -> Option<Matrix3<f64>> {
        let p = self.frame.arm_point(x);
        let jacobian = match &self.geometry {
            ArmGeometry::Serial(a) => a.handle(&a.joints_at(&p)?).1,
            ArmGeometry::Delta(a) => a.jacobian(&a.joints_at(&p)?)?,
        };
        Some(self.frame.axes * jacobian)
    }

    /// J⁻ᵀ at `x`: the handle force (device frame) that joint torques τ need is J⁻ᵀ τ. None out
    /// of reach or singular.
    pub fn to_handle(&self, x: &Vector3<f64>) -> Option<Matrix3<f64>> {
        Some(self.jacobian(x)?.try_inverse()?.transpose())
    }

    /// ∂F/∂θ at `x` (device frame) for gravity `g` (m/s²) against the unit `up` (device frame):
    /// F = G θ is the force that holds the handle there. None out of reach.
    pub fn force_regressor(
        &self,
        x: &Vector3<f64>,
        up: &Vector3<f64>,
        g: f64,
    ) -> Option<ForceRegressor> {
        let p = self.frame.arm_point(x);
        let up = self.frame.axes.transpose() * up * g;
        let (jacobian, torques) = match &self.geometry {
            ArmGeometry::Serial(a) => {
                let q = a.joints_at(&p)?;
                (a.handle(&q).1, a.torque_regressor(&q, &up))
            }
            ArmGeometry::Delta(a) => {
                let q = a.joints_at(&p)?;
                let j = a.jacobian(&q)?;
                (j, a.torque_regressor(&q, &up, &j))
            }
        };
        // F = J (JᵀJ + λ² I)⁻¹ τ for every column at once.
        let size = jacobian.norm();
        let quality = 3.0 * 3f64.sqrt() * jacobian.determinant().abs() / size.powi(3);
        let lambda = SINGULAR_DAMPING * size * (1.0 - quality / SINGULAR_QUALITY).max(0.0);
        let damped =
            jacobian.transpose() * jacobian + Matrix3::from_diagonal_element(lambda * lambda);
        let inverse = damped.try_inverse()?;
        Some(self.frame.axes * jacobian * inverse * torques)
    }
}

impl SerialArm {
    /// (ψ, α, β) with the handle at `p` (arm frame), elbow above the line from shoulder to
    /// handle; None out of reach.
    pub fn joints_at(&self, p: &Vector3<f64>) -> Option<Vector3<f64>> {
        let rel = p - self.shoulder;
        let r = rel.x.hypot(rel.y);
        let h = rel.z;
        let d = r.hypot(h);
        if d < 1e-9 {
            return None;
        }
        let (l1, l2) = (self.upper, self.fore);
        let cos_shoulder = (l1 * l1 + d * d - l2 * l2) / (2.0 * l1 * d);
        if !(-1.0..=1.0).contains(&cos_shoulder) {
            return None;
        }
        let alpha = h.atan2(r) + cos_shoulder.acos();
        let beta = (r - l1 * alpha.cos()).atan2(l1 * alpha.sin() - h);
        Some(Vector3::new(rel.y.atan2(rel.x), alpha, beta))
    }

    /// The handle (arm frame) and the Jacobian ∂p/∂q at `q`.
    pub fn handle(&self, q: &Vector3<f64>) -> (Vector3<f64>, Matrix3<f64>) {
        let (sy, cy) = q[0].sin_cos();
        let (sa, ca) = q[1].sin_cos();
        let (sb, cb) = q[2].sin_cos();
        let (radial, lateral, z) = (
            Vector3::new(cy, sy, 0.0),
            Vector3::new(-sy, cy, 0.0),
            Vector3::z(),
        );
        let r = self.upper * ca + self.fore * sb;
        let h = self.upper * sa - self.fore * cb;
        let mut j = Matrix3::zeros();
        j.set_column(0, &(lateral * r));
        j.set_column(1, &((radial * -sa + z * ca) * self.upper));
        j.set_column(2, &((radial * cb + z * sb) * self.fore));
        (self.shoulder + radial * r + z * h, j)
    }

    /// Y(q) for `up_g` = g v_G (arm frame): the holding torque per unit of each base parameter.
    fn torque_regressor(
        &self,
        q: &Vector3<f64>,
        up_g: &Vector3<f64>,
    ) -> SMatrix<f64, 3, MAX_PARAMETERS> {
        let (sy, cy) = q[0].sin_cos();
        let (sa, ca) = q[1].sin_cos();
        let (sb, cb) = q[2].sin_cos();
        // v_G g along the turning base's radial and lateral directions, and up.
        let ur = up_g.x * cy + up_g.y * sy;
        let ut = -up_g.x * sy + up_g.y * cy;
        let uz = up_g.z;
        let mut y = SMatrix::<f64, 3, MAX_PARAMETERS>::zeros();
        // Upper arm along (cos α e_r + sin α e_z) and across (−sin α e_r + cos α e_z).
        y[(0, 0)] = ca * ut;
        y[(1, 0)] = -sa * ur + ca * uz;
        y[(0, 1)] = -sa * ut;
        y[(1, 1)] = -ca * ur - sa * uz;
        // Forearm along (sin β e_r − cos β e_z) and across (cos β e_r + sin β e_z).
        y[(0, 2)] = sb * ut;
        y[(2, 2)] = cb * ur + sb * uz;
        y[(0, 3)] = cb * ut;
        y[(2, 3)] = -sb * ur + cb * uz;
        // The base's radial e_r and lateral e_t moments turn with ψ only.
        y[(0, 4)] = ut;
        y[(0, 5)] = -ur;
        y
    }
}

impl DeltaArm {
    fn leg(&self, i: usize) -> Vector3<f64> {
        let (s, c) = self.legs[i].sin_cos();
        Vector3::new(c, s, 0.0)
    }

    fn pivot(&self, i: usize) -> Vector3<f64> {
        self.leg(i) * self.base_radius + Vector3::z() * self.pivot_height
    }

    fn elbow(&self, i: usize, angle: f64) -> Vector3<f64> {
        let (s, c) = angle.sin_cos();
        self.pivot(i) + (self.leg(i) * c - Vector3::z() * s) * self.arm
    }

    /// Each arm's angle below the horizontal with the platform at `p`, elbows out; None out of
    /// reach.
    pub fn joints_at(&self, p: &Vector3<f64>) -> Option<Vector3<f64>> {
        let mut q = Vector3::zeros();
        for i in 0..3 {
            let u = self.leg(i);
            let rel = p + u * self.platform_radius - self.pivot(i);
            let (radial, lateral, up) = (rel.dot(&u), rel.dot(&Vector3::z().cross(&u)), rel.z);
            // |(radial − a cos θ, lateral, up + a sin θ)| = rod: A cos θ + B sin θ + C = 0.
            let a = -2.0 * radial * self.arm;
            let b = 2.0 * up * self.arm;
            let c = radial * radial + lateral * lateral + up * up + self.arm * self.arm
                - self.rod * self.rod;
            let norm = a.hypot(b);
            // Written so that a non-finite position is out of reach too.
            if c.is_nan() || norm.is_nan() || c.abs() > norm || norm == 0.0 {
                return None;
            }
            let angle = b.atan2(a) + (-c / norm).acos() + std::f64::consts::PI;
            q[i] = angle.rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
        }
        Some(q)
    }

    /// The platform's centre at `q`: the lower meeting point of the three rods' spheres.
    pub fn platform(&self, q: &Vector3<f64>) -> Vector3<f64> {
        let c = [0, 1, 2].map(|i| self.elbow(i, q[i]) - self.leg(i) * self.platform_radius);
        let d = (c[1] - c[0]).norm();
        let ex = (c[1] - c[0]) / d;
        let i = ex.dot(&(c[2] - c[0]));
        let ey = (c[2] - c[0] - ex * i).normalize();
        let ez = ex.cross(&ey);
        let j = ey.dot(&(c[2] - c[0]));
        let x = d / 2.0;
        let y = (i * i + j * j - 2.0 * i * x) / (2.0 * j);
        let z = (self.rod * self.rod - x * x - y * y).max(0.0).sqrt();
        c[0] + ex * x + ey * y + ez * if ez.z > 0.0 { -z } else { z }
    }

    /// ∂p/∂q at `q` (each rod keeps its length: s_i · (ṗ − ė_i) = 0); None where singular.
    fn jacobian(&self, q: &Vector3<f64>) -> Option<Matrix3<f64>> {
        let p = self.platform(q);
        let mut rods = Matrix3::zeros();
        let mut along = Vector3::zeros();
        for i in 0..3 {
            let (s, c) = q[i].sin_cos();
            let u = self.leg(i);
            let rod = p + u * self.platform_radius - self.elbow(i, q[i]);
            rods.set_row(i, &rod.transpose());
            along[i] = rod.dot(&((-u * s - Vector3::z() * c) * self.arm));
        }
        Some(rods.try_inverse()? * Matrix3::from_diagonal(&along))
    }

    /// Y(q) for `up_g` = g v_G (arm frame), the Jacobian `j` at q.
    fn torque_regressor(
        &self,
        q: &Vector3<f64>,
        up_g: &Vector3<f64>,
        j: &Matrix3<f64>,
    ) -> SMatrix<f64, 3, MAX_PARAMETERS> {
        let mut y = SMatrix::<f64, 3, MAX_PARAMETERS>::zeros();
        for i in 0..3 {
            let (s, c) = q[i].sin_cos();
            let (ur, uz) = (up_g.dot(&self.leg(i)), up_g.z);
            // Arm i along (cos θ u − sin θ z) and across (sin θ u + cos θ z).
            y[(i, 2 * i)] = -s * ur - c * uz;
            y[(i, 2 * i + 1)] = c * ur - s * uz;
        }
        // The platform translates with the handle: its weight reaches the joints through Jᵀ.
        y.set_column(6, &(j.transpose() * up_g));
        y
    }
}

/// The `[arm]` table: an arm's geometry and where it sits in the device frame, as a device
/// profile gives it and a grid file records it (docs/devices.md §4, docs/grid-format.md §4).
/// A fixed-length array that refuses any other length: serde's own arrays read the first N
/// values of a longer list and drop the rest silently. For the arm tables here and the
/// profiles' arrays.
pub fn exact<'de, D, T, const N: usize>(d: D) -> Result<[T; N], D::Error>
where
    D: serde::Deserializer<'de>,
    T: Deserialize<'de>,
{
    let values: Vec<T> = Vec::deserialize(d)?;
    let found = values.len();
    values
        .try_into()
        .map_err(|_| serde::de::Error::custom(format!("expected {N} values, found {found}")))
}

/// Lengths in metres, leg directions in degrees; `axes` names, for each device axis, the arm
/// axis it is, with a sign ("x", "-y", …); `origin_m` is the arm-frame point at the device's
/// origin.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case", deny_unknown_fields)]
pub enum ArmTable {
    Serial {
        #[serde(deserialize_with = "exact")]
        shoulder_m: [f64; 3],
        upper_m: f64,
        fore_m: f64,
        #[serde(default = "same_axes", deserialize_with = "exact")]
        axes: [String; 3],
        #[serde(default, deserialize_with = "exact")]
        origin_m: [f64; 3],
    },
    Delta {
        arm_m: f64,
        rod_m: f64,
        base_radius_m: f64,
        platform_radius_m: f64,
        pivot_height_m: f64,
        #[serde(deserialize_with = "exact")]
        legs_deg: [f64; 3],
        #[serde(default = "same_axes", deserialize_with = "exact")]
        axes: [String; 3],
        #[serde(default, deserialize_with = "exact")]
        origin_m: [f64; 3],
    },
}

fn same_axes() -> [String; 3] {
    ["x", "y", "z"].map(String::from)
}

/// The least angle between two legs of a delta, degrees.
pub const MIN_LEG_ANGLE_DEG: f64 = 30.0;

/// The longest link or offset an `[arm]` table may give, m.
pub const MAX_LENGTH_M: f64 = 1.0;

impl ArmTable {
    /// The arm this table describes.
    ///
    /// # Errors
    /// A sentence naming the key that is wrong: a length out of (0, 1] m, an offset beyond 1 m,
    /// axes that are not a signed permutation of x, y, z, or an arm that cannot reach the
    /// device's origin.
    pub fn arm(&self) -> Result<Arm, String> {
        let length = |key: &str, v: f64| {
            if v > 0.0 && v <= MAX_LENGTH_M {
                Ok(v)
            } else {
                Err(format!(
                    "`{key}` is {v} m, expected more than 0 and at most {MAX_LENGTH_M} m"
                ))
            }
        };
        let offset = |key: &str, v: &[f64; 3]| {
            if v.iter().all(|c| c.abs() <= MAX_LENGTH_M) {
                Ok(Vector3::from(*v))
            } else {
                Err(format!(
                    "`{key}` is {v:?} m, expected components within ±{MAX_LENGTH_M} m"
                ))
            }
        };
        let (geometry, axes, origin) = match self {
            Self::Serial {
                shoulder_m,
                upper_m,
                fore_m,
                axes,
                origin_m,
            } => (
                ArmGeometry::Serial(SerialArm {
                    shoulder: offset("shoulder_m", shoulder_m)?,
                    upper: length("upper_m", *upper_m)?,
                    fore: length("fore_m", *fore_m)?,
                }),
                axes,
                origin_m,
            ),
            Self::Delta {
                arm_m,
                rod_m,
                base_radius_m,
                platform_radius_m,
                pivot_height_m,
                legs_deg,
                axes,
                origin_m,
            } => {
                if !legs_deg.iter().all(|d| d.is_finite() && d.abs() <= 360.0) {
                    return Err(format!(
                        "`legs_deg` is {legs_deg:?}, expected angles within ±360°"
                    ));
                }
                // Legs closer than this leave the platform's position undetermined.
                let apart = |a: f64, b: f64| {
                    let d = (a - b).rem_euclid(360.0);
                    d.min(360.0 - d) >= MIN_LEG_ANGLE_DEG
                };
                let [l0, l1, l2] = *legs_deg;
                if !(apart(l0, l1) && apart(l1, l2) && apart(l0, l2)) {
                    return Err(format!(
                        "`legs_deg` is {legs_deg:?}: the legs must be at least \
                         {MIN_LEG_ANGLE_DEG}° apart"
                    ));
                }
                (
                    ArmGeometry::Delta(DeltaArm {
                        arm: length("arm_m", *arm_m)?,
                        rod: length("rod_m", *rod_m)?,
                        base_radius: length("base_radius_m", *base_radius_m)?,
                        platform_radius: length("platform_radius_m", *platform_radius_m)?,
                        pivot_height: length("pivot_height_m", *pivot_height_m)?,
                        legs: legs_deg.map(f64::to_radians),
                    }),
                    axes,
                    origin_m,
                )
            }
        };
        let mut rows = Matrix3::zeros();
        let mut used = [false; 3];
        for (row, name) in axes.iter().enumerate() {
            let (sign, letter) = match name.strip_prefix('-') {
                Some(rest) => (-1.0, rest),
                None => (1.0, name.strip_prefix('+').unwrap_or(name)),
            };
            let column = ["x", "y", "z"].iter().position(|a| *a == letter);
            match column {
                Some(c) if !used[c] => {
                    used[c] = true;
                    rows[(row, c)] = sign;
                }
                _ => {
                    return Err(format!(
                        "`axes` is {axes:?}: name each arm axis once, with an optional sign, \
                         e.g. [\"x\", \"-z\", \"y\"]"
                    ))
                }
            }
        }
        let arm = Arm {
            geometry,
            frame: ArmFrame {
                axes: rows,
                origin: offset("origin_m", origin)?,
            },
        };
        let at_origin = arm.force_regressor(&Vector3::zeros(), &arm.up(), 9.81);
        if !at_origin.is_some_and(|g| g.iter().all(|c| c.is_finite())) {
            return Err(
                "the arm cannot reach the device's origin, or is singular there (check origin_m \
                 and the lengths)"
                    .into(),
            );
        }
        Ok(arm)
    }

    /// The table of `arm`.
    pub fn of(arm: &Arm) -> Self {
        let axes = [0, 1, 2].map(|row| {
            let r = arm.frame.axes.row(row);
            let c = r.iamax_full().1;
            format!(
                "{}{}",
                if r[c] < 0.0 { "-" } else { "" },
                ["x", "y", "z"][c]
            )
        });
        let origin_m = arm.frame.origin.into();
        match arm.geometry {
            ArmGeometry::Serial(a) => Self::Serial {
                shoulder_m: a.shoulder.into(),
                upper_m: a.upper,
                fore_m: a.fore,
                axes,
                origin_m,
            },
            ArmGeometry::Delta(a) => Self::Delta {
                arm_m: a.arm,
                rod_m: a.rod,
                base_radius_m: a.base_radius,
                platform_radius_m: a.platform_radius,
                pivot_height_m: a.pivot_height,
                legs_deg: a.legs.map(f64::to_degrees),
                axes,
                origin_m,
            },
        }
    }
}

/// The calibrated gravity of an arm: its geometry, base parameters and gravity, evaluated at a
/// reported position without allocating (the servo thread's hot path).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ArmGravity {
    pub arm: Arm,
    /// The base parameters, in [`Arm::parameter_names`] order.
    pub parameters: [f64; MAX_PARAMETERS],
    /// Unit v_G (device frame), against gravity.
    pub up: Vector3<f64>,
    /// m/s².
    pub g: f64,
}

/// Bisection steps toward the device's origin for a position out of the arm's reach.
const REACH_STEPS: usize = 12;
/// Where the force of a position out of reach is taken: this share of the way from the origin
/// to the last reachable point found, away from the singular pose at the edge of the reach.
const EDGE_MARGIN: f64 = 0.95;

impl ArmGravity {
    /// The force that holds the handle at `x` (device frame, m), N. Out of the arm's reach (a
    /// reading past a stop, a geometry a little off), the force at the reachable point nearest
    /// `x` on the way to the device's origin.
    pub fn force(&self, x: &Vector3<f64>) -> Vector3<f64> {
        let theta = SMatrix::<f64, MAX_PARAMETERS, 1>::from(self.parameters);
        if !x.iter().all(|c| c.is_finite()) {
            // No position, no model: nothing to render (the safety layer treats the reading).
            return Vector3::zeros();
        }
        if let Some(g) = self.arm.force_regressor(x, &self.up, self.g) {
            return g * theta;
        }
        // Bisect the segment from the origin (reachable) to x for the last reachable point.
        let (mut inside, mut outside) = (0.0, 1.0);
        for _ in 0..REACH_STEPS {
            let mid = 0.5 * (inside + outside);
            if self.arm.reaches(&(x * mid)) {
                inside = mid;
            } else {
                outside = mid;
            }
        }
        // A step back inside from the edge, where the arm nears a singular pose.
        self.arm
            .force_regressor(&(x * (inside * EDGE_MARGIN)), &self.up, self.g)
            .or_else(|| {
                self.arm
                    .force_regressor(&Vector3::zeros(), &self.up, self.g)
            })
            .map_or(Vector3::zeros(), |g| g * theta)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A PHANToM 1.5's arm (the `phantom_1_5` profile's geometry).
    pub(crate) fn phantom() -> Arm {
        Arm {
            geometry: ArmGeometry::Serial(SerialArm {
                shoulder: Vector3::new(-0.215, 0.0, 0.170),
                upper: 0.215,
                fore: 0.170,
            }),
            frame: ArmFrame::offset(Vector3::zeros()),
        }
    }

    /// Its gravity with parameters of the order of the published arm's, level.
    pub(crate) fn phantom_gravity() -> ArmGravity {
        ArmGravity {
            arm: phantom(),
            parameters: [-0.0017, 0.0, -0.0075, 0.0, 0.0, 0.0, 0.0],
            up: Vector3::z(),
            g: 9.81,
        }
    }

    pub(crate) fn delta() -> Arm {
        Arm {
            geometry: ArmGeometry::Delta(DeltaArm {
                arm: 0.060,
                rod: 0.1025,
                base_radius: 0.0372,
                platform_radius: 0.014,
                pivot_height: 0.090,
                legs: [180f64, -60.0, 60.0].map(f64::to_radians),
            }),
            frame: ArmFrame::offset(Vector3::zeros()),
        }
    }

    /// Its gravity with a platform of 40 g and arms of the order of the Falcon's, level.
    pub(crate) fn delta_gravity() -> ArmGravity {
        ArmGravity {
            arm: delta(),
            parameters: [0.0012, 0.0, 0.0012, 0.0, 0.0012, 0.0, 0.04],
            up: Vector3::z(),
            g: 9.81,
        }
    }

    /// Points of a 7×7×7 lattice over ±`half` m that the arm reaches.
    fn reached(arm: &Arm, half: f64) -> Vec<Vector3<f64>> {
        (0..343)
            .map(|n| Vector3::new((n % 7) as f64, ((n / 7) % 7) as f64, (n / 49) as f64))
            .map(|s| (s / 3.0).add_scalar(-1.0) * half)
            .filter(|x| arm.joints_at(x).is_some())
            .collect()
    }

    /// The Jacobian in the device frame is ∂x/∂q of the handle's position, by central
    /// differences, through a frame that swaps and flips axes and moves the origin.
    #[test]
    fn the_jacobian_is_the_handles_derivative_in_the_device_frame() {
        let frame = ArmFrame {
            axes: Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0),
            origin: Vector3::new(0.003, -0.002, 0.001),
        };
        for arm in [phantom(), delta()].map(|a| Arm { frame, ..a }) {
            let points = reached(&arm, 0.06);
            assert!(points.len() > 100, "{}", points.len());
            for x in points {
                let j = arm.jacobian(&x).unwrap();
                let q = arm.joints_at(&x).unwrap();
                let h = 1e-6;
                for k in 0..3 {
                    let dq = Vector3::ith(k, h);
                    let column = (arm.handle(&(q + dq)) - arm.handle(&(q - dq))) / (2.0 * h);
                    let error = (column - j.column(k)).norm();
                    assert!(error < 1e-6 * (1.0 + column.norm()), "{x}: {column} {j}");
                }
            }
        }
    }

    #[test]
    fn inverse_kinematics_inverts_forward_kinematics() {
        for (arm, half) in [(phantom(), 0.12), (delta(), 0.05)] {
            let points = reached(&arm, half);
            assert!(points.len() > 100, "{}: {}", arm.kind(), points.len());
            for x in points {
                let q = arm.joints_at(&x).unwrap();
                assert!((arm.handle(&q) - x).norm() < 1e-9, "{}: {x:?}", arm.kind());
            }
        }
    }

    /// The holding force is the gradient of the potential energy along the handle: moving the
    /// handle by δ against F costs U(x + δ) − U(x) = F · δ. U is written here from the
    /// parameters' bodies directly, point by point, not through the regressor.
    #[test]
    fn the_force_is_the_gradient_of_the_potential_energy() {
        let g = 9.81;
        let up = Vector3::new(0.1, -0.05, 1.0).normalize();
        for (arm, half) in [(phantom(), 0.1), (delta(), 0.04)] {
            let theta = [0.031, -0.004, 0.012, 0.002, 0.006, -0.003, 0.05];
            let gravity = ArmGravity {
                arm,
                parameters: theta,
                up,
                g,
            };
            // U = g v_G · Σ θ_k b_k(q), with the b_k of the module's doc.
            let energy = |x: &Vector3<f64>| {
                let q = arm.joints_at(x).unwrap();
                let b: Vec<Vector3<f64>> = match arm.geometry {
                    ArmGeometry::Serial(_) => {
                        let (e_r, e_t) = (
                            Vector3::new(q[0].cos(), q[0].sin(), 0.0),
                            Vector3::new(-q[0].sin(), q[0].cos(), 0.0),
                        );
                        let z = Vector3::z();
                        vec![
                            e_r * q[1].cos() + z * q[1].sin(),
                            -e_r * q[1].sin() + z * q[1].cos(),
                            e_r * q[2].sin() - z * q[2].cos(),
                            e_r * q[2].cos() + z * q[2].sin(),
                            e_r,
                            e_t,
                        ]
                    }
                    ArmGeometry::Delta(d) => {
                        let mut b = Vec::new();
                        for i in 0..3 {
                            let u = d.leg(i);
                            b.push(u * q[i].cos() - Vector3::z() * q[i].sin());
                            b.push(u * q[i].sin() + Vector3::z() * q[i].cos());
                        }
                        b.push(*x);
                        b
                    }
                };
                g * up.dot(
                    &b.iter()
                        .zip(theta)
                        .map(|(b, t)| b * t)
                        .sum::<Vector3<f64>>(),
                )
            };
            for x in reached(&arm, half) {
                let f = gravity.force(&x);
                let h = 1e-6;
                let gradient = Vector3::from_fn(|a, _| {
                    let e = Vector3::ith(a, h);
                    (energy(&(x + e)) - energy(&(x - e))) / (2.0 * h)
                });
                assert!(
                    (f - gradient).norm() < 1e-5 * (1.0 + f.norm()),
                    "{}: at {x:?} F = {f:?}, ∇U = {gradient:?}",
                    arm.kind()
                );
            }
        }
    }

    #[test]
    fn a_platform_mass_weighs_its_weight_along_up() {
        let up = Vector3::new(0.2, 0.0, 1.0).normalize();
        let mut theta = [0.0; MAX_PARAMETERS];
        theta[6] = 0.030;
        let gravity = ArmGravity {
            arm: delta(),
            parameters: theta,
            up,
            g: 9.81,
        };
        for x in reached(&delta(), 0.04) {
            let f = gravity.force(&x);
            assert!((f - up * 0.030 * 9.81).norm() < 1e-6, "{x:?}: {f:?}");
        }
    }

    #[test]
    fn a_reading_out_of_reach_gets_a_finite_force_and_one_inside_its_own() {
        let arm = phantom();
        let gravity = ArmGravity {
            arm,
            parameters: [0.03, 0.0, -0.01, 0.0, 0.0, 0.0, 0.0],
            up: Vector3::z(),
            g: 9.81,
        };
        let far = Vector3::new(0.5, 0.0, 0.0);
        assert!(arm.joints_at(&far).is_none());
        let f = gravity.force(&far);
        assert!(f.norm() > 0.0 && f.iter().all(|c| c.is_finite()), "{f:?}");
        let inside = Vector3::new(0.05, 0.02, -0.03);
        let theta = SMatrix::<f64, MAX_PARAMETERS, 1>::from(gravity.parameters);
        let direct = arm.force_regressor(&inside, &Vector3::z(), 9.81).unwrap() * theta;
        assert_eq!(gravity.force(&inside), direct);
    }

    #[test]
    fn an_arm_table_round_trips_and_names_what_is_wrong() {
        let mut arm = delta();
        arm.frame.axes = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
        let table = ArmTable::of(&arm);
        let text = toml::to_string(&table).unwrap();
        let back: ArmTable = toml::from_str(&text).unwrap();
        let read = back.arm().unwrap();
        assert_eq!(read.frame, arm.frame);
        assert_eq!(read.kind(), "delta");
        let bad: ArmTable = toml::from_str(
            "kind = \"serial\"\nshoulder_m = [0.0, 0.0, 0.1]\nupper_m = 0.2\nfore_m = 0.2\n\
             axes = [\"x\", \"x\", \"z\"]\n",
        )
        .unwrap();
        assert!(bad.arm().unwrap_err().contains("`axes`"));
        let short: ArmTable = toml::from_str(
            "kind = \"serial\"\nshoulder_m = [0.0, 0.0, 0.1]\nupper_m = 0.0\nfore_m = 0.2\n",
        )
        .unwrap();
        assert!(short.arm().unwrap_err().contains("`upper_m`"));
        assert!(toml::from_str::<ArmTable>("kind = \"scara\"\n").is_err());
    }

    #[test]
    fn near_the_edge_of_its_reach_and_for_no_number_the_force_stays_bounded() {
        for arm in [delta(), phantom()] {
            let gravity = ArmGravity {
                arm,
                parameters: [0.005, 0.001, -0.004, 0.0, 0.003, 0.0, 0.05],
                up: Vector3::z(),
                g: 9.81,
            };
            let at_home = gravity.force(&Vector3::zeros()).norm();
            let mut largest: f64 = 0.0;
            // Along rays from the origin out past the reach, every half millimetre.
            for dir in [
                Vector3::x(),
                -Vector3::x(),
                Vector3::y(),
                Vector3::z(),
                -Vector3::z(),
                Vector3::new(1.0, 1.0, -1.0).normalize(),
                Vector3::new(-1.0, 0.5, 1.0).normalize(),
            ] {
                for k in 0..1000 {
                    let f = gravity.force(&(dir * (k as f64 * 5e-4)));
                    assert!(f.iter().all(|c| c.is_finite()), "{}: {f:?}", arm.kind());
                    largest = largest.max(f.norm());
                }
            }
            println!(
                "{}: |F| at home {at_home:.3} N, largest {largest:.3} N",
                arm.kind()
            );
            // Near a singular pose (beyond the stops of a real arm: a stretched serial arm, a
            // delta's arm in line with its rod) the damping bounds |F| by |τ| / (2 λ): tens of
            // newtons at most for these parameters, where J⁻ᵀ itself grows without bound.
            assert!(largest < 30.0, "{}: {largest} N", arm.kind());
            let nan = Vector3::new(f64::NAN, 0.0, 0.01);
            assert_eq!(gravity.force(&nan), Vector3::zeros());
            assert_eq!(
                gravity.force(&Vector3::repeat(f64::INFINITY)),
                Vector3::zeros()
            );
        }
    }

    #[test]
    fn a_delta_whose_legs_coincide_is_refused() {
        let mut table = ArmTable::of(&delta());
        if let ArmTable::Delta { legs_deg, .. } = &mut table {
            *legs_deg = [0.0, 0.0, 120.0];
        }
        let error = table.arm().unwrap_err();
        assert!(error.contains("`legs_deg`"), "{error}");
    }
}
