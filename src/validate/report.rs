//! The experiment's results: every repetition, the statistics per mode and contact point, and the
//! three ways they leave: the terminal table, `penalties.csv` and `summary.json`.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use serde_json::json;

use super::probe::Rest;
use super::{Mode, ValidateRequest};
use crate::grid::GridFile;

/// One repetition.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    pub mode: Mode,
    /// Index of the contact point (its number is this + 1).
    pub point: usize,
    pub repetition: usize,
    /// Where the handle rested, m.
    pub position: Vector3<f64>,
    /// ΔX = ‖P_n − X‖, m.
    pub penalty: f64,
    /// Depth below the surface, (P_n − X)·v_G, m.
    pub depth: f64,
    /// Distance across the surface normal, m (what the horizontal hold let through).
    pub lateral: f64,
    pub settled: bool,
    /// s.
    pub settle_time: f64,
}

/// Mean and sample standard deviation of the settled repetitions at one contact point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PointStats {
    /// m (NaN when no repetition settled).
    pub mean: f64,
    /// m.
    pub std: f64,
    /// Settled repetitions.
    pub count: usize,
}

/// One mode's results.
#[derive(Clone, Debug, PartialEq)]
pub struct ModeReport {
    pub mode: Mode,
    /// Mean penalty over every settled repetition at every point, m.
    pub mean: f64,
    /// Standard deviation over all of them, m.
    pub std: f64,
    /// Repetitions that found no steady state (left out of the statistics).
    pub unsettled: usize,
    /// Per contact point, in point order.
    pub points: Vec<PointStats>,
}

/// Everything a validation measured.
#[derive(Clone, Debug, PartialEq)]
pub struct Report {
    pub device: String,
    pub grid: PathBuf,
    /// kg.
    pub probe_mass: f64,
    /// N/m.
    pub stiffness: f64,
    /// m/s² (the grid's).
    pub g: f64,
    pub repetitions: usize,
    /// m_p g / k, m.
    pub ideal: f64,
    /// The contact points, m, in point order.
    pub points: Vec<Vector3<f64>>,
    /// In run order.
    pub modes: Vec<ModeReport>,
    pub samples: Vec<Sample>,
}

/// Mean and sample standard deviation (0 for one value, NaN for none).
fn mean_std(values: &[f64]) -> (f64, f64) {
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    if values.len() < 2 {
        return (mean, if values.is_empty() { f64::NAN } else { 0.0 });
    }
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (mean, var.sqrt())
}

/// Millimetres, for the files.
fn mm(v: f64) -> f64 {
    v * 1e3
}

impl Report {
    pub(super) fn new(
        request: &ValidateRequest,
        file: &GridFile,
        grid: &Path,
        points: &[Vector3<f64>],
        rests: &[Rest],
    ) -> Self {
        let normal = file.grid.gravity_direction;
        let samples: Vec<Sample> = rests
            .iter()
            .map(|r| {
                let offset = points[r.point] - r.position;
                let depth = offset.dot(&normal);
                Sample {
                    mode: request.modes[r.run],
                    point: r.point,
                    repetition: r.repetition,
                    position: r.position,
                    penalty: offset.norm(),
                    depth,
                    lateral: (offset - normal * depth).norm(),
                    settled: r.settled,
                    settle_time: r.settle_time,
                }
            })
            .collect();
        let modes = request
            .modes
            .iter()
            .map(|&mode| {
                let of_mode = |p: Option<usize>| {
                    samples
                        .iter()
                        .filter(|s| s.mode == mode && s.settled && p.is_none_or(|p| s.point == p))
                        .map(|s| s.penalty)
                        .collect::<Vec<f64>>()
                };
                let (mean, std) = mean_std(&of_mode(None));
                let points = (0..points.len())
                    .map(|p| {
                        let values = of_mode(Some(p));
                        let (mean, std) = mean_std(&values);
                        PointStats {
                            mean,
                            std,
                            count: values.len(),
                        }
                    })
                    .collect();
                ModeReport {
                    mode,
                    mean,
                    std,
                    unsettled: samples
                        .iter()
                        .filter(|s| s.mode == mode && !s.settled)
                        .count(),
                    points,
                }
            })
            .collect();
        Self {
            device: request.device.to_string(),
            grid: grid.to_path_buf(),
            probe_mass: request.probe_mass,
            stiffness: request.stiffness,
            g: file.grid.g,
            repetitions: request.repetitions,
            ideal: request.probe_mass * file.grid.g / request.stiffness,
            points: points.to_vec(),
            modes,
            samples,
        }
    }

    /// The table `hgcd validate` prints.
    pub fn table(&self) -> String {
        let mut out = format!(
            "penalty ΔX = ‖P_n − X‖ at steady state, mm: mean ± standard deviation over {} \
             repetitions\n(probe {:.0} g, surface {} N/mm; ideal m_p g / k = {:.3} mm)\n",
            self.repetitions,
            self.probe_mass * 1e3,
            self.stiffness * 1e-3,
            mm(self.ideal)
        );
        let _ = write!(out, "   n  P_n mm            ");
        for m in &self.modes {
            let _ = write!(out, "  {:<18}", m.mode.name());
        }
        out.push('\n');
        for (n, p) in self.points.iter().enumerate() {
            let p = p * 1e3;
            let _ = write!(
                out,
                "  {:>2}  ({:>4.0}, {:>4.0}, {:>4.0})",
                n + 1,
                p.x,
                p.y,
                p.z
            );
            for m in &self.modes {
                let s = m.points[n];
                let cell = format!("{:.3} ± {:.3}", mm(s.mean), mm(s.std));
                let _ = write!(out, "  {cell:<18}");
            }
            out.push('\n');
        }
        let _ = write!(out, "  mean                  ");
        for m in &self.modes {
            let error = (m.mean / self.ideal - 1.0) * 1e2;
            let cell = format!("{:.3} ({error:+.1} %)", mm(m.mean));
            let _ = write!(out, "  {cell:<18}");
        }
        out.push('\n');
        for m in self.modes.iter().filter(|m| m.unsettled > 0) {
            let _ = writeln!(
                out,
                "  {}: {} repetition(s) found no steady state and are left out (see the CSV)",
                m.mode.name(),
                m.unsettled
            );
        }
        // Cells are padded to line up; lines end without the padding.
        out.lines().map(|l| format!("{}\n", l.trim_end())).collect()
    }

    /// Every repetition, one line each (`penalties.csv`).
    pub fn csv(&self) -> String {
        let mut out = String::from(
            "mode,point,x_mm,y_mm,z_mm,repetition,penalty_mm,depth_mm,lateral_mm,settled,settle_ms\n",
        );
        for s in &self.samples {
            let p = self.points[s.point] * 1e3;
            let _ = writeln!(
                out,
                "{},{},{},{},{},{},{:.5},{:.5},{:.5},{},{:.0}",
                s.mode.name(),
                s.point + 1,
                p.x,
                p.y,
                p.z,
                s.repetition + 1,
                mm(s.penalty),
                mm(s.depth),
                mm(s.lateral),
                s.settled,
                s.settle_time * 1e3
            );
        }
        out
    }

    /// `summary.json` (docs/validation.md §4 lists the keys).
    pub fn summary_json(&self, wall_time: f64) -> String {
        let modes: serde_json::Map<String, serde_json::Value> = self
            .modes
            .iter()
            .map(|m| {
                let points: Vec<serde_json::Value> = m
                    .points
                    .iter()
                    .enumerate()
                    .map(|(n, s)| {
                        let p = self.points[n] * 1e3;
                        json!({
                            "number": n + 1,
                            "position_mm": [p.x, p.y, p.z],
                            "mean_mm": mm(s.mean),
                            "std_mm": mm(s.std),
                            "repetitions": s.count,
                        })
                    })
                    .collect();
                let value = json!({
                    "mean_mm": mm(m.mean),
                    "std_mm": mm(m.std),
                    "error_percent": (m.mean / self.ideal - 1.0) * 1e2,
                    "unsettled": m.unsettled,
                    "points": points,
                });
                (m.mode.name().to_string(), value)
            })
            .collect();
        let summary = json!({
            "device": self.device,
            "grid": self.grid.display().to_string(),
            "probe_mass_g": self.probe_mass * 1e3,
            "stiffness_n_per_mm": self.stiffness * 1e-3,
            "g": self.g,
            "repetitions": self.repetitions,
            "ideal_mm": mm(self.ideal),
            "modes": modes,
            "wall_time_s": wall_time,
        });
        let mut text = serde_json::to_string_pretty(&summary).expect("JSON values serialise");
        text.push('\n');
        text
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sample_standard_deviation() {
        let (m, s) = mean_std(&[1.0, 2.0, 3.0]);
        assert_eq!((m, s), (2.0, 1.0));
        assert_eq!(mean_std(&[4.0]), (4.0, 0.0));
        assert!(mean_std(&[]).1.is_nan());
    }
}
