//! Fuzzing the log parser with proptest: arbitrary text, CSV-like token soup, mutated valid logs
//! (numbers, comments, headers, line structure) and logs of any columns, rate and values never
//! panic; each either loads as a log that keeps every rule of `docs/log-format.md` or is refused
//! with a `LogError` of one line.
//!
//! The default case count keeps `cargo test` fast; for a long run:
//! `PROPTEST_CASES=100000 cargo test --release --lib discrepancy::log::fuzz`.

use std::fmt::Write as _;
use std::path::Path;

use proptest::prelude::*;

use super::{
    Log, LogError, GAP_STEPS, MAX_DAMPING, MAX_FORCE, MAX_POSITION, MAX_STIFFNESS, MIN_DURATION,
    RATE_RANGE,
};
use crate::protocol::fuzz::{self, mutated, mutation, near, number, text_properties};

/// The columns of a recorded log, in the order `hgcd record` writes them.
const COLUMNS: [&str; 10] = ["t", "x", "y", "z", "fx", "fy", "fz", "xr", "yr", "zr"];

/// Column names a generated header draws from: the known ones, one twice, an unknown, none.
const NAMES: [&str; 13] = [
    "t", "x", "y", "z", "fx", "fy", "fz", "xr", "yr", "zr", "t", "q", "",
];

/// Rows of a valid log: 10.5 s at 200 Hz, the fewest a log may hold (about 90 kB).
const ROWS: usize = 2101;
const PERIOD: f64 = 5e-3;

/// Pieces of CSV and of logs, the kind of thing a mutation should insert.
fn token() -> BoxedStrategy<String> {
    prop_oneof![
        Just(",".to_string()),
        Just("\n".to_string()),
        Just("\r\n".to_string()),
        Just("#".to_string()),
        Just(" ".to_string()),
        Just("nan".to_string()),
        Just("-inf".to_string()),
        Just("1e308".to_string()),
        Just("-0".to_string()),
        Just("0x10".to_string()),
        Just("1_000".to_string()),
        Just("# device = other\n".to_string()),
        Just("# stiffness_n_per_m = 0\n".to_string()),
        Just("# damping_n_s_per_m = 1e3\n".to_string()),
        Just("t,x,y,z,fx,fy,fz\n".to_string()),
        prop::sample::select(COLUMNS.to_vec()).prop_map(str::to_string),
        number().boxed(),
        ".{0,8}".boxed(),
    ]
    .boxed()
}

/// Row `k` of a log with `columns`: a slow motion inside a few centimetres, forces about 1 N,
/// time `k` periods; a column of another name holds a 7.
fn row(k: usize, period: f64, columns: &[&str]) -> String {
    let t = k as f64 * period;
    let values: Vec<String> = columns
        .iter()
        .map(|c| match *c {
            "t" => format!("{t}"),
            "x" | "xr" => format!("{:.6}", 0.02 * (0.5 * t).sin()),
            "y" | "yr" => format!("{:.6}", 0.02 * (0.7 * t).cos()),
            "z" | "zr" => format!("{:.6}", 0.01 * (0.3 * t).sin()),
            "fx" | "fy" => format!("{:.4}", 0.1 * (2.0 * t).sin()),
            "fz" => format!("{:.4}", 1.2 + 0.1 * t.cos()),
            _ => "7".to_string(),
        })
        .collect();
    values.join(",") + "\n"
}

/// The comments `hgcd record` writes and a header of `columns`.
fn head(columns: &[&str]) -> String {
    format!(
        "# hgcd record log\n# device = sim-point-mass\n# stiffness_n_per_m = 200\n\
         # damping_n_s_per_m = 9\n{}\n",
        columns.join(",")
    )
}

fn body(rows: usize, period: f64, columns: &[&str]) -> String {
    let mut text = String::new();
    for k in 0..rows {
        text.push_str(&row(k, period, columns));
    }
    text
}

fn valid_text() -> String {
    head(&COLUMNS) + &body(ROWS, PERIOD, &COLUMNS)
}

/// What every outcome of the parser must satisfy.
fn loads_soundly_or_is_refused_in_one_line(text: &str) -> Result<(), TestCaseError> {
    let log = match Log::parse(text, Path::new("log.csv")) {
        Err(e) => {
            let message = e.to_string();
            prop_assert!(!message.contains('\n'), "{message:?}");
            let read_or_write = matches!(e, LogError::Read { .. } | LogError::Write { .. });
            prop_assert!(!read_or_write, "{message}");
            return Ok(());
        }
        Ok(log) => log,
    };
    let n = log.len();
    prop_assert!(log.time.iter().all(|t| t.is_finite()));
    prop_assert!(log.time.windows(2).all(|w| w[0] < w[1]));
    prop_assert_eq!(log.position.len(), n);
    prop_assert_eq!(log.force.len(), n);
    let within = |v: &[nalgebra::Vector3<f64>], limit: f64| {
        v.iter().all(|x| x.iter().all(|c| c.abs() <= limit))
    };
    prop_assert!(within(&log.position, MAX_POSITION));
    prop_assert!(within(&log.force, MAX_FORCE));
    if let Some(r) = &log.reference {
        prop_assert_eq!(r.len(), n);
        prop_assert!(within(r, MAX_POSITION));
    }
    if let Some(e) = &log.excitation {
        prop_assert!(e.stiffness > 0.0 && e.stiffness <= MAX_STIFFNESS);
        prop_assert!((0.0..=MAX_DAMPING).contains(&e.damping));
    }
    prop_assert!(log.device.as_ref().is_none_or(|d| !d.contains('\n')));
    prop_assert!(log.duration() >= MIN_DURATION);
    let period = log.period();
    prop_assert!((RATE_RANGE.0..=RATE_RANGE.1).contains(&(1.0 / period)));
    prop_assert!(log
        .time
        .windows(2)
        .all(|w| w[1] - w[0] <= GAP_STEPS * period));
    Ok(())
}

text_properties!(
    fuzz::cases(256),
    loads_soundly_or_is_refused_in_one_line,
    token,
    Just(valid_text())
);

proptest! {
    #![proptest_config(fuzz::cases(256))]

    /// The comments and the header mutated, the rows as they were.
    #[test]
    fn mutated_headers_never_panic(mutations in proptest::collection::vec(mutation(token()), 1..6)) {
        let text = mutated(head(&COLUMNS), &mutations) + &body(ROWS, PERIOD, &COLUMNS);
        loads_soundly_or_is_refused_in_one_line(&text)?;
    }

    /// Columns in any order, some missing, some named twice, some unknown; any rate and length;
    /// a few rows replaced by anything.
    #[test]
    fn logs_of_any_columns_rate_and_values_never_panic(
        columns in prop_oneof![
            Just(COLUMNS.to_vec()).prop_shuffle(),
            proptest::collection::vec(prop::sample::select(NAMES.to_vec()), 0..12),
        ],
        period in near(4.5e-3..5.2e-3),
        rows in prop_oneof![1 => 0..50usize, 4 => 1900..2600usize],
        replaced in proptest::collection::vec((any::<prop::sample::Index>(), ".{0,30}"), 0..3),
    ) {
        let mut lines: Vec<String> = (0..rows).map(|k| row(k, period, &columns)).collect();
        for (at, text) in replaced {
            if !lines.is_empty() {
                let i = at.index(lines.len());
                lines[i] = text + "\n";
            }
        }
        let mut text = head(&columns);
        let _ = write!(text, "{}", lines.concat());
        loads_soundly_or_is_refused_in_one_line(&text)?;
    }
}

#[test]
fn the_valid_logs_the_mutations_start_from_load() {
    let log = Log::parse(&valid_text(), Path::new("log.csv")).unwrap();
    assert_eq!(log.len(), ROWS);
    assert!(log.reference.is_some() && log.excitation.is_some());
    let mut shuffled = COLUMNS;
    shuffled.reverse();
    let text = head(&shuffled) + &body(ROWS, PERIOD, &shuffled);
    assert_eq!(Log::parse(&text, Path::new("log.csv")).unwrap(), log);
}
