//! `sim:delta`: an Omega.3 / Falcon style delta: three rotary arms on a fixed base, each carrying
//! a parallelogram of two rods down to a platform that only translates. Link lengths and encoders
//! are the Novint Falcon's (libnifalcon's `FalconGeometry.h`, after Stamper's thesis); the masses,
//! friction and motors are estimates of a Falcon-class device. Every number and approximation is
//! listed in docs/simulated-devices.md.
//!
//! The device frame has z up along the delta's axis, the base above the handle, and its origin at
//! the home pose: the handle on the axis `home_depth` below the plane of the arm pivots, in the
//! middle of the workspace. Leg 0 points away from the user (−x), legs 1 and 2 to the user's
//! right and left front, so the device is symmetric in y. Joint i is arm i's angle below the
//! horizontal (positive: the elbow down).

use nalgebra::{Matrix3, Vector3};

use super::linkage::{Drives, JointState, Linkage, Mechanism, Point, UnitVariation, Unreachable};
use crate::config::SimConfig;

/// Geometry and masses of the delta (SI units).
#[derive(Clone, Debug, PartialEq)]
pub struct Delta {
    /// Arm length (pivot to elbow), m.
    pub arm: f64,
    /// Parallelogram rod length (elbow to platform), m.
    pub rod: f64,
    /// Radius of the arm pivots about the axis, m.
    pub base_radius: f64,
    /// Radius of the rods' platform joints about the platform centre, m.
    pub platform_radius: f64,
    /// Height of the arm pivots above the handle at home, m.
    pub home_depth: f64,
    /// Platform with the grip, kg (moves with the handle).
    pub m_platform: f64,
    /// One leg's parallelogram (two rods and their end bars), kg: half rides on the elbow, half
    /// on the platform.
    pub m_rods: f64,
    /// One arm with its capstan sector, kg, and its centre of mass from the pivot, m.
    pub m_arm: f64,
    pub arm_com: f64,
    /// One arm's inertia about its centre of mass, about the pivot axis, kg m².
    pub i_arm: f64,
    /// Mechanical stops of every arm (lower, upper), rad.
    pub limits: (f64, f64),
    /// Directions of the three legs in the horizontal plane (away from the user, right front,
    /// left front).
    pub legs: [Vector3<f64>; 3],
    /// Where the home pose puts the handle off the device frame's origin, m: zero on the
    /// nominal device, up to a millimetre on a unit.
    pub home_offset: Vector3<f64>,
}

impl Delta {
    /// The nominal device: Falcon geometry, Falcon-class masses.
    pub fn nominal() -> Self {
        Self {
            arm: 0.060,
            rod: 0.1025,
            base_radius: 0.037233758,
            platform_radius: 0.014,
            home_depth: 0.090,
            m_platform: 0.045,
            m_rods: 0.010,
            m_arm: 0.030,
            arm_com: 0.020,
            i_arm: 2.0e-5,
            limits: ((-65f64).to_radians(), 100f64.to_radians()),
            legs: [180.0f64, -60.0, 60.0].map(|deg| {
                let (s, c) = deg.to_radians().sin_cos();
                Vector3::new(c, s, 0.0)
            }),
            home_offset: Vector3::zeros(),
        }
    }

    /// The nominal device with its masses and centres of mass varied as one unit, its link
    /// lengths and home pose a little off the nominal ones.
    pub fn unit(variation: &mut UnitVariation) -> Self {
        let d = Self::nominal();
        let arm = variation.vary_length(d.arm);
        let rod = variation.vary_length(d.rod);
        let base_radius = variation.vary_length(d.base_radius);
        let platform_radius = variation.vary_length(d.platform_radius);
        let home_offset = variation.home_offset();
        Self {
            arm,
            rod,
            base_radius,
            platform_radius,
            home_offset,
            m_platform: variation.vary(d.m_platform),
            m_rods: variation.vary(d.m_rods),
            m_arm: variation.vary(d.m_arm),
            arm_com: variation.vary(d.arm_com),
            i_arm: variation.vary(d.i_arm),
            ..d
        }
    }

    /// Kinematics of the point `along` from pivot `i` along arm i (only θ_i moves it).
    fn arm_point(&self, i: usize, joints: &JointState, along: f64) -> Point {
        let u = self.legs[i];
        let (s, c) = (joints.sin[i], joints.cos[i]);
        let qd = &joints.qd;
        let mut jacobian = Matrix3::zeros();
        jacobian.set_column(i, &((-u * s - Vector3::z() * c) * along));
        Point {
            position: self.pivot(i) + (u * c - Vector3::z() * s) * along,
            jacobian,
            bias: (-u * c + Vector3::z() * s) * (along * qd[i] * qd[i]),
        }
    }

    /// Pivot of arm i, device frame.
    fn pivot(&self, i: usize) -> Vector3<f64> {
        self.legs[i] * self.base_radius + Vector3::z() * self.home_depth + self.home_offset
    }

    /// The platform centre at `joints`: the lower intersection of the three spheres of radius
    /// `rod` about the elbows shifted in by the platform radius. Out of reach (the spheres do not
    /// meet) it returns the nearest point the construction gives (rods stretched), which the joint
    /// limits keep the plant from reaching.
    fn platform(&self, joints: &JointState) -> Vector3<f64> {
        let u = &self.legs;
        let centre = |i: usize| {
            let (s, c) = (joints.sin[i], joints.cos[i]);
            self.pivot(i) + (u[i] * c - Vector3::z() * s) * self.arm - u[i] * self.platform_radius
        };
        let (c0, c1, c2) = (centre(0), centre(1), centre(2));
        let d = (c1 - c0).norm();
        let ex = (c1 - c0) / d;
        let i = ex.dot(&(c2 - c0));
        let ey = (c2 - c0 - ex * i).normalize();
        let ez = ex.cross(&ey);
        let j = ey.dot(&(c2 - c0));
        // Equal radii: x = d/2, y = (i² + j² − 2 i x) / (2 j).
        let x = d / 2.0;
        let y = (i * i + j * j - 2.0 * i * x) / (2.0 * j);
        let z = (self.rod * self.rod - x * x - y * y).max(0.0).sqrt();
        // The solution below the elbows.
        let down = if ez.z > 0.0 { -z } else { z };
        c0 + ex * x + ey * y + ez * down
    }
}

impl Mechanism for Delta {
    fn handle(&self, joints: &JointState) -> Point {
        let p = self.platform(joints);
        let qd = &joints.qd;
        let u = &self.legs;
        // Each rod keeps its length: s_i · (ṗ − ė_i) = 0 with s_i the rod vector, e_i the elbow.
        let mut a = Matrix3::zeros();
        let mut d = Vector3::zeros();
        let mut second = Vector3::zeros();
        let mut elbow_rate = [Vector3::zeros(); 3];
        let mut rods = [Vector3::zeros(); 3];
        for i in 0..3 {
            let (s, c) = (joints.sin[i], joints.cos[i]);
            let elbow = self.pivot(i) + (u[i] * c - Vector3::z() * s) * self.arm;
            let de = (-u[i] * s - Vector3::z() * c) * self.arm;
            let dde = (-u[i] * c + Vector3::z() * s) * self.arm;
            let rod = p + u[i] * self.platform_radius - elbow;
            a.set_row(i, &rod.transpose());
            d[i] = rod.dot(&de);
            second[i] = rod.dot(&dde) * qd[i] * qd[i];
            elbow_rate[i] = de * qd[i];
            rods[i] = rod;
        }
        let a_inv = a.try_inverse().unwrap_or_else(Matrix3::zeros);
        let jacobian = a_inv * Matrix3::from_diagonal(&d);
        let pd = jacobian * qd;
        // Twice differentiated: s_i · p̈ = s_i · e_i'' terms − |ṡ_i|².
        for i in 0..3 {
            second[i] -= (pd - elbow_rate[i]).norm_squared();
        }
        Point {
            position: p,
            jacobian,
            bias: a_inv * second,
        }
    }

    fn joints_at(&self, x: &Vector3<f64>) -> Option<Vector3<f64>> {
        let mut q = Vector3::zeros();
        for (i, u) in self.legs.iter().enumerate() {
            // The rod's platform end relative to the pivot: radial, lateral and vertical parts.
            let rel = x + u * self.platform_radius - self.pivot(i);
            let radial = rel.dot(u);
            let lateral = rel.dot(&Vector3::z().cross(u));
            let up = rel.z;
            // |(radial − a cos θ, lateral, up + a sin θ)| = rod: A cos θ + B sin θ + C = 0.
            let a = -2.0 * radial * self.arm;
            let b = 2.0 * up * self.arm;
            let c = radial * radial + lateral * lateral + up * up + self.arm * self.arm
                - self.rod * self.rod;
            let r = a.hypot(b);
            if c.abs() > r {
                return None;
            }
            // The branch with the elbow out, continuous with the home pose.
            let theta = b.atan2(a) + (-c / r).acos();
            q[i] = (theta + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
                - std::f64::consts::PI;
        }
        Some(q)
    }

    fn handle_mass(&self) -> f64 {
        self.m_platform + 1.5 * self.m_rods
    }

    fn masses(&self, joints: &JointState, visit: &mut dyn FnMut(f64, &Point)) {
        for i in 0..3 {
            visit(0.5 * self.m_rods, &self.arm_point(i, joints, self.arm));
            visit(self.m_arm, &self.arm_point(i, joints, self.arm_com));
        }
    }

    fn rotations(&self, _joints: &JointState) -> (Matrix3<f64>, Vector3<f64>) {
        // The arms turn about their fixed pivot axes; the rods' own rotation is neglected.
        (Matrix3::from_diagonal_element(self.i_arm), Vector3::zeros())
    }

    fn joint_limits(&self) -> (Vector3<f64>, Vector3<f64>) {
        (
            Vector3::repeat(self.limits.0),
            Vector3::repeat(self.limits.1),
        )
    }
}

/// The drives of a Falcon-class delta: capstan from a 14.25 mm motor shaft to a 110 mm arm drum
/// (ratio 7.72); 320-slot encoder wheels read in quadrature (1280 counts per motor turn); motor,
/// rotor and friction figures are estimates for 555-size brushed motors (docs/simulated-devices.md).
pub fn nominal_drives() -> Drives {
    Drives {
        ratio: Vector3::repeat(0.110 / 0.01425),
        rotor_inertia: Vector3::repeat(3.0e-6),
        peak_torque: Vector3::repeat(0.055),
        counts_per_rev: Vector3::repeat(4.0 * 320.0),
        coulomb: Vector3::repeat(0.004),
        viscous: Vector3::repeat(0.0002),
    }
}

/// The `sim:delta` plant a `[sim]` section describes.
///
/// # Errors
/// [`Unreachable`] when the handle cannot start at `sim.start_position_mm`.
pub fn from_config(sim: &SimConfig) -> Result<Linkage<Delta>, Unreachable> {
    Linkage::unit_from_config(sim, Delta::unit, nominal_drives())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::linkage::checks::{self, cube, env, G};
    use crate::sim::linkage::Environment;
    use crate::sim::Plant;

    fn delta_at(x_mm: [f64; 3], env: Environment) -> Linkage<Delta> {
        checks::at(Delta::nominal(), nominal_drives(), x_mm, env)
    }

    #[test]
    fn inverse_kinematics_inverts_forward_kinematics_and_home_is_the_origin() {
        let delta = Delta::nominal();
        let zero = Vector3::zeros();
        let home = delta.joints_at(&zero).unwrap();
        assert!(delta.handle(&JointState::at_rest(&home)).position.norm() < 1e-12);
        // Symmetric: every arm at the same angle, about 23° below horizontal.
        assert!((home.amax() - home.amin()).abs() < 1e-12);
        assert!((home[0].to_degrees() - 23.4).abs() < 0.1, "{home:?}");
        for x in cube(4) {
            let x = Vector3::from(x) * 1e-3;
            let q = delta.joints_at(&x).unwrap();
            assert!(
                (delta.handle(&JointState::at_rest(&q)).position - x).amax() < 1e-12,
                "{x:?}"
            );
        }
        assert!(delta.joints_at(&Vector3::new(0.0, 0.0, -0.2)).is_none());
    }

    #[test]
    fn jacobians_and_velocity_products_match_finite_differences() {
        let delta = Delta::nominal();
        let qd = Vector3::new(0.9, -1.3, 0.6);
        for x in cube(2) {
            let q = delta.joints_at(&(Vector3::from(x) * 1e-3)).unwrap();
            checks::assert_points_match_finite_differences(&delta, &q, &qd, 1e-6);
        }
    }

    #[test]
    fn gravity_torque_is_the_gradient_of_the_potential_energy_for_any_gravity() {
        let mut plant = delta_at([0.0; 3], checks::tilted());
        for x in cube(2) {
            let q = plant
                .mechanism()
                .joints_at(&(Vector3::from(x) * 1e-3))
                .unwrap();
            checks::assert_gravity_torque_is_the_gradient(&mut plant, &q);
        }
    }

    #[test]
    fn gravity_pulls_the_handle_down_along_the_axis_at_home_and_tilts_it_off_axis() {
        let home = delta_at([0.0; 3], env(1.0, 0.0));
        let f = -home.holding_force();
        assert!(f.xy().norm() < 1e-12, "{f:?}");
        // More than the platform and the rods' platform halves weigh: the arms add their share.
        let d = Delta::nominal();
        assert!(f.z < -(d.m_platform + 1.5 * d.m_rods) * G);
        assert!((f.z + 0.880).abs() < 0.005, "{f:?}");
        let (least, most, steepest, sideways) =
            checks::gravity_force_spread(|x| delta_at(x, env(1.0, 0.0)), &-Vector3::z());
        // docs/simulated-devices.md: 0.75 to 1.18 N, up to 18.5° from vertical, 0.27 N sideways.
        assert!((0.74..0.77).contains(&least), "{least}");
        assert!((1.16..1.20).contains(&most), "{most}");
        assert!((17.0..20.0).contains(&steepest), "{steepest}");
        assert!((0.26..0.29).contains(&sideways), "{sideways}");
    }

    #[test]
    fn the_calibration_cube_lies_inside_the_joint_limits() {
        let (lo, hi) = Delta::nominal().limits;
        for x in cube(8) {
            let q = Delta::nominal()
                .joints_at(&(Vector3::from(x) * 1e-3))
                .unwrap();
            assert!(q.min() > lo + 0.05 && q.max() < hi - 0.05, "{x:?}: {q:?}");
        }
    }

    #[test]
    fn frictionless_motion_conserves_energy() {
        // Largest energy error over 0.15 s of free motion (thrown up, falling back), relative to
        // the largest kinetic energy on the way.
        checks::assert_energy_is_conserved(|dt| {
            let mut plant = delta_at([0.0; 3], env(0.0, 0.03));
            plant.set_state(plant.joints(), Vector3::new(-3.0, -2.0, -1.0));
            let (worst, peak) = checks::free_motion_energy(&mut plant, 0.15, dt);
            worst / peak
        });
    }

    #[test]
    fn the_holding_force_holds_a_frictionless_delta_still_for_seconds() {
        for x in [[0.0, 0.0, 0.0], [30.0, -25.0, 35.0], [-40.0, 40.0, -40.0]] {
            checks::assert_holding_force_holds_still(delta_at(x, env(0.0, 0.03)));
        }
    }

    #[test]
    fn drives_give_about_9_n_and_0_03_mm_at_home() {
        let home = delta_at([0.0; 3], env(1.0, 0.0));
        let j = home
            .mechanism()
            .handle(&JointState::at_rest(&home.joints()))
            .jacobian;
        let drives = nominal_drives();
        let peak = drives.peak_joint_torque();
        // The largest force along each axis before one motor saturates.
        let most = |axis: usize| {
            (0..3)
                .map(|i| peak[i] / j[(axis, i)].abs())
                .fold(f64::INFINITY, f64::min)
        };
        assert!((9.0..9.2).contains(&most(0)), "{}", most(0));
        assert!(most(1) > 9.0 && most(2) > 9.0);
        // One count moves the handle by |J column| × step.
        let step = drives.joint_resolution()[0];
        for i in 0..3 {
            let at_handle = j.column(i).norm() * step;
            assert!((0.02e-3..0.04e-3).contains(&at_handle), "{at_handle}");
        }
        for x in [[0.0, 0.0, 0.0], [13.7, -21.1, 33.3], [-38.0, 5.5, -12.0]] {
            let plant = delta_at(x, env(1.0, 0.0));
            let sensed = plant.sensed_position(&Vector3::zeros());
            assert!((sensed - plant.position()).amax() < 0.04e-3, "{x:?}");
        }
    }

    #[test]
    fn rough_handling_anywhere_in_reach_stays_finite_and_inside_the_stops() {
        // Pushes of up to 9 N in changing directions drive the handle to the edges of its
        // workspace, against the stops and the stretched legs; the state stays finite.
        for friction in [0.0, 1.0] {
            let mut plant = delta_at([0.0; 3], env(friction, 0.03));
            let (lo, hi) = plant.workspace();
            let (qlo, qhi) = plant.mechanism().limits;
            for n in 0..100_000u32 {
                let k = f64::from(n / 2_000);
                let push = Vector3::new((1.7 * k).sin(), (2.3 * k).cos(), (0.9 * k).sin()) * 9.0;
                plant.step(&push, 1e-4);
                let (x, q) = (plant.position(), plant.joints());
                assert!(x.iter().chain(q.iter()).all(|c| c.is_finite()), "step {n}");
                assert!((0..3).all(|a| x[a] >= lo[a] && x[a] <= hi[a]), "{x:?}");
                assert!(q.min() >= qlo && q.max() <= qhi);
            }
        }
    }

    #[test]
    fn units_differ_by_a_few_percent_and_seed_zero_is_the_nominal_delta() {
        assert_eq!(Delta::unit(&mut UnitVariation::new(0)), Delta::nominal());
        let nominal = delta_at([0.0; 3], env(1.0, 0.0)).holding_force();
        checks::assert_units_differ(from_config, nominal, 0.002..0.05);
    }

    #[test]
    fn a_stop_never_throws_the_handle_faster_than_it_came() {
        // Led by a spring and damper (200 N/m, 5 N s/m) whose set point moves at 15 mm/s from
        // home, as exploration's probes do, with the holding force fed forward, along the 26
        // directions of a cube's faces, edges and corners, frictionless and with the published
        // friction: every step that logs a contact leaves the arm with no more kinetic energy
        // than it had plus the work of the force, and each contact's speed is at most the
        // handle's just before.
        let dt = 1e-4;
        let mut contacts = 0;
        for friction in [0.0, 1.0] {
            for n in (0..27).filter(|&n| n != 13) {
                let d = Vector3::new((n % 3) as f64, ((n / 3) % 3) as f64, (n / 9) as f64);
                let direction = (d - Vector3::repeat(1.0)).normalize();
                let mut plant = delta_at([0.0; 3], env(friction, 0.0));
                for step in 0..80_000 {
                    let t = step as f64 * dt;
                    let (energy, moving, from) =
                        (plant.kinetic_energy(), plant.velocity(), plant.position());
                    let set_point = direction * (0.015 * t);
                    let force = plant.holding_force() + (set_point - from) * 200.0
                        - (moving - direction * 0.015) * 5.0;
                    let count = plant.contacts().count();
                    plant.step(&force, dt);
                    if plant.contacts().count() == count {
                        continue;
                    }
                    contacts += 1;
                    let work = (force - plant.holding_force()).dot(&(plant.position() - from));
                    let after = plant.kinetic_energy();
                    assert!(
                        after <= energy + work.max(0.0) + 1e-12,
                        "{direction:?} at {t} s: {after} J after, {energy} J before"
                    );
                    let contact = plant.contacts().contacts().last().unwrap();
                    let speed = moving.norm();
                    assert!(
                        contact.speed <= 1.01 * speed + 1e-9,
                        "{contact:?}, {speed} m/s"
                    );
                }
            }
        }
        assert!(contacts >= 40, "{contacts} contacts");
    }

    #[test]
    fn handle_friction_holds_below_its_level_and_takes_the_energy_of_a_slide() {
        checks::assert_handle_friction_sticks_and_slides(delta_at, [20.0, -15.0, 10.0]);
    }
}
