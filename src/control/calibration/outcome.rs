//! What a calibration ends with: a [`CalibrationResult`] or a [`CalibrationFailure`]. The
//! lattice's share of the result (v_G, the forces carried to the vertices, the vertices not
//! reached filled in) is worked out by [`crate::fit::lattice`].

use nalgebra::Vector3;

use super::plan::Vertex;

/// What was measured at one vertex (or, for one the handle could not reach, filled in).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VertexResult {
    pub vertex: Vertex,
    /// Apparent mass M̂(X_i) = F·v_G / g, kg: negative where the force points along −v_G.
    pub mass: f64,
    /// Holding force: the middle of the stick band, N (what the vector mode interpolates),
    /// carried from `measured_at` to the vertex once the grid is complete.
    pub force: Vector3<f64>,
    /// The holding force where it was measured, at `measured_at`, N: the hold itself, which
    /// the arm model is fitted to (zero for a vertex not reached).
    pub held_force: Vector3<f64>,
    /// The force at the first rest near the vertex, N: the one-sided measurement the paper's
    /// procedure makes, anywhere inside the stick band (reported beside `force`).
    pub one_sided_force: Vector3<f64>,
    /// Half-width of the stick band along x, y and z: the friction there, N.
    pub friction: Vector3<f64>,
    /// Updates of the force estimate (settles off the vertex and rounds of band measurements).
    pub iterations: u32,
    /// Distance from the vertex of the rest the band was measured at, m.
    pub final_error: f64,
    /// Where `force` was measured, m: the second rest near the vertex without friction, the mean
    /// of the rests the bands were crossed from with it, or, measured by strokes, where their
    /// windows had the handle on average. The result carries `force` from there to the vertex
    /// (`fit::lattice::carry_to_vertices`).
    pub measured_at: Vector3<f64>,
    /// Device time spent on this vertex, move included, s.
    pub duration: f64,
    /// False for a vertex the handle could not reach: its values are filled from neighbours.
    pub reached: bool,
    /// For a vertex not reached: why, if it was not a stop (the handle did not converge there,
    /// twice); None for a stop, and for a vertex reached.
    pub failure: Option<CalibrationFailure>,
}

impl VertexResult {
    /// A vertex not reached (nothing measured there yet): its values to be filled from its
    /// neighbours.
    pub fn not_reached(vertex: Vertex) -> Self {
        Self {
            vertex,
            mass: 0.0,
            force: Vector3::zeros(),
            held_force: Vector3::zeros(),
            one_sided_force: Vector3::zeros(),
            friction: Vector3::zeros(),
            iterations: 0,
            final_error: 0.0,
            measured_at: vertex.position,
            duration: 0.0,
            reached: false,
            failure: None,
        }
    }
}

/// What the initialisation measured at the rest point X_C.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InitialMeasurement {
    /// Holding force at X_C (the middle of the stick bands), N; where the survey strokes found
    /// the bands misread, the holding force the strokes measured.
    pub load: Vector3<f64>,
    /// Half-widths of the stick bands along x, y, z, N; where the bands were misread, the
    /// sliding friction the survey strokes measured along each axis.
    pub friction: Vector3<f64>,
    /// The sliding friction along x, y, z that the survey strokes measured (half the difference
    /// of their passes), N; none where they did not carry the handle through.
    pub sliding_friction: Option<Vector3<f64>>,
    /// Moving mass along x, y, z, kg: timed by the pulses, scaled by the share of their excess
    /// they pushed with once the survey strokes have measured the load and sliding friction.
    pub inertia: Vector3<f64>,
    /// Standard deviation of the reported position at rest, m.
    pub noise: f64,
    /// The largest step between consecutive readings at rest: the encoder's step, or a few
    /// standard deviations of noise without one, m.
    pub step: f64,
    /// Hold stiffness built from these, N/m per axis.
    pub stiffness: Vector3<f64>,
}

/// A finished calibration.
#[derive(Clone, Debug, PartialEq)]
pub struct CalibrationResult {
    /// Unit v_G: the principal direction of the measured holding forces, signed so that the
    /// masses are positive on average.
    pub gravity_direction: Vector3<f64>,
    /// |load| / g at X_C, kg: a rough mass.
    pub initial_mass: f64,
    /// Rest point X_C of the initialisation, m.
    pub rest_point: Vector3<f64>,
    pub initial: InitialMeasurement,
    /// Results in grid order (x fastest).
    pub vertices: Vec<VertexResult>,
    pub origin: Vector3<f64>,
    pub dims: [usize; 3],
    pub left_out: Vec<Vertex>,
    /// Vertices the handle could not reach (their values are filled, `docs/grid-format.md` §4).
    pub unreachable: Vec<Vertex>,
    /// Vertices of an explored grid outside the explored workspace: never visited, their values
    /// extrapolated from the calibrated ones (`docs/grid-format.md` §4).
    pub extrapolated: Vec<Vertex>,
    /// What exploration found (`calibration.workspace = "explore"`).
    pub workspace: Option<super::explore::WorkspaceMap>,
    /// Device time of the whole run, s.
    pub duration: f64,
    /// Where that time went.
    pub time_spent: TimeSpent,
}

/// Device time a calibration spent in each kind of step, s (they add up to its duration).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TimeSpent {
    /// At X_C: catching the handle, its stick bands, moving mass and survey strokes.
    pub initialisation: f64,
    /// Probing the reachable workspace (`calibration.workspace = "explore"`).
    pub exploration: f64,
    /// Moving from vertex to vertex.
    pub moves: f64,
    /// At vertices: settling, rests, updates and pushes toward the vertex.
    pub rests: f64,
    /// At vertices: the stick bands' rounds and the check after them.
    pub bands: f64,
    /// At vertices: the strokes.
    pub strokes: f64,
}

impl TimeSpent {
    pub fn total(&self) -> f64 {
        self.initialisation + self.exploration + self.moves + self.rests + self.bands + self.strokes
    }
}

/// `initialisation 14.0 s, moves 11.1 s, …`: the kinds of step that took any time.
impl std::fmt::Display for TimeSpent {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "initialisation {:.1} s", self.initialisation)?;
        for (what, seconds) in [
            ("exploration", self.exploration),
            ("moves", self.moves),
            ("rests", self.rests),
            ("bands", self.bands),
            ("strokes", self.strokes),
        ] {
            if seconds > 0.0 {
                write!(f, ", {what} {seconds:.1} s")?;
            }
        }
        Ok(())
    }
}

/// What became of a vertex that was not measured, for people: `at` is a stop `distance` m away
/// (`failure` None) or a hold that did not converge there (twice when `retried`); its values
/// will be filled.
pub fn unreachable_note(
    at: &Vertex,
    distance: f64,
    failure: Option<&CalibrationFailure>,
    retried: bool,
) -> String {
    let twice = if retried { ", twice" } else { "" };
    let why = match failure {
        None => format!(
            "is unreachable: the handle stays {:.1} mm away and does not yield to a push{twice}",
            distance * 1e3
        ),
        Some(failure) => format!("could not be measured{twice}: {failure}"),
    };
    format!("{at} {why}; its values will be filled from its neighbours")
}

/// Why a calibration failed.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum CalibrationFailure {
    #[error(
        "initialisation found no steady state within {timeout:.0} s (is the handle free to move \
         and held by nothing but the field?)"
    )]
    InitTimeout { timeout: f64 },
    #[error(
        "the handle rests at ({:.1}, {:.1}, {:.1}) mm, {:.0} mm outside the workspace the device \
         declares, ({:.1}, {:.1}, {:.1}) to ({:.1}, {:.1}, {:.1}) mm: nothing was pushed (bring the \
         handle into it, or correct device.workspace_*_mm or the device's device-info report)",
        position.x * 1e3 + 0.0, position.y * 1e3 + 0.0, position.z * 1e3 + 0.0, outside * 1e3,
        lo.x * 1e3, lo.y * 1e3, lo.z * 1e3, hi.x * 1e3, hi.y * 1e3, hi.z * 1e3
    )]
    OutsideWorkspace {
        /// Where the handle rested, m.
        position: Vector3<f64>,
        /// The declared box, m.
        lo: Vector3<f64>,
        hi: Vector3<f64>,
        /// How far beyond the box and its slack the handle is, m.
        outside: f64,
    },
    #[error(
        "initialisation: the handle did not move under {push_n:.2} N along {axis}; something holds \
         it (a hand, a cable, a support), or its friction is beyond what calibration pushes \
         (a share of safety.max_force_n: docs/calibration.md §9.2)"
    )]
    Held { axis: char, push_n: f64 },
    #[error(
        "{vertex} did not converge within {timeout:.0} s ({iterations} updates); the handle may \
         be blocked by a stop, the vertex may lie outside the reachable workspace, or \
         calibration.eps_m_mm may be below the position noise"
    )]
    VertexTimeout {
        vertex: Vertex,
        timeout: f64,
        iterations: u32,
    },
    #[error("{vertex} did not converge after {iterations} updates")]
    TooManyIterations { vertex: Vertex, iterations: u32 },
    #[error(
        "{vertex}: the hold kept the handle {offset_mm:.1} mm off it, further than friction can \
         (a stop within a few millimetres of it, or a load the stick bands misread)"
    )]
    HeldOff { vertex: Vertex, offset_mm: f64 },
    #[error(
        "{missed} of the {of} vertices could not be measured (at least half must be, to fill \
         in the others); the warnings above say where (mechanical stops or obstacles? check \
         device.workspace_*_mm and calibration.centre_mm)"
    )]
    TooFewVertices { missed: usize, of: usize },
    #[error(
        "the explored workspace spans {needed} vertices along {axis} at calibration.spacing_mm; \
         at most {} fit (raise calibration.spacing_mm)",
        super::plan::MAX_EXPLORED_SIDE
    )]
    ExploredTooLarge { axis: char, needed: usize },
    #[error(
        "exploration found no vertex {margin_mm:.0} mm inside the reachable workspace (the \
         handle met stops close to X_C along every direction: is it free to move?)"
    )]
    NothingExplored { margin_mm: f64 },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missed_vertex_is_said_to_be_tried_twice_only_when_it_was() {
        let at = Vertex {
            index: [1, -1, -1],
            position: Vector3::new(0.04, -0.04, -0.04),
        };
        let timeout = CalibrationFailure::VertexTimeout {
            vertex: at,
            timeout: 10.0,
            iterations: 5,
        };
        let stop = unreachable_note(&at, 0.01, None, true);
        assert_eq!(
            stop,
            "vertex (1, -1, -1) at (40.0, -40.0, -40.0) mm is unreachable: the handle stays \
             10.0 mm away and does not yield to a push, twice; its values will be filled from \
             its neighbours"
        );
        assert!(!unreachable_note(&at, 0.01, None, false).contains("twice"));
        let unread = unreachable_note(&at, 0.01, Some(&timeout), true);
        assert!(
            unread.contains("could not be measured, twice: vertex (1, -1, -1)"),
            "{unread}"
        );
        let explored = unreachable_note(&at, 0.01, Some(&timeout), false);
        assert!(
            explored.contains("could not be measured: vertex"),
            "{explored}"
        );
    }
}
