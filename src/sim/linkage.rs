//! Linkage plants: a mechanism simulated in the space of its three actuated joints q,
//!
//!   M(q) q̈ + h(q, q̇) + τ_g(q) + τ_f = sat(Jᵀ F) + Jᵀ F_env,
//!
//! F_env the environment's spring and damping at the handle (no motor limits them), with the
//! handle where forward kinematics puts it. A [`Mechanism`] supplies the geometry and the
//! masses (handle kinematics, lumped masses, the links' rotational inertia); [`Linkage`] does the
//! rest the same
//! way for every mechanism: inertia and velocity-product terms from those bodies, gravity from
//! their potential energy for any gravity vector, motor torque limits, joint friction with
//! stick-slip, Coulomb friction at the handle (a cable, a sleeve, a user's fingertip), hard joint
//! stops and joint encoders.

use nalgebra::{Matrix3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::{ContactLog, Plant};
use crate::config::SimConfig;

pub use crate::profile::kinematics::{JointState, Point};

/// How far the handle must leave the obstacle for its next touch to count as a new contact, m.
const RELEASE: f64 = 1e-4;
/// How far a joint must leave its stop for its next touch to count as a new contact, rad: about
/// [`RELEASE`] at the handle on links of 0.1–0.2 m. A joint held on its stop by the hold chatters
/// off it by nanoradians at every substep; that is one contact, not thousands.
const JOINT_RELEASE: f64 = 1e-3;
/// Rounds of the joint-by-joint impulse when several joints run into their stops at once.
const IMPULSE_ROUNDS: usize = 4;

/// The geometry and masses of a mechanism (kinematics only: no friction, motors or sensors).
/// Positions are in the device frame, m, with the handle at the origin at q = 0 on the nominal
/// unit (a unit's home may sit up to [`UnitVariation::HOME_SPREAD`] from it).
pub trait Mechanism: Send + 'static {
    /// The handle's kinematics (the point forces act on and the device reports).
    fn handle(&self, joints: &JointState) -> Point;
    /// Joint angles that put the handle at `x`, in the mechanism's working assembly mode; `None`
    /// out of reach.
    fn joints_at(&self, x: &Vector3<f64>) -> Option<Vector3<f64>>;
    /// The mass that rides on the handle, kg (a delta's platform); [`Linkage`] adds it at the
    /// handle's kinematics, after the payload.
    fn handle_mass(&self) -> f64 {
        0.0
    }
    /// Visit every other lumped mass (kg) with its kinematics: the masses carry both weight and
    /// inertia.
    fn masses(&self, joints: &JointState, visit: &mut dyn FnMut(f64, &Point));
    /// What the links' rotation about their own centres of mass adds to the joint-space
    /// dynamics: (inertia, kg m²; velocity-product torques, N m), from the kinetic energy
    /// ½ ωᵀ I ω of each link.
    fn rotations(&self, joints: &JointState) -> (Matrix3<f64>, Vector3<f64>);
    /// Mechanical stops: (lower, upper) joint angle, rad.
    fn joint_limits(&self) -> (Vector3<f64>, Vector3<f64>);
}

/// What drives and senses each joint: motor, transmission, encoder and joint friction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Drives {
    /// Transmission ratio, motor angle per joint angle (capstan drums).
    pub ratio: Vector3<f64>,
    /// Rotor inertia, kg m² at the motor shaft.
    pub rotor_inertia: Vector3<f64>,
    /// Peak motor torque, N m at the motor shaft.
    pub peak_torque: Vector3<f64>,
    /// Encoder counts per motor revolution (after quadrature decoding).
    pub counts_per_rev: Vector3<f64>,
    /// Coulomb friction at the joint, N m; it is also the static (breakaway) level.
    pub coulomb: Vector3<f64>,
    /// Viscous friction at the joint, N m s/rad.
    pub viscous: Vector3<f64>,
}

impl Drives {
    /// Peak joint torque, N m.
    pub fn peak_joint_torque(&self) -> Vector3<f64> {
        self.peak_torque.component_mul(&self.ratio)
    }

    /// Joint angle per encoder count, rad.
    pub fn joint_resolution(&self) -> Vector3<f64> {
        Vector3::repeat(std::f64::consts::TAU)
            .component_div(&self.counts_per_rev.component_mul(&self.ratio))
    }
}

/// Deterministic differences between nominally identical units (`sim.unit_seed`): a few percent
/// in masses and friction, and, drawn from a stream of their own (so a unit's masses are the
/// same with or without them), up to half a percent in link lengths and a millimetre in where
/// the home pose sits, so that a profile's published geometry is never exactly the unit's.
pub struct UnitVariation(Option<(ChaCha8Rng, ChaCha8Rng)>);

impl UnitVariation {
    /// Largest relative change of one parameter.
    pub const SPREAD: f64 = 0.03;
    /// Largest relative change of a link length.
    pub const LENGTH_SPREAD: f64 = 0.005;
    /// Largest distance of a unit's home pose from the nominal one, m.
    pub const HOME_SPREAD: f64 = 1e-3;

    /// Seed 0 is the nominal unit: [`UnitVariation::vary`] then changes nothing.
    pub fn new(unit_seed: u64) -> Self {
        Self((unit_seed != 0).then(|| {
            (
                ChaCha8Rng::seed_from_u64(unit_seed),
                ChaCha8Rng::seed_from_u64(unit_seed ^ 0x6765_6f6d_6574_7279),
            )
        }))
    }

    /// `value` scaled by a factor drawn uniformly in 1 ± [`UnitVariation::SPREAD`].
    pub fn vary(&mut self, value: f64) -> f64 {
        match &mut self.0 {
            None => value,
            Some((rng, _)) => value * (1.0 + rng.gen_range(-Self::SPREAD..=Self::SPREAD)),
        }
    }

    /// Each component varied on its own.
    pub fn vary3(&mut self, v: Vector3<f64>) -> Vector3<f64> {
        v.map(|c| self.vary(c))
    }

    /// A link length scaled by a factor drawn uniformly in 1 ± [`UnitVariation::LENGTH_SPREAD`].
    pub fn vary_length(&mut self, value: f64) -> f64 {
        match &mut self.0 {
            None => value,
            Some((_, rng)) => {
                value * (1.0 + rng.gen_range(-Self::LENGTH_SPREAD..=Self::LENGTH_SPREAD))
            }
        }
    }

    /// Where the unit's home pose sits from the nominal one: uniform in a ball of radius
    /// [`UnitVariation::HOME_SPREAD`], m.
    pub fn home_offset(&mut self) -> Vector3<f64> {
        match &mut self.0 {
            None => Vector3::zeros(),
            Some((_, rng)) => loop {
                let v = Vector3::from_fn(|_, _| rng.gen_range(-1.0..=1.0));
                if v.norm() <= 1.0 {
                    break v * Self::HOME_SPREAD;
                }
            },
        }
    }
}

/// The environment a linkage works in.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Environment {
    /// Gravitational acceleration vector in the device frame, m/s² (−g v_G).
    pub gravity: Vector3<f64>,
    /// Probe mass fixed to the handle, kg.
    pub payload: f64,
    /// Multiplies every joint friction coefficient (0: frictionless joints).
    pub friction_scale: f64,
    /// Coulomb friction at the handle, N: the handle sticks while the Cartesian force friction
    /// must supply to hold it is at most this, and slides against this much force otherwise.
    pub handle_friction: f64,
    /// A spring at the handle (a cable, a hose): stiffness, N/m, pulling toward the anchor,
    /// device frame, m.
    pub spring: (f64, Vector3<f64>),
    /// Viscous damping at the handle, N·s/m.
    pub handle_damping: f64,
}

impl Environment {
    /// Gravity (`sim.g` against `sim.gravity_direction`), payload, joint friction scale, handle
    /// friction (`sim.coulomb_friction_n`), spring and damping at the handle of `[sim]`.
    pub fn from_config(sim: &SimConfig) -> Self {
        Self {
            gravity: -Vector3::from(sim.gravity_direction).normalize() * sim.g,
            payload: sim.probe_mass_kg,
            friction_scale: sim.friction_scale,
            handle_friction: sim.coulomb_friction_n,
            spring: (sim.spring_n_per_m, sim.spring_anchor()),
            handle_damping: sim.damping_n_s_per_m,
        }
    }
}

/// Why a linkage cannot start where it was asked to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Unreachable;

/// A mechanism with drives, in an environment, and its state.
#[derive(Clone, Debug)]
pub struct Linkage<M: Mechanism> {
    mechanism: M,
    drives: Drives,
    env: Environment,
    /// Joint-space inertia of the motor rotors, kg m².
    rotor_inertia: Vector3<f64>,
    peak: Vector3<f64>,
    resolution: Vector3<f64>,
    lower: Vector3<f64>,
    upper: Vector3<f64>,
    workspace: (Vector3<f64>, Vector3<f64>),
    /// A box the handle cannot enter (`sim.obstacle_*_mm`), m: a wall the user did not declare.
    obstacle: Option<(Vector3<f64>, Vector3<f64>)>,
    /// Whether the handle rests against the obstacle: it ran into it and has not left it by
    /// more than [`RELEASE`] since (pressed on, it creeps back in from a few µm away).
    touching: bool,
    /// Whether each joint rests on a stop: it ran into it and has not left it by more than
    /// [`JOINT_RELEASE`] since.
    on_stop: [bool; 3],
    contacts: ContactLog,
    q: Vector3<f64>,
    /// Joint velocities; a component that is exactly zero marks a joint held (stuck by static
    /// friction or resting on a stop) until the torque on it leaves its static band.
    qd: Vector3<f64>,
}

/// Joint-space dynamics at one state.
struct Dynamics {
    inertia: Matrix3<f64>,
    /// Velocity-product (Coriolis and centrifugal) torques.
    bias: Vector3<f64>,
    /// ∂U/∂q, U the potential energy: the torque that holds the mechanism against gravity.
    gravity: Vector3<f64>,
}

impl<M: Mechanism> Linkage<M> {
    /// At rest with the handle at `start` (m).
    ///
    /// # Errors
    /// [`Unreachable`] when the handle cannot be there within the joint limits.
    pub fn new(
        mechanism: M,
        drives: Drives,
        env: Environment,
        start: &Vector3<f64>,
    ) -> Result<Self, Unreachable> {
        let (lower, upper) = mechanism.joint_limits();
        let q = mechanism.joints_at(start).ok_or(Unreachable)?;
        if (0..3).any(|j| q[j] < lower[j] || q[j] > upper[j]) {
            return Err(Unreachable);
        }
        let workspace = reachable_box(&mechanism, &lower, &upper);
        Ok(Self {
            rotor_inertia: drives
                .rotor_inertia
                .component_mul(&drives.ratio.component_mul(&drives.ratio)),
            peak: drives.peak_joint_torque(),
            resolution: drives.joint_resolution(),
            mechanism,
            drives,
            env,
            lower,
            upper,
            workspace,
            obstacle: None,
            touching: false,
            on_stop: [false; 3],
            contacts: ContactLog::default(),
            q,
            qd: Vector3::zeros(),
        })
    }

    /// The unit `sim.unit_seed` picks, at rest at `sim.start_position_mm` in `[sim]`'s
    /// environment: `unit` varies the mechanism, then the drives' friction varies.
    ///
    /// # Errors
    /// [`Unreachable`] when the handle cannot start at `sim.start_position_mm`.
    pub fn unit_from_config(
        sim: &SimConfig,
        unit: impl FnOnce(&mut UnitVariation) -> M,
        nominal: Drives,
    ) -> Result<Self, Unreachable> {
        let mut variation = UnitVariation::new(sim.unit_seed);
        let mechanism = unit(&mut variation);
        let drives = Drives {
            coulomb: variation.vary3(nominal.coulomb),
            viscous: variation.vary3(nominal.viscous),
            ..nominal
        };
        let mut linkage = Self::new(
            mechanism,
            drives,
            Environment::from_config(sim),
            &sim.start_position(),
        )?;
        linkage.obstacle = sim.obstacle();
        if linkage.in_obstacle(&linkage.position()) {
            return Err(Unreachable);
        }
        Ok(linkage)
    }

    /// How far `x` (m) is from the obstacle, m (0 inside or without one).
    fn obstacle_distance(&self, x: &Vector3<f64>) -> f64 {
        self.obstacle.map_or(0.0, |(lo, hi)| {
            ((lo - x).sup(&Vector3::zeros()) + (x - hi).sup(&Vector3::zeros())).norm()
        })
    }

    /// Whether `x` (m) lies inside the obstacle.
    fn in_obstacle(&self, x: &Vector3<f64>) -> bool {
        self.obstacle
            .is_some_and(|(lo, hi)| (0..3).all(|a| x[a] > lo[a] && x[a] < hi[a]))
    }

    pub fn mechanism(&self) -> &M {
        &self.mechanism
    }

    /// Joint angles, rad.
    pub fn joints(&self) -> Vector3<f64> {
        self.q
    }

    /// Joint velocities, rad/s.
    pub fn joint_velocities(&self) -> Vector3<f64> {
        self.qd
    }

    /// Put the mechanism at joint angles `q` moving at `qd` (tests).
    pub fn set_state(&mut self, q: Vector3<f64>, qd: Vector3<f64>) {
        self.q = q;
        self.qd = qd;
    }

    /// ∂U/∂q at the current joints, payload included, N m: the joint torques that hold the
    /// mechanism still against gravity.
    pub fn gravity_torque(&self) -> Vector3<f64> {
        let joints = self.joint_state();
        self.dynamics(&joints, &self.mechanism.handle(&joints))
            .gravity
    }

    /// Kinetic energy, J.
    pub fn kinetic_energy(&self) -> f64 {
        let joints = self.joint_state();
        let d = self.dynamics(&joints, &self.mechanism.handle(&joints));
        0.5 * self.qd.dot(&(d.inertia * self.qd))
    }

    /// Potential energy in gravity, J (zero level at the device origin).
    pub fn potential_energy(&self) -> f64 {
        let g = self.env.gravity;
        let at_rest = JointState::at_rest(&self.q);
        let handle = self.mechanism.handle(&at_rest);
        let mut u = -self.env.payload * g.dot(&handle.position);
        let on_handle = self.mechanism.handle_mass();
        if on_handle > 0.0 {
            u -= on_handle * g.dot(&handle.position);
        }
        self.mechanism
            .masses(&at_rest, &mut |m, p| u -= m * g.dot(&p.position));
        u
    }

    /// The joints where the mechanism is now, moving as it moves.
    fn joint_state(&self) -> JointState {
        JointState::new(&self.q, &self.qd)
    }

    /// Inertia, velocity-product and gravity terms at `joints`; `handle` is the handle's
    /// kinematics there (the payload rides on it).
    fn dynamics(&self, joints: &JointState, handle: &Point) -> Dynamics {
        let g = self.env.gravity;
        let (inertia, bias) = self.mechanism.rotations(joints);
        let mut d = Dynamics {
            inertia: inertia + Matrix3::from_diagonal(&self.rotor_inertia),
            bias,
            gravity: Vector3::zeros(),
        };
        let mut add_mass = |m: f64, p: &Point| {
            let jt = p.jacobian.transpose();
            d.inertia += jt * p.jacobian * m;
            d.bias += jt * p.bias * m;
            d.gravity -= jt * g * m;
        };
        if self.env.payload > 0.0 {
            add_mass(self.env.payload, handle);
        }
        let on_handle = self.mechanism.handle_mass();
        if on_handle > 0.0 {
            add_mass(on_handle, handle);
        }
        self.mechanism.masses(joints, &mut add_mass);
        d
    }

    /// How far the torque `phi` a held joint `j` needs lies outside what holds it: static friction
    /// both ways, and a stop without limit in the direction it pushes.
    fn excess(&self, j: usize, phi: f64) -> f64 {
        let band = self.drives.coulomb[j] * self.env.friction_scale;
        if self.q[j] <= self.lower[j] {
            (-band - phi).max(0.0)
        } else if self.q[j] >= self.upper[j] {
            (phi - band).max(0.0)
        } else {
            (phi.abs() - band).max(0.0)
        }
    }
}

/// q̈ with the joints in `held` kept still: the rows and columns of held joints are replaced by
/// identity so their acceleration is zero and the others see them as fixed.
fn solve_held(m: &Matrix3<f64>, rhs: &Vector3<f64>, held: &[bool; 3]) -> Vector3<f64> {
    let mut a = *m;
    let mut b = *rhs;
    for j in 0..3 {
        if held[j] {
            a.set_row(j, &Vector3::zeros().transpose());
            a.set_column(j, &Vector3::zeros());
            a[(j, j)] = 1.0;
            b[j] = 0.0;
        }
    }
    match a.cholesky() {
        Some(c) => c.solve(&b),
        None => a.lu().solve(&b).unwrap_or_else(Vector3::zeros),
    }
}

/// The root r of r |v(r)| = `limit`, with v(r)_i = c_i / (1 + r l_i) over A's modes (l_i, c_i)
/// (l_i = ∞ for a mode A cannot move along), given r |v(r)| → |A⁺ v'| > `limit` as r → ∞.
/// r |v(r)| rises monotonically from 0, so Newton's steps are kept inside a bracket that they,
/// or a bisection where a step would leave it, narrow each time; the first step from 0 lands at
/// `limit` / |v'|. Converges in a handful of steps where bisection alone took some hundred.
fn slide_rate(mode: &[(f64, f64); 3], limit: f64) -> f64 {
    // g(r) = r |v(r)| - limit and its slope: d|v|/dr = -Σ l c² / (1 + r l)³ / |v|.
    let g = |r: f64| {
        let (mut v2, mut dv2) = (0.0, 0.0);
        for &(l, c) in mode {
            if l.is_finite() {
                let q = 1.0 / (1.0 + r * l);
                v2 += c * c * q * q;
                dv2 -= 2.0 * l * c * c * q * q * q;
            }
        }
        let v = v2.sqrt();
        (r * v - limit, v + r * 0.5 * dv2 / v)
    };
    let (mut lo, mut hi) = (0.0, f64::INFINITY);
    let mut r = 0.0;
    for _ in 0..200 {
        let (value, slope) = g(r);
        if value.abs() <= 1e-12 * limit {
            return r;
        }
        if value < 0.0 {
            lo = r;
        } else {
            hi = r;
        }
        let newton = r - value / slope;
        r = if newton > lo && newton < hi && newton.is_finite() {
            newton
        } else if hi.is_finite() {
            0.5 * (lo + hi)
        } else {
            2.0 * lo.max(f64::MIN_POSITIVE)
        };
        if hi.is_finite() && hi - lo <= 1e-15 * hi {
            break;
        }
    }
    r
}

/// The box the handle can reach within the joint limits, from forward kinematics on a lattice of
/// joint angles, padded by 5 mm so no reachable point lies outside it.
fn reachable_box<M: Mechanism>(
    mechanism: &M,
    lower: &Vector3<f64>,
    upper: &Vector3<f64>,
) -> (Vector3<f64>, Vector3<f64>) {
    const STEPS: usize = 12;
    let mut lo = Vector3::repeat(f64::INFINITY);
    let mut hi = Vector3::repeat(f64::NEG_INFINITY);
    for i in 0..=STEPS {
        for j in 0..=STEPS {
            for k in 0..=STEPS {
                let s = Vector3::new(i as f64, j as f64, k as f64) / STEPS as f64;
                let q = lower + (upper - lower).component_mul(&s);
                let x = mechanism.handle(&JointState::at_rest(&q)).position;
                if x.iter().all(|c| c.is_finite()) {
                    lo = lo.inf(&x);
                    hi = hi.sup(&x);
                }
            }
        }
    }
    (lo.add_scalar(-0.005), hi.add_scalar(0.005))
}

impl<M: Mechanism> Linkage<M> {
    /// Integrate for `dt` seconds under the motor torques `torque` at the joints (N m, limited
    /// here to the motors' peak): a joint-space device's firmware drives its arm this way. The
    /// environment's spring and damping act at the handle as under [`Plant::step`].
    pub fn step_joint_torque(&mut self, torque: &Vector3<f64>, dt: f64) {
        let joints = self.joint_state();
        let handle = self.mechanism.handle(&joints);
        self.step_with(&joints, &handle, torque, dt);
    }

    /// The environment's force on the handle at `handle`: the spring toward its anchor and the
    /// viscous damping of the handle's velocity, N.
    fn external_force(&self, handle: &Point) -> Vector3<f64> {
        let (k, anchor) = self.env.spring;
        -(handle.position - anchor) * k - handle.jacobian * self.qd * self.env.handle_damping
    }

    /// The joint angles the encoders see with the handle displaced by `noise` (m) from where it
    /// is, before they are quantised, rad.
    pub fn sensed_joints(&self, noise: &Vector3<f64>) -> Vector3<f64> {
        let zero = Vector3::zeros();
        if *noise == zero {
            return self.q;
        }
        let j = self
            .mechanism
            .handle(&JointState::at_rest(&self.q))
            .jacobian;
        self.q + j.lu().solve(noise).unwrap_or(zero)
    }

    /// The inelastic impulse of the stops that the joints marked `into` ran into (see
    /// [`Linkage::step_with`]): those whose velocity points into their stop end at rest, the
    /// others move on with the momentum `inertia` (the joint-space inertia) passes them.
    fn stop_at_limits(&mut self, inertia: &Matrix3<f64>, into: &[bool; 3]) {
        let pushing = |q: f64, qd: f64, lower: f64, upper: f64| {
            (q >= upper && qd > 0.0) || (q <= lower && qd < 0.0)
        };
        // Projected joint by joint, in rounds (two or three stops at once converge in a few).
        if let Some(mobility) = inertia.try_inverse() {
            for _ in 0..IMPULSE_ROUNDS {
                for j in (0..3).filter(|&j| into[j]) {
                    let (q, qd) = (self.q[j], self.qd[j]);
                    let column = mobility.column(j);
                    if pushing(q, qd, self.lower[j], self.upper[j]) && column[j] > 0.0 {
                        self.qd -= column * (qd / column[j]);
                    }
                }
            }
        }
        for j in (0..3).filter(|&j| into[j]) {
            if pushing(self.q[j], self.qd[j], self.lower[j], self.upper[j])
                || self.qd[j].abs() < 1e-12
            {
                self.qd[j] = 0.0;
            }
        }
    }

    /// Coulomb friction at the handle over one step of `dt`, implicit as the point mass's: with
    /// A = J M⁻¹ Jᵀ the handle's mobility (through the joints that are not held) and v' the
    /// handle's velocity the other forces give, the new velocity v minimises
    /// ½ (v − v')ᵀ A⁺ (v − v') + f_c dt |v|. The handle stops when friction can hold it,
    /// |A⁺ v'| ≤ f_c dt (the least impulse that stops it; from rest, the net force within f_c);
    /// otherwise it slides with v = (I + r A)⁻¹ v', r the root of r |v| = f_c dt, and friction
    /// takes f_c dt of momentum against v. Held joints' own friction is left to hold what the
    /// handle's impulse adds to them.
    fn brake_at_handle(&mut self, inertia: &Matrix3<f64>, jacobian: &Matrix3<f64>, dt: f64) {
        let velocity = jacobian * self.qd;
        if velocity == Vector3::zeros() {
            return;
        }
        let held = [0, 1, 2].map(|j| self.qd[j] == 0.0);
        let jt = jacobian.transpose();
        let limit = self.env.handle_friction * dt;
        // With no joint held, A = J M⁻¹ Jᵀ is invertible wherever J is, and the impulse that
        // stops the handle is A⁻¹ v' = J⁻ᵀ M q̇: the common case (a handle at rest, nudged
        // within its friction) is decided without A's modes.
        if !held.contains(&true) {
            if let Some(stopping) = jt.lu().solve(&(inertia * self.qd)) {
                if stopping.norm() <= limit {
                    self.qd = Vector3::zeros();
                    return;
                }
            }
        }
        let through = |impulse: &Vector3<f64>| solve_held(inertia, &(jt * impulse), &held);
        let mobility = Matrix3::from_columns(&[0, 1, 2].map(|i| {
            let unit = Vector3::ith(i, 1.0);
            jacobian * through(&unit)
        }));
        let modes = (mobility + mobility.transpose())
            .scale(0.5)
            .symmetric_eigen();
        let largest = modes.eigenvalues.max();
        if largest.is_nan() || largest <= 0.0 {
            return;
        }
        // Each mode of A: (mobility, the velocity's component); modes A cannot move along
        // (held joints) carry none of the velocity.
        let along = modes.eigenvectors.transpose() * velocity;
        let mode = [0, 1, 2].map(|i| {
            let l = modes.eigenvalues[i];
            if l > 1e-9 * largest {
                (l, along[i])
            } else {
                (f64::INFINITY, 0.0)
            }
        });
        let holding = Vector3::from_fn(|i, _| mode[i].1 / mode[i].0).norm();
        if holding <= limit {
            self.qd = Vector3::zeros();
            return;
        }
        // The sliding velocity (I + r A)⁻¹ v' in A's modes.
        let slide_at = |r: f64| Vector3::from_fn(|i, _| mode[i].1 / (1.0 + r * mode[i].0));
        let r = slide_rate(&mode, limit);
        let slide = modes.eigenvectors * slide_at(r);
        self.qd += through(&(slide * (-limit / slide.norm())));
    }

    /// One step under the motors' joint torques `torque` (limited here to their peak) and the
    /// environment's spring and damping at the handle ([`Linkage::external_force`]: no motor's
    /// to limit), N m.
    fn step_with(&mut self, joints: &JointState, handle: &Point, torque: &Vector3<f64>, dt: f64) {
        let external = handle.jacobian.transpose() * self.external_force(handle);
        let actuator = torque.zip_map(&self.peak, |t, peak| t.clamp(-peak, peak)) + external;
        let d = self.dynamics(joints, handle);
        let scale = self.env.friction_scale;
        // Every torque but the holding reaction of held joints; sliding joints feel Coulomb
        // friction against their motion.
        let mut free =
            actuator - d.bias - d.gravity - self.drives.viscous.component_mul(&self.qd) * scale;
        let mut held = [false; 3];
        for j in 0..3 {
            if self.qd[j] == 0.0 {
                held[j] = true;
            } else {
                free[j] -= self.drives.coulomb[j] * scale * self.qd[j].signum();
            }
        }
        // Release, one at a time, the held joint whose needed holding torque is furthest outside
        // its band; it starts to slide against kinetic friction.
        let qdd = loop {
            let qdd = solve_held(&d.inertia, &free, &held);
            let phi = d.inertia * qdd - free;
            let mut worst = None;
            let mut worst_excess = 0.0;
            for j in (0..3).filter(|&j| held[j]) {
                let e = self.excess(j, phi[j]);
                if e > worst_excess {
                    worst = Some(j);
                    worst_excess = e;
                }
            }
            match worst {
                None => break qdd,
                Some(j) => {
                    held[j] = false;
                    free[j] += self.drives.coulomb[j] * scale * phi[j].signum();
                }
            }
        };
        for j in 0..3 {
            let before = self.qd[j];
            let after = if held[j] { 0.0 } else { before + qdd[j] * dt };
            // Coulomb friction stops a sliding joint; it stays held until the torque breaks away.
            let stopped =
                before != 0.0 && after * before <= 0.0 && self.drives.coulomb[j] * scale > 0.0;
            self.qd[j] = if stopped { 0.0 } else { after };
        }
        if self.env.handle_friction > 0.0 {
            self.brake_at_handle(&d.inertia, &handle.jacobian, dt);
        }
        let before = self.q;
        self.q += self.qd * dt;
        self.contacts.tick(dt);
        // Hard stops: an inelastic impulse at each stop a joint runs into. That joint stops, and
        // the others take the momentum the mechanism's inertia passes them: the new velocity is
        // the one nearest the old in the kinetic-energy metric with those joints at rest, so a
        // stop never adds energy (zeroing the joint alone would set the others' velocities
        // free of the one that balanced them, and a parallel arm's handle would leap off along
        // the stop). A contact is a stop the joint was not resting on before; its speed is the
        // handle's speed towards the surface the stop makes in the handle's space (the joint's
        // rate over the gradient of its angle there), not the speed it slides on along it.
        let moving = self.qd;
        let mut approach: f64 = 0.0;
        let mut into = [false; 3];
        let mut met = false;
        for j in 0..3 {
            if self.q[j] < self.lower[j] || self.q[j] > self.upper[j] {
                self.q[j] = self.q[j].clamp(self.lower[j], self.upper[j]);
                into[j] = true;
                if before[j] != self.q[j] && !self.on_stop[j] {
                    met = true;
                    approach = approach.max(towards_stop(&handle.jacobian, j, moving[j]));
                }
                self.on_stop[j] = true;
            } else if (self.q[j] - self.lower[j]).min(self.upper[j] - self.q[j]) > JOINT_RELEASE {
                self.on_stop[j] = false;
            }
        }
        if into.contains(&true) {
            self.stop_at_limits(&d.inertia, &into);
        }
        // The obstacle stops the whole arm where it was (a sticky, inelastic wall).
        if self.obstacle.is_some() {
            if self.in_obstacle(&self.position()) {
                self.q = before;
                // The whole arm stops, at the speed it had.
                approach = approach.max((handle.jacobian * moving).norm());
                self.qd = Vector3::zeros();
                met |= !self.touching;
                self.touching = true;
            } else if self.obstacle_distance(&self.position()) > RELEASE {
                self.touching = false;
            }
        }
        if met {
            self.contacts.record(self.position(), approach);
        }
    }
}

/// The handle's speed towards the surface on which joint `j` is at a limit, joint rate `rate`
/// (rad/s) with handle Jacobian `jacobian`, m/s: the rate over the gradient of the joint's
/// angle in the handle's space (row j of the inverse Jacobian); the whole speed the joint gives
/// the handle where the Jacobian is singular.
fn towards_stop(jacobian: &Matrix3<f64>, j: usize, rate: f64) -> f64 {
    match jacobian.try_inverse() {
        Some(inverse) if inverse.row(j).norm() > 0.0 => rate.abs() / inverse.row(j).norm(),
        _ => (jacobian.column(j) * rate).norm(),
    }
}

impl<M: Mechanism> Plant for Linkage<M> {
    fn step(&mut self, force: &Vector3<f64>, dt: f64) {
        let joints = self.joint_state();
        let handle = self.mechanism.handle(&joints);
        self.step_with(&joints, &handle, &(handle.jacobian.transpose() * force), dt);
    }

    fn position(&self) -> Vector3<f64> {
        self.mechanism
            .handle(&JointState::at_rest(&self.q))
            .position
    }

    fn velocity(&self) -> Vector3<f64> {
        self.mechanism.handle(&self.joint_state()).jacobian * self.qd
    }

    fn workspace(&self) -> (Vector3<f64>, Vector3<f64>) {
        self.workspace
    }

    fn contacts(&self) -> &ContactLog {
        &self.contacts
    }

    fn holding_force(&self) -> Vector3<f64> {
        // NaN only at a singular pose, which the joint limits keep the mechanisms away from.
        let at_rest = JointState::at_rest(&self.q);
        let handle = self.mechanism.handle(&at_rest);
        let tau = self.dynamics(&at_rest, &handle).gravity;
        let (k, anchor) = self.env.spring;
        handle
            .jacobian
            .transpose()
            .lu()
            .solve(&tau)
            .map(|f| f + (handle.position - anchor) * k)
            .unwrap_or_else(|| Vector3::repeat(f64::NAN))
    }

    fn moving_mass_per_axis(&self) -> Vector3<f64> {
        let at_rest = JointState::at_rest(&self.q);
        let handle = self.mechanism.handle(&at_rest);
        let mobility = self
            .dynamics(&at_rest, &handle)
            .inertia
            .try_inverse()
            .map(|h| handle.jacobian * h * handle.jacobian.transpose());
        mobility.map_or(Vector3::repeat(f64::NAN), |m| m.diagonal().map(|d| 1.0 / d))
    }

    fn up(&self) -> Vector3<f64> {
        -self.env.gravity.normalize()
    }

    fn sensed_position(&self, noise: &Vector3<f64>) -> Vector3<f64> {
        let q = self.sensed_joints(noise);
        let counts = q.component_div(&self.resolution).map(f64::round);
        self.mechanism
            .handle(&JointState::at_rest(
                &counts.component_mul(&self.resolution),
            ))
            .position
    }

    fn set_world(&mut self, payload_kg: f64, up: &Vector3<f64>) {
        self.env.payload = payload_kg;
        self.env.gravity = -up * self.env.gravity.norm();
    }
}

/// Checks every linkage plant's tests run: kinematics against finite differences, gravity as the
/// gradient of the potential energy, energy conservation and holding still.
#[cfg(test)]
pub(crate) mod checks {
    use super::*;

    /// Standard gravity, m/s².
    pub(crate) const G: f64 = 9.81;

    /// Gravity straight down −z, with `payload` (kg) on the handle and friction scaled by
    /// `friction_scale`.
    pub(crate) fn env(friction_scale: f64, payload: f64) -> Environment {
        Environment {
            gravity: Vector3::new(0.0, 0.0, -G),
            payload,
            friction_scale,
            handle_friction: 0.0,
            spring: (0.0, Vector3::zeros()),
            handle_damping: 0.0,
        }
    }

    /// `mechanism` with `drives` at rest in `env`, its handle at `x_mm` (mm).
    pub(crate) fn at<M: Mechanism>(
        mechanism: M,
        drives: Drives,
        x_mm: [f64; 3],
        env: Environment,
    ) -> Linkage<M> {
        Linkage::new(mechanism, drives, env, &(Vector3::from(x_mm) * 1e-3)).unwrap()
    }

    /// Gravity tilted off every device axis, with a 30 g payload.
    pub(crate) fn tilted() -> Environment {
        Environment {
            gravity: -Vector3::new(0.17, -0.05, 1.0).normalize() * G,
            payload: 0.03,
            friction_scale: 1.0,
            handle_friction: 0.0,
            spring: (0.0, Vector3::zeros()),
            handle_damping: 0.0,
        }
    }

    /// A spring and damping in `plant`'s environment act alike whether the arm is driven by a
    /// handle force or by the joint torques Jᵀ F a joint-space firmware sends: the same motion
    /// under `force` (N) for 0.2 s.
    pub(crate) fn assert_the_environment_acts_under_joint_torques<M: Mechanism + Clone>(
        plant: Linkage<M>,
        force: &Vector3<f64>,
    ) {
        let (mut by_force, mut by_torque) = (plant.clone(), plant);
        let dt = 1e-4;
        for _ in 0..2000 {
            by_force.step(force, dt);
            let handle = by_torque.mechanism.handle(&by_torque.joint_state());
            by_torque.step_joint_torque(&(handle.jacobian.transpose() * force), dt);
        }
        let apart = (by_force.position() - by_torque.position()).norm();
        assert!(apart < 1e-9, "{apart} m apart");
    }

    /// Handle positions over the ±40 mm calibration cube, `steps` intervals an edge, mm.
    pub(crate) fn cube(steps: u32) -> impl Iterator<Item = [f64; 3]> {
        let at = move |n: u32| -40.0 + 80.0 * f64::from(n) / f64::from(steps);
        (0..=steps).flat_map(move |i| {
            (0..=steps).flat_map(move |j| (0..=steps).map(move |k| [at(i), at(j), at(k)]))
        })
    }

    /// The handle and every lumped mass at (q, q̇): each Jacobian column is ∂x/∂q_j by central
    /// differences (within 1e-8) and each bias is J̇ q̇ (within `bias_tolerance`).
    pub(crate) fn assert_points_match_finite_differences<M: Mechanism>(
        mechanism: &M,
        q: &Vector3<f64>,
        qd: &Vector3<f64>,
        bias_tolerance: f64,
    ) {
        let zero = Vector3::zeros();
        let h = 1e-6;
        let points = |q: &Vector3<f64>, qd: &Vector3<f64>| {
            let joints = JointState::new(q, qd);
            let handle = mechanism.handle(&joints);
            let mut all = vec![handle];
            mechanism.masses(&joints, &mut |_, p| all.push(*p));
            all
        };
        for (n, p) in points(q, qd).iter().enumerate() {
            let at = |q: &Vector3<f64>| points(q, &zero)[n];
            for j in 0..3 {
                let mut e = Vector3::zeros();
                e[j] = h;
                let column = (at(&(q + e)).position - at(&(q - e)).position) / (2.0 * h);
                assert!(
                    (column - p.jacobian.column(j)).amax() < 1e-8,
                    "point {n} at {q:?}"
                );
            }
            // J̇ q̇ = d/dt (J) q̇ along the motion.
            let jdot = (at(&(q + qd * h)).jacobian - at(&(q - qd * h)).jacobian) / (2.0 * h);
            assert!(
                (jdot * qd - p.bias).amax() < bias_tolerance,
                "point {n} at {q:?}"
            );
        }
    }

    /// At joints `q` the gravity torque is ∂U/∂q by central differences, within 1e-8 N m.
    pub(crate) fn assert_gravity_torque_is_the_gradient<M: Mechanism>(
        plant: &mut Linkage<M>,
        q: &Vector3<f64>,
    ) {
        let h = 1e-6;
        let mut fd = Vector3::zeros();
        for j in 0..3 {
            let mut e = Vector3::zeros();
            e[j] = h;
            plant.set_state(q + e, Vector3::zeros());
            let up = plant.potential_energy();
            plant.set_state(q - e, Vector3::zeros());
            fd[j] = (up - plant.potential_energy()) / (2.0 * h);
        }
        plant.set_state(*q, Vector3::zeros());
        assert!((plant.gravity_torque() - fd).amax() < 1e-8, "{q:?}");
    }

    /// Free motion for `duration` s in steps of `dt`, asserting no stop is reached: (largest
    /// error of the total energy, largest kinetic energy on the way), J.
    pub(crate) fn free_motion_energy<M: Mechanism>(
        plant: &mut Linkage<M>,
        duration: f64,
        dt: f64,
    ) -> (f64, f64) {
        let start = plant.kinetic_energy() + plant.potential_energy();
        let (lo, hi) = plant.mechanism().joint_limits();
        let (mut worst, mut peak) = (0.0f64, 0.0f64);
        for _ in 0..(duration / dt).round() as usize {
            plant.step(&Vector3::zeros(), dt);
            let q = plant.joints();
            assert!(
                (0..3).all(|j| q[j] > lo[j] && q[j] < hi[j]),
                "hit a stop: {q:?}"
            );
            peak = peak.max(plant.kinetic_energy());
            worst = worst.max((plant.kinetic_energy() + plant.potential_energy() - start).abs());
        }
        (worst, peak)
    }

    /// `drift(dt)`, a relative energy error of free motion, is below 2e-3 at 0.1 ms and falls
    /// with dt: the error is the integrator's, first order in dt, not the model's.
    pub(crate) fn assert_energy_is_conserved(drift: impl Fn(f64) -> f64) {
        let (coarse, fine) = (drift(1e-4), drift(2.5e-5));
        assert!(coarse < 2e-3, "{coarse}");
        assert!(fine < coarse / 3.0, "{fine} vs {coarse}");
    }

    /// A frictionless plant given its own holding force stays within 1 µm for 3 s.
    pub(crate) fn assert_holding_force_holds_still<M: Mechanism>(mut plant: Linkage<M>) {
        let start = plant.position();
        let hold = plant.holding_force();
        for _ in 0..30_000 {
            plant.step(&hold, 1e-4);
        }
        assert!(
            (plant.position() - start).norm() < 1e-6,
            "from {start:?} drifted to {:?}",
            plant.position()
        );
    }

    /// Weightless, frictionless joints, handle friction 0.1 N: the handle from `x_mm` stays put
    /// pushed with 0.9 f_c along each axis and a diagonal, moves pushed with 1.1 f_c, and
    /// thrown at 20 mm/s it stops having turned its kinetic energy into friction's work, f_c
    /// times the path (within 2 %).
    pub(crate) fn assert_handle_friction_sticks_and_slides<M: Mechanism>(
        plant_at: impl Fn([f64; 3], Environment) -> Linkage<M>,
        x_mm: [f64; 3],
    ) {
        let f_c = 0.1;
        let env = Environment {
            gravity: Vector3::zeros(),
            payload: 0.0,
            friction_scale: 0.0,
            handle_friction: f_c,
            spring: (0.0, Vector3::zeros()),
            handle_damping: 0.0,
        };
        let dt = 1e-4;
        for direction in [
            Vector3::x(),
            -Vector3::y(),
            Vector3::z(),
            Vector3::new(1.0, -1.0, 1.0).normalize(),
        ] {
            let pushed = |share: f64| {
                let mut plant = plant_at(x_mm, env);
                let start = plant.position();
                for _ in 0..5_000 {
                    plant.step(&(direction * (share * f_c)), dt);
                }
                plant.position() - start
            };
            assert_eq!(pushed(0.9), Vector3::zeros(), "{direction:?}");
            let moved = pushed(1.1);
            assert!(moved.dot(&direction) > 1e-5, "{direction:?}: {moved:?}");
        }
        let mut plant = plant_at(x_mm, env);
        let q = plant.joints();
        let handle = plant.mechanism().handle(&JointState::at_rest(&q));
        let thrown = handle
            .jacobian
            .lu()
            .solve(&Vector3::new(0.012, 0.0, -0.016));
        plant.set_state(q, thrown.unwrap());
        let energy = plant.kinetic_energy();
        let mut path = 0.0;
        for _ in 0..20_000 {
            let before = plant.position();
            plant.step(&Vector3::zeros(), dt);
            path += (plant.position() - before).norm();
        }
        assert_eq!(plant.joint_velocities(), Vector3::zeros());
        let work = f_c * path;
        assert!(
            (work - energy).abs() < 0.02 * energy,
            "{work} J vs {energy} J"
        );
    }

    /// Over the calibration cube (11 points an edge) the gravity force −holding force of
    /// `plant_at(x_mm)`: (least, most, N; largest angle from `direction`, degrees; largest part
    /// across the z axis, N).
    pub(crate) fn gravity_force_spread<M: Mechanism>(
        plant_at: impl Fn([f64; 3]) -> Linkage<M>,
        direction: &Vector3<f64>,
    ) -> (f64, f64, f64, f64) {
        let (mut least, mut most, mut steepest, mut sideways) =
            (f64::INFINITY, 0.0f64, 0.0f64, 0.0f64);
        for x in cube(10) {
            let f = -plant_at(x).holding_force();
            least = least.min(f.norm());
            most = most.max(f.norm());
            steepest = steepest.max((f.dot(direction) / f.norm()).acos().to_degrees());
            sideways = sideways.max(f.xy().norm());
        }
        (least, most, steepest, sideways)
    }

    /// Units 1 and 2 of `from_config` hold their home pose with forces that differ from each
    /// other and from the nominal unit's `nominal` (unit 0) by a relative `change`.
    pub(crate) fn assert_units_differ<M: Mechanism>(
        from_config: fn(&SimConfig) -> Result<Linkage<M>, Unreachable>,
        nominal: Vector3<f64>,
        change: std::ops::Range<f64>,
    ) {
        let force = |seed: u64| {
            let sim = SimConfig {
                unit_seed: seed,
                ..SimConfig::default()
            };
            from_config(&sim).unwrap().holding_force()
        };
        let (zero, one, two) = (force(0), force(1), force(2));
        assert_eq!(zero, nominal);
        for f in [one, two] {
            let c = (f - nominal).norm() / nominal.norm();
            assert!(change.contains(&c), "{c}");
        }
        assert_ne!(one, two);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The sliding rate meets r |v(r)| = limit to roundoff, on mobilities spread over six
    /// decades (the delta's modes differ by up to three), with a mode A cannot move along, and
    /// from an impulse just above the stick limit to ten thousand times it.
    #[test]
    fn the_sliding_rate_is_the_root_of_the_friction_impulse() {
        let norm_at = |mode: &[(f64, f64); 3], r: f64| {
            mode.iter()
                .filter(|(l, _)| l.is_finite())
                .map(|(l, c)| (c / (1.0 + r * l)).powi(2))
                .sum::<f64>()
                .sqrt()
        };
        for mode in [
            [(1.0, 0.3), (2.0, -0.2), (5.0, 0.1)],
            [(1e-3, 0.01), (1.0, -0.5), (1e3, 2.0)],
            [(10.0, 0.0), (f64::INFINITY, 0.0), (0.5, -1.0)],
        ] {
            // |A⁺ v'|, the most friction can take: the root exists below it.
            let stopping = mode
                .iter()
                .map(|(l, c)| (c / l).powi(2))
                .sum::<f64>()
                .sqrt();
            for share in [0.9999, 0.5, 1e-4] {
                let limit = share * stopping;
                let r = slide_rate(&mode, limit);
                let reached = r * norm_at(&mode, r);
                assert!(
                    (reached - limit).abs() <= 1e-9 * limit,
                    "{mode:?}, {share}: r = {r}, r |v| = {reached}, limit {limit}"
                );
            }
        }
    }

    /// The handle brake's quick stick test (no joint held: the stopping impulse is J⁻ᵀ M q̇)
    /// and its test in A's modes decide alike: on the PHANToM and the delta, thrown in ten
    /// directions, the handle sticks when friction's impulse is 1 % above |A⁻¹ v|, computed
    /// here from A = J M⁻¹ Jᵀ inverted outright, and slides, slower, when it is 1 % below (the
    /// quick test passes that case on to the modes).
    #[test]
    fn the_quick_stick_test_and_the_modes_agree_on_the_stopping_impulse() {
        let sim = SimConfig::default();
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let phantom = crate::sim::phantom::from_config(&sim).unwrap();
        let delta = crate::sim::delta::from_config(&sim).unwrap();
        fn check<M: Mechanism + Clone>(plant: &Linkage<M>, rng: &mut ChaCha8Rng) {
            for _ in 0..10 {
                let mut plant = plant.clone();
                let q = plant.joints();
                let qd = Vector3::from_fn(|_, _| rng.gen_range(-0.5..0.5));
                plant.set_state(q, qd);
                let joints = JointState::new(&q, &qd);
                let handle = plant.mechanism().handle(&joints);
                let d = plant.dynamics(&joints, &handle);
                let j = handle.jacobian;
                let a = j * d.inertia.try_inverse().unwrap() * j.transpose();
                let stopping = (a.try_inverse().unwrap() * (j * qd)).norm();
                let dt = 1e-3;
                for (share, sticks) in [(1.01, true), (0.99, false)] {
                    let mut braked = plant.clone();
                    braked.env.handle_friction = share * stopping / dt;
                    braked.brake_at_handle(&d.inertia, &j, dt);
                    let speed = (j * braked.qd).norm();
                    if sticks {
                        assert_eq!(braked.qd, Vector3::zeros(), "{qd:?}");
                    } else {
                        assert!(speed > 0.0 && speed < (j * qd).norm(), "{qd:?}: {speed}");
                    }
                }
            }
        }
        check(&phantom, &mut rng);
        check(&delta, &mut rng);
    }
}
