//! On-line gravity compensation (paper §4, Eq. 15): F = Z_E + F_G(X), where Z_E is the force
//! offset an application renders and F_G the calibrated gravity force:
//! - scalar mode (the paper): F_G = M(X) g v_G with M trilinearly interpolated;
//! - vector mode: the per-vertex holding forces measured during calibration, interpolated with
//!   the same weights (keeps the horizontal components a real linkage has);
//! - arm mode: J⁻ᵀ τ_g of the arm model fitted at calibration (`arm`, `fit`), everywhere the arm
//!   reaches; arm + residual: that plus the vector lattice of what it left over at the vertices,
//!   fading to nothing over one spacing beyond the lattice.
//!
//! The offset follows the application: a stale offset (no update for `stale_after`) ramps to zero
//! over `ramp_time`; removing it (client gone) is immediate.

use nalgebra::{Rotation3, Vector3};

use super::{ControlOutput, Controller, DeviceState};
use crate::arm::ArmGravity;
pub use crate::config::{CompensationMode, OutsideGrid};
use crate::grid::{EffectRecord, GridFile, MassGrid, Problem};

/// The calibrated gravity force field F_G(X).
#[derive(Clone, Debug, PartialEq)]
pub struct GravityModel {
    pub grid: MassGrid,
    pub mode: CompensationMode,
    pub outside: OutsideGrid,
    /// Per-vertex holding forces (vector mode) or what the arm model left of them (arm +
    /// residual), grid order, N.
    forces: Vec<Vector3<f64>>,
    /// The arm model (arm modes).
    arm: Option<ArmGravity>,
    /// The held-out score of this model at calibration, % (`[model] held_out_pct`; None for a
    /// grid without one).
    pub held_out_pct: Option<f64>,
    /// Forces of the position alone added to the grid's ([`StaticEffect`]).
    effect: Option<StaticEffect>,
    /// Unit direction against gravity: the arm model's v_G where the grid has one (a linkage's
    /// lattice v_G is the direction of its holding forces, which its counterweights turn),
    /// else the lattice's.
    pub up: Vector3<f64>,
}

/// The forces of the position alone that `hgcd analyze` found missing from a grid
/// (docs/discrepancy.md §5), compensated with it: the grid's force and a payload's weight
/// turned by a tilt, plus a spring.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StaticEffect {
    /// Gravity turned since the calibration: R (F_G + m_p g v_G).
    pub tilt: Rotation3<f64>,
    /// A payload's weight m_p g v_G, N.
    pub weight: Vector3<f64>,
    /// A spring k (X − X_0): the force that holds against it (stiffness N/m, anchor m).
    pub spring: Option<(f64, Vector3<f64>)>,
    /// The most force the effects may add to the grid's, N: twice the largest gravity force the
    /// calibration measured at its vertices (set by [`GravityModel::with_effect`]). A model
    /// file cannot make the daemon push harder than the device's own weight could.
    pub bound: f64,
}

impl StaticEffect {
    /// The effects of `records` on a grid with v_G `up` and `g` (None when none is a force of
    /// the position), and for each one left out, the reason. Friction, damping and a delay
    /// are not forces of the position: compensating them feeds energy into the handle (a
    /// negative damping), so they are left out with the reason.
    pub fn from_records(
        records: &[EffectRecord],
        up: &Vector3<f64>,
        g: f64,
    ) -> (Option<Self>, Vec<(EffectRecord, &'static str)>) {
        let mut effect = Self {
            tilt: Rotation3::identity(),
            weight: Vector3::zeros(),
            spring: None,
            bound: f64::INFINITY,
        };
        let mut any = false;
        let mut refused = Vec::new();
        for record in records {
            match record {
                EffectRecord::None => {}
                EffectRecord::Payload { mass_kg } => {
                    effect.weight += up * (mass_kg * g);
                    any = true;
                }
                EffectRecord::GravityTilt {
                    angle_rad,
                    rotation_axis,
                } => {
                    // Tilts compose, the later turning the earlier (a model file's, then
                    // what `auto_update` took in).
                    effect.tilt =
                        Rotation3::new(Vector3::from(*rotation_axis) * *angle_rad) * effect.tilt;
                    any = true;
                }
                EffectRecord::Spring {
                    stiffness_n_per_m,
                    anchor_m,
                } => {
                    effect.spring = Some((*stiffness_n_per_m, Vector3::from(*anchor_m)));
                    any = true;
                }
                EffectRecord::CoulombFriction { .. } | EffectRecord::ViscousDamping { .. } => {
                    refused.push((
                        record.clone(),
                        "friction opposes the motion; compensating it feeds energy in \
                         (negative damping) and can make the handle run away",
                    ))
                }
                EffectRecord::TimeDelay { .. } => refused.push((
                    record.clone(),
                    "a delay is not a force; shorten the device's force path instead",
                )),
            }
        }
        (any.then_some(effect), refused)
    }

    /// The force with these effects, at `x`, of a grid whose force there is `grid`, N.
    fn apply(&self, x: &Vector3<f64>, grid: Vector3<f64>) -> Vector3<f64> {
        let mut f = self.tilt * (grid + self.weight);
        if let Some((stiffness, anchor)) = self.spring {
            f += (x - anchor) * stiffness;
        }
        let added = f - grid;
        let size = added.norm();
        if size > self.bound {
            grid + added * (self.bound / size)
        } else {
            f
        }
    }
}

/// Why a grid cannot serve as a gravity model.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ModelError {
    #[error(
        "vector mode needs per-vertex force vectors ([vertices] force_vectors) and this grid has \
         none: recalibrate with this version of hgcd, or use compensation.mode = \"scalar\""
    )]
    NoForceVectors,
    #[error(
        "compensation.mode = \"{mode}\" needs the arm model a calibration fits for a device whose \
         profile has an arm, and this grid has none (docs/calibration.md §13): use \"vector\" or \
         \"scalar\", or calibrate with such a profile"
    )]
    NoArm { mode: CompensationMode },
    #[error("its arm model is unusable: {0}")]
    BadArm(Problem),
}

impl GravityModel {
    /// The model of a grid file: its lattice, and in vector mode its per-vertex force vectors;
    /// in the arm modes its arm model, and for arm + residual the vector lattice of what the arm
    /// model leaves at the measured vertices (the others filled from them).
    ///
    /// Errors: [`ModelError::NoForceVectors`] in a vector mode for a grid without them,
    /// [`ModelError::NoArm`] in an arm mode for a grid without an arm model.
    pub fn new(
        file: GridFile,
        mode: CompensationMode,
        outside: OutsideGrid,
    ) -> Result<Self, ModelError> {
        let vertex_forces = || {
            let forces = &file.vertices.force_vectors;
            if forces.len() != file.grid.vertex_count() {
                return Err(ModelError::NoForceVectors);
            }
            Ok(forces
                .iter()
                .copied()
                .map(Vector3::from)
                .collect::<Vec<_>>())
        };
        let arm = match mode {
            CompensationMode::Arm | CompensationMode::ArmResidual => {
                let record = file.arm.as_ref().ok_or(ModelError::NoArm { mode })?;
                Some(record.gravity().map_err(ModelError::BadArm)?)
            }
            _ => None,
        };
        let forces: Vec<Vector3<f64>> = match mode {
            CompensationMode::Scalar | CompensationMode::Arm => Vec::new(),
            CompensationMode::Vector => vertex_forces()?,
            CompensationMode::ArmResidual => {
                let arm = arm.as_ref().expect("an arm mode");
                let measured = file.measured();
                let mut left: Vec<Vector3<f64>> = vertex_forces()?
                    .iter()
                    .enumerate()
                    .map(|(n, f)| {
                        let (i, j, k) = file.grid.coordinates(n);
                        f - arm.force(&file.grid.vertex_position(i, j, k))
                    })
                    .collect();
                file.fill_unmeasured(&mut left, &measured);
                left
            }
        };
        let held_out_pct = file.model.as_ref().and_then(|m| m.held_out_pct.of(mode));
        let up = file
            .arm
            .as_ref()
            .map(|a| Vector3::from(a.gravity_direction))
            .filter(|up| (up.norm() - 1.0).abs() < 1e-6)
            .unwrap_or(file.grid.gravity_direction);
        Ok(Self {
            grid: file.grid,
            mode,
            outside,
            forces,
            arm,
            held_out_pct,
            effect: None,
            up,
        })
    }

    /// This model with `effect` added to it.
    /// An arm model turns the gravity it holds the arm against, not the handle force: a tilt
    /// turns the arm model's v_G (and a payload's weight with it), and the lattice's residual
    /// stays as measured.
    pub fn with_effect(self, effect: Option<StaticEffect>) -> Self {
        // The bound: twice the largest force the calibration measured at a vertex.
        let g = &self.grid;
        let largest = (0..g.vertex_count())
            .map(|n| {
                let (i, j, k) = g.coordinates(n);
                self.force(&g.vertex_position(i, j, k)).norm()
            })
            .fold(0.0, f64::max);
        self.with_effect_bounded(effect, 2.0 * largest)
    }

    /// [`GravityModel::with_effect`] with the effects' added force bounded by `bound`, N
    /// (`f64::INFINITY`: the model as it is, for fitting the effects to measurements).
    pub fn with_effect_bounded(mut self, effect: Option<StaticEffect>, bound: f64) -> Self {
        let effect = effect.map(|e| StaticEffect { bound, ..e });
        self.effect = match (effect, &mut self.arm) {
            (Some(mut effect), Some(arm)) => {
                arm.up = effect.tilt * arm.up;
                self.up = arm.up;
                effect.weight = effect.tilt * effect.weight;
                effect.tilt = Rotation3::identity();
                Some(effect)
            }
            (effect, _) => effect,
        };
        self
    }

    /// This model with gravity turned further by `tilt` and `payload_kg` more on the handle,
    /// composed with the effects it has as `compensation.auto_update` composes them, and
    /// unbounded: what such a change would make its force, for reading one from forces
    /// measured.
    pub fn changed(&self, tilt: &Rotation3<f64>, payload_kg: f64) -> Self {
        let mut model = self.clone();
        let GravityModel {
            grid,
            arm,
            effect,
            up,
            ..
        } = &mut model;
        let effect = effect.get_or_insert(StaticEffect {
            tilt: Rotation3::identity(),
            weight: Vector3::zeros(),
            spring: None,
            bound: f64::INFINITY,
        });
        effect.bound = f64::INFINITY;
        let weight = *up * (payload_kg * grid.g);
        match arm {
            // Its tilts are folded into the arm's v_G, the weights turned with them.
            Some(arm) => {
                effect.weight = tilt * (effect.weight + weight);
                arm.up = tilt * arm.up;
                *up = arm.up;
            }
            None => {
                effect.weight += weight;
                effect.tilt = tilt * effect.tilt;
            }
        }
        model
    }

    /// v_G as this model compensates now (unit, against gravity): [`up`](Self::up) turned by the
    /// tilt a model file or `compensation.auto_update` gave a lattice (an arm's tilts are folded
    /// into its `up`). What a watch reads along.
    pub fn gravity_up(&self) -> Vector3<f64> {
        self.effect.as_ref().map_or(self.up, |e| e.tilt * self.up)
    }

    /// The arm model (arm modes).
    pub fn arm(&self) -> Option<&ArmGravity> {
        self.arm.as_ref()
    }

    /// The model `compensation.mode` asks for: `mode`, or, unset, the model the calibration
    /// chose by its held-out score (`[model] chosen`), else the vector mode when the grid has a
    /// force vector for every vertex (every grid calibration writes has: where the field turns
    /// away from v_G, as on a linkage, the scalar mode leaves its sideways part) and the scalar
    /// mode otherwise.
    pub fn configured(
        file: GridFile,
        mode: Option<CompensationMode>,
        outside: OutsideGrid,
    ) -> Result<Self, ModelError> {
        let has_vectors = file.vertices.force_vectors.len() == file.grid.vertex_count();
        let chosen = file.model.as_ref().and_then(|m| m.chosen.parse().ok());
        let mode = mode.or(chosen).unwrap_or(if has_vectors {
            CompensationMode::Vector
        } else {
            CompensationMode::Scalar
        });
        Self::new(file, mode, outside)
    }

    /// F_G at `x`, N. Outside the lattice `outside` applies to the lattice modes; the arm
    /// modes hold wherever the arm reaches.
    pub fn force(&self, x: &Vector3<f64>) -> Vector3<f64> {
        let lattice = |forces: &[Vector3<f64>]| -> Vector3<f64> {
            let (idx, w) = self.grid.cell_weights(x);
            (0..8).map(|n| forces[idx[n]] * w[n]).sum()
        };
        let grid = match (self.mode, &self.arm) {
            (CompensationMode::Arm, Some(arm)) => arm.force(x),
            (CompensationMode::ArmResidual, Some(arm)) => {
                // The residual fades from its face value to nothing over one spacing outside.
                let outside = self.grid.distance_outside(x);
                let fade = (1.0 - outside / self.grid.spacing).max(0.0);
                let residual = if fade > 0.0 {
                    lattice(&self.forces) * fade
                } else {
                    Vector3::zeros()
                };
                arm.force(x) + residual
            }
            _ if self.outside == OutsideGrid::Zero && !self.grid.contains(x) => {
                return Vector3::zeros();
            }
            (CompensationMode::Vector, _) => lattice(&self.forces),
            _ => self.grid.gravity_force(x),
        };
        match &self.effect {
            Some(effect) => effect.apply(x, grid),
            None => grid,
        }
    }
}

/// An application force offset Z_E with its staleness handling. An offset's age is judged on both
/// clocks a tick carries, device time and host time ([`DeviceState::host_time`]), and the larger
/// wins: a device whose clock stops cannot keep an offset fresh, nor can a host that stalls.
#[derive(Clone, Copy, Debug)]
pub struct ForceOffset {
    target: Vector3<f64>,
    /// Device and host time of the last update, s.
    updated_at: (f64, f64),
    stale_after: f64,
    ramp_time: f64,
}

impl ForceOffset {
    pub fn new(stale_after: f64, ramp_time: f64) -> Self {
        Self {
            target: Vector3::zeros(),
            updated_at: (f64::NEG_INFINITY, f64::NEG_INFINITY),
            stale_after,
            ramp_time,
        }
    }

    /// A fresh offset from the application, applied at the tick `now`.
    pub fn set(&mut self, force: Vector3<f64>, now: &DeviceState) {
        self.target = force;
        self.updated_at = (now.time, now.host_time);
    }

    /// Remove the offset at once (the application went away).
    pub fn clear(&mut self) {
        self.target = Vector3::zeros();
        self.updated_at = (f64::NEG_INFINITY, f64::NEG_INFINITY);
    }

    /// Time since the last update at the tick `now`, s: the larger of the two clocks' readings.
    fn age(&self, now: &DeviceState) -> f64 {
        (now.time - self.updated_at.0).max(now.host_time - self.updated_at.1)
    }

    /// The offset to render at the tick `now`: the latest value while fresh, then a linear ramp to
    /// zero over `ramp_time` (by elapsed time, so missed ticks do not slow it).
    pub fn at(&self, now: &DeviceState) -> Vector3<f64> {
        let stale_for = self.age(now) - self.stale_after;
        if stale_for <= 0.0 {
            self.target
        } else {
            self.target * (1.0 - stale_for / self.ramp_time).max(0.0)
        }
    }
}

/// F = Z_E + F_G(X) (Eq. 15). Without a model it renders the offset alone.
#[derive(Clone, Debug)]
pub struct Compensation {
    pub model: Option<Box<GravityModel>>,
    pub offset: ForceOffset,
}

impl Compensation {
    pub fn new(model: Option<Box<GravityModel>>, offset: ForceOffset) -> Self {
        Self { model, offset }
    }

    /// The gravity force alone at `x`.
    pub fn gravity_force(&self, x: &Vector3<f64>) -> Vector3<f64> {
        self.model.as_ref().map_or(Vector3::zeros(), |m| m.force(x))
    }
}

impl Compensation {
    /// This tick's two parts of the force: the offset Z_E, then the gravity force at the
    /// handle.
    pub fn parts(&mut self, s: &DeviceState) -> (Vector3<f64>, Vector3<f64>) {
        (self.offset.at(s), self.gravity_force(&s.position))
    }
}

impl Controller for Compensation {
    fn tick(&mut self, s: &DeviceState) -> ControlOutput {
        let (z_e, gravity) = self.parts(s);
        ControlOutput::force(z_e + gravity)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 40: a model file's spring made the daemon push at the safety limit with nobody
    /// there. What effects add is bounded by twice the largest force the calibration measured;
    /// within the bound they pass unchanged.
    #[test]
    fn what_a_model_file_adds_is_bounded_by_the_calibrated_forces() {
        let uniform = MassGrid::uniform(
            0.12,
            9.81,
            Vector3::z(),
            Vector3::repeat(-0.04),
            0.04,
            [3, 3, 3],
        );
        let weight = 0.12 * 9.81;
        let model = |record: EffectRecord| {
            let (effect, _) = StaticEffect::from_records(&[record], &Vector3::z(), 9.81);
            GravityModel::configured(GridFile::from(uniform.clone()), None, OutsideGrid::Zero)
                .unwrap()
                .with_effect(effect)
        };
        let x = Vector3::new(0.02, -0.01, 0.03);
        let stiff = model(EffectRecord::Spring {
            stiffness_n_per_m: 10_000.0,
            anchor_m: [-1.0, 0.0, 0.0],
        });
        let added = (stiff.force(&x) - Vector3::z() * weight).norm();
        assert!((added - 2.0 * weight).abs() < 1e-9, "{added} N added");
        let gentle = model(EffectRecord::Payload { mass_kg: 0.03 });
        let added = gentle.force(&x) - Vector3::z() * weight;
        assert!(
            (added - Vector3::z() * 0.03 * 9.81).norm() < 1e-12,
            "{added}"
        );
    }

    fn grid() -> MassGrid {
        let mut g = MassGrid::uniform(
            0.1,
            9.81,
            Vector3::new(0.0, 0.1, 1.0),
            Vector3::new(-0.04, -0.04, -0.04),
            0.04,
            [3, 3, 3],
        );
        for (n, m) in g.masses.iter_mut().enumerate() {
            *m = 0.05 + 0.01 * n as f64;
        }
        g
    }

    #[test]
    fn scalar_mode_is_mass_times_g_along_v_g() {
        let g = grid();
        let model = GravityModel::new(
            GridFile::from(g.clone()),
            CompensationMode::Scalar,
            OutsideGrid::HoldNearest,
        )
        .unwrap();
        let x = Vector3::new(0.01, -0.02, 0.03);
        let f = model.force(&x);
        assert!((f - g.gravity_direction * g.mass_at(&x) * 9.81).norm() < 1e-12);
        assert!((f.normalize() - g.gravity_direction).norm() < 1e-12);
    }

    #[test]
    fn an_unset_mode_is_vector_with_force_vectors_and_scalar_without() {
        let mut file = GridFile::from(grid());
        let bare = GravityModel::configured(file.clone(), None, OutsideGrid::Zero).unwrap();
        assert_eq!(bare.mode, CompensationMode::Scalar);
        file.vertices.force_vectors = vec![[0.0, 0.1, 1.0]; 27];
        let calibrated = GravityModel::configured(file.clone(), None, OutsideGrid::Zero).unwrap();
        assert_eq!(calibrated.mode, CompensationMode::Vector);
        let chosen =
            GravityModel::configured(file, Some(CompensationMode::Scalar), OutsideGrid::Zero);
        assert_eq!(chosen.unwrap().mode, CompensationMode::Scalar);
    }

    #[test]
    fn vector_mode_interpolates_the_measured_forces() {
        let g = grid();
        let mut file = GridFile::from(g.clone());
        file.vertices.force_vectors = (0..27)
            .map(|n| [0.01 * n as f64, 0.0, 1.0 + 0.02 * n as f64])
            .collect();
        let model = GravityModel::new(file, CompensationMode::Vector, OutsideGrid::Zero).unwrap();
        // At a vertex: exactly its vector. The field is affine in n, hence in position.
        let v = g.vertex_position(1, 2, 0);
        let n = g.index(1, 2, 0) as f64;
        assert!((model.force(&v) - Vector3::new(0.01 * n, 0.0, 1.0 + 0.02 * n)).norm() < 1e-12);
        // Outside with the zero policy: nothing.
        assert_eq!(model.force(&Vector3::new(0.0, 0.0, 0.2)), Vector3::zeros());
        // Without force vectors the vector mode is refused.
        assert_eq!(
            GravityModel::new(
                GridFile::from(grid()),
                CompensationMode::Vector,
                OutsideGrid::Zero
            ),
            Err(ModelError::NoForceVectors)
        );
    }

    /// A lattice file with an arm model of a PHANToM-like serial arm, "arm" chosen, and a
    /// vertex force of the arm model's own plus (0.01, 0, 0) N at each vertex.
    fn arm_file() -> GridFile {
        use crate::grid::{ArmRecord, HeldOutRecord, ModelRecord};
        let gravity = crate::arm::tests::phantom_gravity();
        let g = grid();
        let mut file = GridFile::from(g.clone());
        file.vertices.force_vectors = (0..27)
            .map(|n| {
                let (i, j, k) = g.coordinates(n);
                (gravity.force(&g.vertex_position(i, j, k)) + Vector3::x() * 0.01).into()
            })
            .collect();
        file.arm = Some(ArmRecord::new("test", &gravity));
        file.model = Some(ModelRecord {
            chosen: "arm".into(),
            held_out_holds: 7,
            held_out_pct: HeldOutRecord {
                arm: Some(0.5),
                arm_residual: Some(0.6),
                ..HeldOutRecord::default()
            },
            warning: None,
        });
        file
    }

    #[test]
    fn the_arm_model_holds_beyond_the_lattice_and_its_residual_fades_over_one_spacing() {
        let file = arm_file();
        let arm = file.arm.as_ref().unwrap().gravity().unwrap();
        // Unset, the mode is the one the calibration chose, with its held-out score.
        let chosen = GravityModel::configured(file.clone(), None, OutsideGrid::Zero).unwrap();
        assert_eq!(chosen.mode, CompensationMode::Arm);
        assert_eq!(chosen.held_out_pct, Some(0.5));
        // Far outside the lattice (and with the zero policy) the arm model still holds.
        let far = Vector3::new(0.1, 0.05, 0.12);
        assert_eq!(chosen.force(&far), arm.force(&far));
        let residual = GravityModel::new(
            file.clone(),
            CompensationMode::ArmResidual,
            OutsideGrid::Zero,
        )
        .unwrap();
        assert_eq!(residual.held_out_pct, Some(0.6));
        // Inside: the arm plus the 10 mN it left at every vertex; half a spacing outside, half
        // of it; a spacing outside and beyond, none.
        let inside = Vector3::new(0.013, -0.021, 0.007);
        let extra = |x: &Vector3<f64>| residual.force(x) - arm.force(x);
        assert!((extra(&inside) - Vector3::x() * 0.01).norm() < 1e-12);
        assert!((extra(&Vector3::new(0.06, 0.0, 0.0)) - Vector3::x() * 0.005).norm() < 1e-12);
        assert_eq!(extra(&Vector3::new(0.0, 0.0, -0.08)), Vector3::zeros());
        // An arm mode on a grid without an arm model is refused, naming the mode.
        let bare = GravityModel::new(
            GridFile::from(grid()),
            CompensationMode::Arm,
            OutsideGrid::Zero,
        );
        assert_eq!(
            bare,
            Err(ModelError::NoArm {
                mode: CompensationMode::Arm
            })
        );
    }

    /// A tick at device time `t` and host time `host`.
    fn at(t: f64, host: f64) -> DeviceState {
        DeviceState {
            time: t,
            host_time: host,
            position: Vector3::zeros(),
            velocity: Vector3::zeros(),
            status: crate::protocol::Status::default(),
            tick: 0,
        }
    }

    #[test]
    fn stale_offsets_ramp_to_zero_and_clear_is_immediate() {
        let mut o = ForceOffset::new(0.05, 0.05);
        o.set(Vector3::new(1.0, 0.0, 0.0), &at(0.0, 0.0));
        assert_eq!(o.at(&at(0.05, 0.05)).x, 1.0);
        // Ramp: 1 N over 50 ms, 20 mN per ms, whatever ticks were seen in between.
        assert!((o.at(&at(0.06, 0.06)).x - 0.8).abs() < 1e-9);
        assert_eq!(o.at(&at(0.1, 0.1)), Vector3::zeros());
        assert_eq!(o.at(&at(0.2, 0.2)), Vector3::zeros());
        o.set(Vector3::new(0.0, 2.0, 0.0), &at(0.3, 0.3));
        o.clear();
        assert_eq!(o.at(&at(0.3, 0.3)), Vector3::zeros());
    }

    #[test]
    fn a_frozen_device_clock_does_not_keep_an_offset_fresh() {
        let mut o = ForceOffset::new(0.05, 0.05);
        o.set(Vector3::new(1.0, 0.0, 0.0), &at(7.0, 100.0));
        // The device's timestamp stops at 7 s while the host's clock runs on.
        assert_eq!(o.at(&at(7.0, 100.04)).x, 1.0);
        assert!((o.at(&at(7.0, 100.06)).x - 0.8).abs() < 1e-9);
        assert_eq!(o.at(&at(7.0, 100.11)), Vector3::zeros());
        // And a host clock that stalls while the device runs on does not either.
        assert_eq!(o.at(&at(7.11, 100.0)), Vector3::zeros());
    }

    // `hgcd check --apply` (issue 36): a payload and a tilt folded into a grid file's numbers.
    mod applied {
        use super::*;
        use crate::grid::file_tests::calibrated;
        use crate::grid::{AppliedRecord, ArmRecord, Change};
        use nalgebra::Rotation3;

        /// What `hgcd run` compensates with `change` as an effect on `file`'s model.
        fn with_effect(file: &GridFile, mode: CompensationMode, change: &Change) -> GravityModel {
            let model = GravityModel::new(file.clone(), mode, OutsideGrid::HoldNearest).unwrap();
            let effect = StaticEffect {
                tilt: Rotation3::new(change.tilt),
                weight: model.up * (change.payload_kg * file.grid.g),
                spring: None,
                bound: f64::INFINITY,
            };
            model.with_effect_bounded(Some(effect), f64::INFINITY)
        }

        fn record() -> AppliedRecord {
            AppliedRecord {
                at: None,
                hgcd_version: None,
                payload_g: 30.0,
                tilt_deg: 4.7,
                tilt_axis: [0.24, 0.97, 0.0],
                device_time_s: Some(41.0),
            }
        }

        /// Points inside the sample grid (±40 mm) and at its corners.
        fn points() -> Vec<Vector3<f64>> {
            (0..125)
                .map(|n| Vector3::new((n % 5) as f64, ((n / 5) % 5) as f64, (n / 25) as f64))
                .map(|s| (s / 2.0).add_scalar(-1.0) * 0.04)
                .collect()
        }

        const CHANGE: Change = Change {
            payload_kg: 0.03,
            tilt: Vector3::new(0.02, 0.08, 0.0),
        };

        /// Folded into the numbers, a change compensates as the same change added as an effect
        /// (what `hgcd check` fitted it with) in every mode the file serves.
        fn assert_folds_as_the_effect(file: &GridFile, modes: &[CompensationMode]) {
            let changed = file.with_change(&CHANGE, record()).unwrap();
            assert_eq!(changed.applied, vec![record()]);
            let reloaded =
                GridFile::from_toml_str(&changed.to_toml_string(), std::path::Path::new("t"))
                    .unwrap();
            assert_eq!(reloaded.applied, changed.applied);
            for &mode in modes {
                let folded =
                    GravityModel::new(reloaded.clone(), mode, OutsideGrid::HoldNearest).unwrap();
                let effect = with_effect(file, mode, &CHANGE);
                for x in points() {
                    let (a, b) = (folded.force(&x), effect.force(&x));
                    assert!(
                        (a - b).norm() < 1e-6,
                        "{mode:?} at {x:?}: {a:?} against {b:?}"
                    );
                }
            }
        }

        /// A model file's tilt and the one `auto_update` took in after it compose (before, the
        /// later replaced the earlier).
        #[test]
        fn tilts_of_several_records_compose() {
            let tilt = |v: Vector3<f64>| EffectRecord::GravityTilt {
                angle_rad: v.norm(),
                rotation_axis: v.normalize().into(),
            };
            let (first, second) = (Vector3::new(0.03, 0.0, 0.0), Vector3::new(0.0, -0.05, 0.01));
            let (effect, refused) =
                StaticEffect::from_records(&[tilt(first), tilt(second)], &Vector3::z(), 9.81);
            assert!(refused.is_empty());
            let both = Rotation3::new(second) * Rotation3::new(first);
            assert!((effect.unwrap().tilt.matrix() - both.matrix()).norm() < 1e-12);
        }

        /// A change read on top of one taken in (what the in-use watch reads after
        /// `auto_update`) compensates as both taken in at once: tilts composed, payloads added.
        #[test]
        fn a_change_on_top_of_a_change_is_both_at_once() {
            let second = Change {
                payload_kg: -0.012,
                tilt: Vector3::new(-0.05, 0.01, 0.03),
            };
            let both = Change {
                payload_kg: CHANGE.payload_kg + second.payload_kg,
                tilt: (Rotation3::new(second.tilt) * Rotation3::new(CHANGE.tilt)).scaled_axis(),
            };
            for (file, mode) in every_mode() {
                let changed = with_effect(&file, mode, &CHANGE)
                    .changed(&Rotation3::new(second.tilt), second.payload_kg);
                let at_once = with_effect(&file, mode, &both);
                for x in points() {
                    let (a, b) = (changed.force(&x), at_once.force(&x));
                    assert!(
                        (a - b).norm() < 1e-9,
                        "{mode:?} at {x:?}: {a:?} against {b:?}"
                    );
                }
            }
        }

        /// A calibrated grid in each mode it serves: the lattices, and with an arm the arm modes.
        fn every_mode() -> [(GridFile, CompensationMode); 4] {
            let mut arm = calibrated();
            arm.arm = Some(ArmRecord::new(
                "test",
                &crate::arm::tests::phantom_gravity(),
            ));
            [
                (calibrated(), CompensationMode::Scalar),
                (calibrated(), CompensationMode::Vector),
                (arm.clone(), CompensationMode::Arm),
                (arm, CompensationMode::ArmResidual),
            ]
        }

        /// After a tilt taken in, the model's gravity points where the tilt turned it, in
        /// every mode: the watch reads along it.
        #[test]
        fn a_tilt_taken_in_turns_the_models_gravity_direction() {
            let turn = Rotation3::new(Vector3::new(-0.05, 0.01, 0.03));
            for (file, mode) in every_mode() {
                let before = GravityModel::new(file.clone(), mode, OutsideGrid::HoldNearest)
                    .unwrap()
                    .gravity_up();
                let expected = turn * Rotation3::new(CHANGE.tilt) * before;
                let after = with_effect(&file, mode, &CHANGE)
                    .changed(&turn, 0.01)
                    .gravity_up();
                assert!((after - expected).norm() < 1e-12, "{mode:?}: {after:?}");
                assert!((after - before).norm() > 0.05, "{mode:?}: turned");
            }
        }

        #[test]
        fn a_lattice_takes_in_a_payload_and_a_tilt_as_its_compensation_adds_them() {
            let file = calibrated();
            assert_folds_as_the_effect(
                &file,
                &[CompensationMode::Scalar, CompensationMode::Vector],
            );
        }

        #[test]
        fn an_arm_takes_in_the_tilt_as_its_gravity_and_the_payload_at_its_handle() {
            for gravity in [
                crate::arm::tests::phantom_gravity(),
                crate::arm::tests::delta_gravity(),
            ] {
                let mut file = calibrated();
                file.arm = Some(ArmRecord::new("test", &gravity));
                assert_folds_as_the_effect(
                    &file,
                    &[CompensationMode::Arm, CompensationMode::ArmResidual],
                );
            }
        }
    }
}
