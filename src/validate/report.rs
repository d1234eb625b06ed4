//! The experiment's results: every reading, the statistics per mode, reading and contact point,
//! and the three ways they leave: the terminal table, `penalties.csv` and `summary.json`.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use serde_json::json;

use super::probe::{Reading, Rest};
use super::{Mode, ValidateRequest};
use crate::grid::GridFile;

/// One reading of one repetition.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sample {
    pub mode: Mode,
    /// Index of the contact point (its number is this + 1).
    pub point: usize,
    pub repetition: usize,
    pub reading: Reading,
    /// Where the handle rested (two-sided: the middle of the two rests), m.
    pub position: Vector3<f64>,
    /// ΔX = ‖P_n − X‖, m.
    pub penalty: f64,
    /// Depth below the surface, (P_n − X)·v_G, m.
    pub depth: f64,
    /// Distance across the surface normal, m (what the horizontal hold let through).
    pub lateral: f64,
    /// Two-sided: both readings settled.
    pub settled: bool,
    /// s (two-sided: the two readings' sum).
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

/// One mode's results from one reading.
#[derive(Clone, Debug, PartialEq)]
pub struct Readings {
    /// Mean penalty over every settled repetition at every point, m.
    pub mean: f64,
    /// Standard deviation over all of them, m.
    pub std: f64,
    /// Repetitions that found no steady state, or under the dither whose reading window's
    /// halves disagreed (left out of the statistics).
    pub unsettled: usize,
    /// Per contact point, in point order.
    pub points: Vec<PointStats>,
}

/// One mode's results.
#[derive(Clone, Debug, PartialEq)]
pub struct ModeReport {
    pub mode: Mode,
    /// hgcd's procedure: the middle of the rests from above and from below.
    pub two_sided: Readings,
    /// The rest sinking into the surface from above (without a dither, the paper's procedure).
    pub above: Readings,
    /// The rest the rising surface pushes the handle up to.
    pub below: Readings,
}

impl ModeReport {
    pub fn of(&self, reading: Reading) -> &Readings {
        match reading {
            Reading::Above => &self.above,
            Reading::Below => &self.below,
            Reading::TwoSided => &self.two_sided,
        }
    }
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
    /// The surface's normal, unit "up".
    pub up: Vector3<f64>,
    /// The dither each reading is taken under: amplitude per direction, N (0: none), frequency,
    /// Hz, and duration, s (`validation.dither_*`).
    pub dither: (f64, f64, f64),
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
        normal: &Vector3<f64>,
        dither: (f64, f64, f64),
        rests: &[Rest],
    ) -> Self {
        let normal = *normal;
        let sample = |r: &Rest, reading: Reading, position: Vector3<f64>| {
            let offset = points[r.point] - position;
            let depth = offset.dot(&normal);
            Sample {
                mode: request.modes[r.run],
                point: r.point,
                repetition: r.repetition,
                reading,
                position,
                penalty: offset.norm(),
                depth,
                lateral: (offset - normal * depth).norm(),
                settled: r.settled,
                settle_time: r.settle_time,
            }
        };
        let mut samples = Vec::with_capacity(rests.len() * 3 / 2);
        for (k, r) in rests.iter().enumerate() {
            samples.push(sample(r, r.reading, r.position));
            // A reading from below follows the same repetition's reading from above.
            let above = k.checked_sub(1).map(|j| &rests[j]).filter(|a| {
                a.reading == Reading::Above
                    && (a.run, a.point, a.repetition) == (r.run, r.point, r.repetition)
            });
            if let (Reading::Below, Some(a)) = (r.reading, above) {
                let mut both = sample(r, Reading::TwoSided, (a.position + r.position) / 2.0);
                both.settled = a.settled && r.settled;
                both.settle_time = a.settle_time + r.settle_time;
                samples.push(both);
            }
        }
        let readings = |mode: Mode, reading: Reading| {
            let of = |p: Option<usize>| {
                samples
                    .iter()
                    .filter(|s| {
                        s.mode == mode
                            && s.reading == reading
                            && s.settled
                            && p.is_none_or(|p| s.point == p)
                    })
                    .map(|s| s.penalty)
                    .collect::<Vec<f64>>()
            };
            let (mean, std) = mean_std(&of(None));
            let points = (0..points.len())
                .map(|p| {
                    let values = of(Some(p));
                    let (mean, std) = mean_std(&values);
                    PointStats {
                        mean,
                        std,
                        count: values.len(),
                    }
                })
                .collect();
            Readings {
                mean,
                std,
                unsettled: samples
                    .iter()
                    .filter(|s| s.mode == mode && s.reading == reading && !s.settled)
                    .count(),
                points,
            }
        };
        let modes = request
            .modes
            .iter()
            .map(|&mode| ModeReport {
                mode,
                two_sided: readings(mode, Reading::TwoSided),
                above: readings(mode, Reading::Above),
                below: readings(mode, Reading::Below),
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
            up: normal,
            dither,
            modes,
            samples,
        }
    }

    /// The table `hgcd validate` prints.
    pub fn table(&self) -> String {
        let (amplitude, frequency, time) = self.dither;
        let dither = if amplitude > 0.0 {
            format!(
                "each rest the mean position under a dither of {amplitude} N at {frequency} Hz \
                 ({time} s; the paper has none: validation.dither_n = 0)\n"
            )
        } else {
            String::new()
        };
        let mut out = format!(
            "penalty ΔX = ‖P_n − X‖ at rest, mm: mean ± standard deviation over {} \
             repetitions\nX: the middle of the rests from above and from below (the paper read \
             from above only)\n{dither}(probe {:.0} g, surface {} N/mm; ideal m_p g / k = {:.3} \
             mm)\n",
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
                let s = m.two_sided.points[n];
                let cell = format!("{:.3} ± {:.3}", mm(s.mean), mm(s.std));
                let _ = write!(out, "  {cell:<18}");
            }
            out.push('\n');
        }
        // From above without a dither is the paper's own reading.
        let above = if amplitude > 0.0 {
            "mean from above       "
        } else {
            "mean from above, paper"
        };
        for (reading, label) in [
            (Reading::TwoSided, "mean                  "),
            (Reading::Above, above),
            (Reading::Below, "mean from below       "),
        ] {
            let _ = write!(out, "  {label}");
            for m in &self.modes {
                let r = m.of(reading);
                let error = (r.mean / self.ideal - 1.0) * 1e2;
                let cell = format!("{:.3} ({error:+.1} %)", mm(r.mean));
                let _ = write!(out, "  {cell:<18}");
            }
            out.push('\n');
        }
        for m in &self.modes {
            for reading in [Reading::Above, Reading::Below] {
                let unsettled = m.of(reading).unsettled;
                if unsettled > 0 {
                    let _ = writeln!(
                        out,
                        "  {}: {unsettled} reading(s) from {} found no steady state (under the \
                         dither: its reading window's halves disagreed); their repetitions are \
                         left out (see the CSV)",
                        m.mode.name(),
                        reading.name()
                    );
                }
            }
        }
        // Cells are padded to line up; lines end without the padding.
        out.lines().map(|l| format!("{}\n", l.trim_end())).collect()
    }

    /// Every reading, one line each (`penalties.csv`).
    pub fn csv(&self) -> String {
        let mut out = String::from(
            "mode,point,x_mm,y_mm,z_mm,repetition,reading,penalty_mm,depth_mm,lateral_mm,settled,\
             settle_ms\n",
        );
        for s in &self.samples {
            let p = self.points[s.point] * 1e3;
            let _ = writeln!(
                out,
                "{},{},{},{},{},{},{},{:.5},{:.5},{:.5},{},{:.0}",
                s.mode.name(),
                s.point + 1,
                p.x,
                p.y,
                p.z,
                s.repetition + 1,
                s.reading.name(),
                mm(s.penalty),
                mm(s.depth),
                mm(s.lateral),
                s.settled,
                s.settle_time * 1e3
            );
        }
        out
    }

    /// One mode's statistics from one reading, as `summary.json` gives them.
    fn readings_json(&self, r: &Readings) -> serde_json::Value {
        let points: Vec<serde_json::Value> = r
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
        json!({
            "mean_mm": mm(r.mean),
            "std_mm": mm(r.std),
            "error_percent": (r.mean / self.ideal - 1.0) * 1e2,
            "unsettled": r.unsettled,
            "points": points,
        })
    }

    /// `summary.json` (docs/validation.md §4 lists the keys).
    pub fn summary_json(&self, wall_time: f64) -> String {
        let modes: serde_json::Map<String, serde_json::Value> = self
            .modes
            .iter()
            .map(|m| {
                let mut value = self.readings_json(&m.two_sided);
                value["from_above"] = self.readings_json(&m.above);
                value["from_below"] = self.readings_json(&m.below);
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
            "up_direction": [self.up.x, self.up.y, self.up.z],
            "dither_n": self.dither.0,
            "dither_hz": self.dither.1,
            "dither_s": self.dither.2,
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
