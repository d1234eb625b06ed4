//! The measured log (docs/log-format.md): CSV with a header row naming at least
//! `t,x,y,z,fx,fy,fz` (s, m, N), optionally `xr,yr,zr` (m); other columns ignored, `#` lines
//! comments. `# key = value` comments before the header carry what `hgcd record` knows: the
//! device's grid id and the excitation's gains.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use thiserror::Error;

/// The largest position a log may carry, m, and the largest force, N: a device's workspace and
/// its actuators are far inside both. A value beyond is a corrupt row, refused.
pub const MAX_POSITION: f64 = 10.0;
pub const MAX_FORCE: f64 = 1000.0;
/// The excitation gains a log's comments may give: K in (0, 1e5] N/m, D in [0, 1e3] N·s/m.
pub const MAX_STIFFNESS: f64 = 1e5;
pub const MAX_DAMPING: f64 = 1e3;

/// The most rows a log may hold: 1000 s at 1 kHz. Analysing a log takes about 600 bytes a row
/// (620 MB at the limit), 1.3 kB for a grid with an arm (1.3 GB; docs/discrepancy.md); a longer
/// one is refused, not read without bound.
pub const MAX_ROWS: usize = 1_000_000;

/// The shortest log analysed, s: its held-out part must still hold several slow cycles.
pub const MIN_DURATION: f64 = 10.0;
/// Sample rates accepted, Hz.
pub const RATE_RANGE: (f64, f64) = (200.0, 20_000.0);
/// A step longer than this many median steps is a gap: the derivatives assume even sampling.
const GAP_STEPS: f64 = 5.0;

/// Why a log cannot be analysed. Each names the file and, where it can, the line.
#[derive(Debug, Error)]
pub enum LogError {
    #[error("cannot read the log {}", path.display())]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("log {}: no header row (the first line that is not a comment)", path.display())]
    NoHeader { path: PathBuf },
    #[error(
        "log {}: the header has no column `{column}` (needed: t,x,y,z,fx,fy,fz)",
        path.display()
    )]
    MissingColumn { path: PathBuf, column: &'static str },
    #[error("log {}: the header {problem}", path.display())]
    Header { path: PathBuf, problem: String },
    #[error("log {} line {line}: {problem}", path.display())]
    Row {
        path: PathBuf,
        line: usize,
        problem: String,
    },
    #[error(
        "log {} line {line}: more than {MAX_ROWS} rows; analyze reads at most {MAX_ROWS} (1000 s \
         at 1 kHz): cut the log",
        path.display()
    )]
    TooLong { path: PathBuf, line: usize },
    #[error(
        "log {}: {seconds:.1} s of data; analyze needs at least {MIN_DURATION} s (hgcd record \
         writes 40 s by default)",
        path.display()
    )]
    TooShort { path: PathBuf, seconds: f64 },
    #[error(
        "log {}: rows come at {rate:.0} Hz; analyze takes {} to {} Hz",
        path.display(), RATE_RANGE.0, RATE_RANGE.1
    )]
    Rate { path: PathBuf, rate: f64 },
    #[error(
        "log {}: a gap of {:.1} ms after t = {after} s (rows come every {:.2} ms): analyze needs \
         evenly spaced rows",
        path.display(), step * 1e3, period * 1e3
    )]
    Gap {
        path: PathBuf,
        after: f64,
        step: f64,
        period: f64,
    },
    #[error("writing the log {}", path.display())]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// The excitation a log was recorded with, as `hgcd record` writes it in the log's comments: the
/// PD law F = F_G(X) + K (X_r − X) + D (Ẋ_r − Ẋ) its force followed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Excitation {
    /// K, N/m.
    pub stiffness: f64,
    /// D, N·s/m.
    pub damping: f64,
}

/// A measured log, SI units.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Log {
    /// s, strictly increasing.
    pub time: Vec<f64>,
    /// Measured end-effector position, m.
    pub position: Vec<Vector3<f64>>,
    /// Total force commanded at that tick, N.
    pub force: Vec<Vector3<f64>>,
    /// The reference the excitation tracked, m (when the log has `xr,yr,zr`).
    pub reference: Option<Vec<Vector3<f64>>>,
    /// The grid id of the device it was recorded on (`# device = ID`).
    pub device: Option<String>,
    /// The excitation's PD gains (`# stiffness_n_per_m = K`, `# damping_n_s_per_m = D`).
    pub excitation: Option<Excitation>,
}

impl Log {
    pub fn len(&self) -> usize {
        self.time.len()
    }

    pub fn is_empty(&self) -> bool {
        self.time.is_empty()
    }

    /// Duration, s.
    pub fn duration(&self) -> f64 {
        match (self.time.first(), self.time.last()) {
            (Some(a), Some(b)) => b - a,
            _ => 0.0,
        }
    }

    /// Median sample period, s.
    pub fn period(&self) -> f64 {
        let mut steps: Vec<f64> = self.time.windows(2).map(|w| w[1] - w[0]).collect();
        if steps.is_empty() {
            return f64::NAN;
        }
        let mid = steps.len() / 2;
        *steps.select_nth_unstable_by(mid, f64::total_cmp).1
    }

    /// Read and check a log file.
    ///
    /// # Errors
    /// [`LogError`]: unreadable, no header or a needed column missing, a row with a missing,
    /// unparsable or non-finite value, times that repeat or go back, a gap, too short, or a rate
    /// out of range.
    pub fn load(path: &Path) -> Result<Self, LogError> {
        let text = crate::sys::read_text(path).map_err(|source| LogError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&text, path)
    }

    /// [`Log::load`] on `text`, read from `path`.
    pub fn parse(text: &str, path: &Path) -> Result<Self, LogError> {
        let row_error = |line: usize, problem: String| LogError::Row {
            path: path.to_path_buf(),
            line,
            problem,
        };
        let mut log = Log::default();
        let mut gains = (None, None);
        let mut columns: Option<Columns> = None;
        for (index, raw) in text.lines().enumerate() {
            let line = index + 1;
            let trimmed = raw.trim();
            if trimmed.is_empty() {
                continue;
            }
            if let Some(comment) = trimmed.strip_prefix('#') {
                if columns.is_none() {
                    if let Some((key, value)) = comment.split_once('=') {
                        let value = value.trim();
                        let gain = |name: &str, zero: bool, max: f64| -> Result<f64, LogError> {
                            match value.parse::<f64>() {
                                Ok(v) if (v > 0.0 || zero && v == 0.0) && v <= max => Ok(v),
                                _ => Err(row_error(
                                    line,
                                    format!(
                                        "`{name}` is `{value}`: expected a number {} {max}",
                                        if zero { "from 0 to" } else { "above 0, up to" }
                                    ),
                                )),
                            }
                        };
                        match key.trim() {
                            "device" => log.device = Some(value.to_string()),
                            "stiffness_n_per_m" => {
                                gains.0 = Some(gain("stiffness_n_per_m", false, MAX_STIFFNESS)?)
                            }
                            "damping_n_s_per_m" => {
                                gains.1 = Some(gain("damping_n_s_per_m", true, MAX_DAMPING)?)
                            }
                            _ => {}
                        }
                    }
                }
                continue;
            }
            let Some(c) = &columns else {
                let parsed = Columns::find(trimmed, path)?;
                if parsed.reference.is_some() {
                    log.reference = Some(Vec::new());
                }
                columns = Some(parsed);
                continue;
            };
            if log.len() == MAX_ROWS {
                return Err(LogError::TooLong {
                    path: path.to_path_buf(),
                    line,
                });
            }
            let fields: Vec<&str> = trimmed.split(',').map(str::trim).collect();
            let value = |i: usize, name: &str| -> Result<f64, LogError> {
                let text = fields
                    .get(i)
                    .ok_or_else(|| row_error(line, format!("no value for `{name}`")))?;
                let v: f64 = text
                    .parse()
                    .map_err(|_| row_error(line, format!("`{name}` is not a number: `{text}`")))?;
                if !v.is_finite() {
                    return Err(row_error(line, format!("`{name}` is {v}")));
                }
                Ok(v)
            };
            let triple = |at: [usize; 3],
                          names: [&str; 3],
                          limit: f64,
                          unit: &str|
             -> Result<Vector3<f64>, LogError> {
                let v = Vector3::new(
                    value(at[0], names[0])?,
                    value(at[1], names[1])?,
                    value(at[2], names[2])?,
                );
                if let Some(i) = (0..3).find(|&i| v[i].abs() > limit) {
                    return Err(row_error(
                        line,
                        format!(
                            "`{}` is {}: beyond ±{limit} {unit}, no device's (a corrupt row)",
                            names[i],
                            crate::config::Number(v[i])
                        ),
                    ));
                }
                Ok(v)
            };
            let t = value(c.time, "t")?;
            if let Some(&previous) = log.time.last() {
                if t == previous {
                    return Err(row_error(
                        line,
                        format!("time {t} s repeats the row before"),
                    ));
                }
                if t < previous {
                    return Err(row_error(
                        line,
                        format!("time {t} s goes back (the row before is at {previous} s)"),
                    ));
                }
            }
            log.time.push(t);
            log.position
                .push(triple(c.position, ["x", "y", "z"], MAX_POSITION, "m")?);
            log.force
                .push(triple(c.force, ["fx", "fy", "fz"], MAX_FORCE, "N")?);
            if let (Some(at), Some(reference)) = (c.reference, log.reference.as_mut()) {
                reference.push(triple(at, ["xr", "yr", "zr"], MAX_POSITION, "m")?);
            }
        }
        if columns.is_none() {
            return Err(LogError::NoHeader {
                path: path.to_path_buf(),
            });
        }
        if let (Some(stiffness), Some(damping)) = gains {
            log.excitation = Some(Excitation { stiffness, damping });
        }
        log.check(path)?;
        Ok(log)
    }

    /// Long enough, evenly sampled at an accepted rate.
    fn check(&self, path: &Path) -> Result<(), LogError> {
        let seconds = self.duration();
        if seconds < MIN_DURATION {
            return Err(LogError::TooShort {
                path: path.to_path_buf(),
                seconds,
            });
        }
        let period = self.period();
        let rate = 1.0 / period;
        if !(RATE_RANGE.0..=RATE_RANGE.1).contains(&rate) {
            return Err(LogError::Rate {
                path: path.to_path_buf(),
                rate,
            });
        }
        if let Some(k) = self
            .time
            .windows(2)
            .position(|w| w[1] - w[0] > GAP_STEPS * period)
        {
            return Err(LogError::Gap {
                path: path.to_path_buf(),
                after: self.time[k],
                step: self.time[k + 1] - self.time[k],
                period,
            });
        }
        Ok(())
    }

    /// The log as CSV, with the device and excitation as comments.
    pub fn to_csv(&self) -> String {
        let mut out = String::from("# hgcd record log (docs/log-format.md)\n");
        if let Some(device) = &self.device {
            let _ = writeln!(out, "# device = {device}");
        }
        if let Some(e) = &self.excitation {
            let _ = writeln!(out, "# stiffness_n_per_m = {}", e.stiffness);
            let _ = writeln!(out, "# damping_n_s_per_m = {}", e.damping);
        }
        out.push_str("t,x,y,z,fx,fy,fz");
        if self.reference.is_some() {
            out.push_str(",xr,yr,zr");
        }
        out.push('\n');
        for k in 0..self.len() {
            let (x, f) = (self.position[k], self.force[k]);
            let _ = write!(
                out,
                "{:.6},{:.9},{:.9},{:.9},{:.6},{:.6},{:.6}",
                self.time[k], x.x, x.y, x.z, f.x, f.y, f.z
            );
            if let Some(r) = &self.reference {
                let r = r[k];
                let _ = write!(out, ",{:.9},{:.9},{:.9}", r.x, r.y, r.z);
            }
            out.push('\n');
        }
        out
    }

    /// Write the log to `path`, a new file: whole or not at all, and never over a file that is
    /// there (a grid, another log). It is written beside `path` under a temporary name, synced,
    /// then linked to `path`, which fails if `path` exists.
    ///
    /// # Errors
    /// [`LogError::Write`]; its source is of kind `AlreadyExists` when `path` is taken.
    pub fn save(&self, path: &Path) -> Result<(), LogError> {
        let name = path.file_name().unwrap_or_default().to_string_lossy();
        let temporary = path.with_file_name(format!(".{name}.{}.tmp", std::process::id()));
        let written = (|| {
            let mut file = std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(&temporary)?;
            std::io::Write::write_all(&mut file, self.to_csv().as_bytes())?;
            file.sync_all()?;
            std::fs::hard_link(&temporary, path)
        })();
        let _ = std::fs::remove_file(&temporary);
        written.map_err(|source| LogError::Write {
            path: path.to_path_buf(),
            source,
        })
    }
}

/// Where the needed columns are in a header.
struct Columns {
    time: usize,
    position: [usize; 3],
    force: [usize; 3],
    reference: Option<[usize; 3]>,
}

impl Columns {
    fn find(header: &str, path: &Path) -> Result<Self, LogError> {
        let names: Vec<&str> = header.split(',').map(str::trim).collect();
        let header_error = |problem: String| LogError::Header {
            path: path.to_path_buf(),
            problem,
        };
        if let Some((i, name)) = names
            .iter()
            .enumerate()
            .find(|(i, n)| !n.is_empty() && names[..*i].contains(n))
        {
            return Err(header_error(format!(
                "names `{name}` twice (columns {} and {}): which one holds the data?",
                names.iter().position(|n| n == name).unwrap_or(0) + 1,
                i + 1
            )));
        }
        let at = |column: &'static str| names.iter().position(|n| *n == column);
        let need = |column: &'static str| {
            at(column).ok_or_else(|| LogError::MissingColumn {
                path: path.to_path_buf(),
                column,
            })
        };
        let reference = match (at("xr"), at("yr"), at("zr")) {
            (Some(a), Some(b), Some(c)) => Some([a, b, c]),
            (None, None, None) => None,
            _ => {
                return Err(header_error(
                    "has some of `xr,yr,zr` but not all three: give the reference's three \
                     columns or none"
                        .into(),
                ))
            }
        };
        Ok(Self {
            time: need("t")?,
            position: [need("x")?, need("y")?, need("z")?],
            force: [need("fx")?, need("fy")?, need("fz")?],
            reference,
        })
    }
}

#[cfg(test)]
mod fuzz;

#[cfg(test)]
mod tests {
    use super::*;

    fn rows(n: usize, period: f64) -> String {
        let mut s = String::from("# device = sim-point-mass\nt,x,y,z,fx,fy,fz,extra\n");
        for k in 0..n {
            let _ = writeln!(s, "{},{},0,0,0,0,1.2,7", k as f64 * period, k as f64 * 1e-6);
        }
        s
    }

    #[test]
    fn a_log_round_trips_through_csv() {
        let text = rows(12_000, 1e-3);
        let log = Log::parse(&text, Path::new("l.csv")).unwrap();
        assert_eq!(log.len(), 12_000);
        assert_eq!(log.device.as_deref(), Some("sim-point-mass"));
        assert!((log.period() - 1e-3).abs() < 1e-12);
        let again = Log::parse(&log.to_csv(), Path::new("l.csv")).unwrap();
        // Written to the nanometre and the micronewton.
        let close = |a: &[Vector3<f64>], b: &[Vector3<f64>], tolerance: f64| {
            a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).amax() <= tolerance)
        };
        assert!(close(&again.position, &log.position, 1e-9));
        assert!(close(&again.force, &log.force, 1e-6));
        assert_eq!(again.device, log.device);
    }

    /// Saving writes a new file whole, leaves no temporary behind, and replaces nothing: a file
    /// that is at the path (one that appeared during a recording, say) stays as it was.
    #[test]
    fn a_log_is_saved_to_a_new_file_only() {
        let dir = tempfile::tempdir().unwrap();
        let log = Log::parse(&rows(12_000, 1e-3), Path::new("l.csv")).unwrap();
        let path = dir.path().join("log.csv");
        log.save(&path).unwrap();
        assert_eq!(Log::load(&path).unwrap().len(), 12_000);
        std::fs::write(&path, "a grid, say").unwrap();
        let LogError::Write { source, .. } = log.save(&path).unwrap_err() else {
            panic!("a write error")
        };
        assert_eq!(source.kind(), std::io::ErrorKind::AlreadyExists);
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "a grid, say");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn bad_logs_say_what_is_wrong() {
        let p = Path::new("l.csv");
        let says = |text: &str, what: &str| {
            let e = Log::parse(text, p).unwrap_err().to_string();
            assert!(e.contains(what), "{e}");
        };
        says("t,x,y,z,fx,fy\n0,0,0,0,0,0\n", "no column `fz`");
        says("# only comments\n", "no header row");
        says(&rows(3000, 1e-3), "3.0 s of data");
        let mut nan = rows(12_000, 1e-3);
        nan = nan.replacen("1.2,7\n", "NaN,7\n", 1);
        says(&nan, "line 3: `fz` is NaN");
        let mut repeat = rows(12_000, 1e-3);
        repeat = repeat.replacen("0.001,", "0,", 1);
        says(&repeat, "line 4: time 0 s repeats");
        let slow = rows(200, 0.1);
        says(&slow, "rows come at 10 Hz");
        let mut gap = String::from("t,x,y,z,fx,fy,fz\n");
        for k in 0..12_000 {
            let t = k as f64 * 1e-3 + if k >= 500 { 0.019 } else { 0.0 };
            let _ = writeln!(gap, "{t},{},0,0,0,0,1.2", k as f64 * 1e-6);
        }
        says(&gap, "a gap of 20.0 ms after t = 0.499 s");
    }

    /// Issue 40: `hgcd analyze` on 10⁷ rows used 3 GB. A log of more than `MAX_ROWS` rows is
    /// refused with one line at the first row beyond.
    #[test]
    fn a_log_of_more_rows_than_analyze_reads_is_refused() {
        let mut text = String::from(
            "t,x,y,z,fx,fy,fz
",
        );
        for k in 0..=MAX_ROWS {
            let _ = writeln!(text, "{k}e-4,0,0,0,0,0,1");
        }
        let e = Log::parse(&text, Path::new("l.csv"))
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            "log l.csv line 1000002: more than 1000000 rows; analyze reads at most 1000000 \
             (1000 s at 1 kHz): cut the log"
        );
        // One row fewer is read (and is 100 s at 10 kHz).
        text.truncate(text.trim_end().rfind('\n').unwrap() + 1);
        assert_eq!(
            Log::parse(&text, Path::new("l.csv")).unwrap().len(),
            MAX_ROWS
        );
    }
}
