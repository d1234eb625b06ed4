//! Fuzzing the grid loader with proptest: arbitrary text, TOML-like token soup and mutated valid
//! files never panic; each either loads as a grid that keeps every rule of the format and
//! survives a save/load round trip, or is refused with a `GridError` of one line.
//!
//! The default case count keeps `cargo test` fast; for a long run:
//! `PROPTEST_CASES=200000 cargo test --release --lib grid::fuzz`.

use std::path::Path;

use nalgebra::Vector3;
use proptest::prelude::*;

use super::file::tests::calibrated;
use super::file::GridFile;
use super::lattice::tests::sample;
use super::GridError;

/// A valid file with every table the format knows and an unknown one.
fn valid_text() -> String {
    let mut file = calibrated();
    if let Some(c) = &mut file.calibration {
        c.n_init = Some(30);
        c.left_out_vertices = Some(vec![[-2, -2, -2], [2, 2, 2]]);
    }
    let mut text = file.to_toml_string();
    text.push_str("\n[future]\nkey = \"value\"\nwhen = 1979-05-27\n");
    text
}

/// Pieces of TOML and of grid files, the kind of thing a mutation should insert.
fn token() -> impl Strategy<Value = String> {
    prop_oneof![
        Just("nan".to_string()),
        Just("-inf".to_string()),
        Just("1e308".to_string()),
        Just("-1e-320".to_string()),
        Just("0".to_string()),
        Just("-0.0".to_string()),
        Just("9223372036854775807".to_string()),
        Just("-9223372036854775808".to_string()),
        Just("4294967296".to_string()),
        Just("\"\"".to_string()),
        Just("\"hgcd-grid/1\"".to_string()),
        Just("[".to_string()),
        Just("]".to_string()),
        Just("[[".to_string()),
        Just("{ a = 1 }".to_string()),
        Just(",".to_string()),
        Just("=".to_string()),
        Just("\n".to_string()),
        Just("#".to_string()),
        Just("[device]\n".to_string()),
        Just("[calibration]\n".to_string()),
        Just("[vertices]\n".to_string()),
        Just("[[vertices]]\n".to_string()),
        Just("dims = [1000, 1000, 1000]\n".to_string()),
        Just("masses = []\n".to_string()),
        Just("g = 9.81\n".to_string()),
        Just("force_vectors = [[1, 2]]\n".to_string()),
        Just("1979-05-27T07:32:00Z".to_string()),
        "[a-z_]{1,12}",
        "-?[0-9]{1,25}(\\.[0-9]{1,20})?(e-?[0-9]{1,3})?",
        ".{0,8}",
    ]
}

/// Mostly values in `range` (so that some files load), sometimes any value at all.
fn near(range: std::ops::Range<f64>) -> impl Strategy<Value = f64> {
    prop_oneof![3 => range, 1 => any::<f64>()]
}

/// One edit of a text, at a position given as a fraction of its length.
#[derive(Clone, Debug)]
enum Mutation {
    Insert(f64, String),
    Delete(f64, usize),
    Replace(f64, usize, String),
    DuplicateLine(f64),
    DropLine(f64),
    Truncate(f64),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    let at = 0.0..1.0f64;
    prop_oneof![
        (at.clone(), token()).prop_map(|(a, t)| Mutation::Insert(a, t)),
        (at.clone(), 1..40usize).prop_map(|(a, n)| Mutation::Delete(a, n)),
        (at.clone(), 1..12usize, token()).prop_map(|(a, n, t)| Mutation::Replace(a, n, t)),
        at.clone().prop_map(Mutation::DuplicateLine),
        at.clone().prop_map(Mutation::DropLine),
        at.prop_map(Mutation::Truncate),
    ]
}

/// The char boundary nearest below `fraction` of `text`'s length.
fn boundary(text: &str, fraction: f64) -> usize {
    let mut at = ((text.len() as f64) * fraction) as usize;
    while !text.is_char_boundary(at) {
        at -= 1;
    }
    at
}

fn apply(text: &mut String, m: &Mutation) {
    let end_of = |text: &str, from: usize, n: usize| {
        text[from..]
            .char_indices()
            .nth(n)
            .map_or(text.len(), |(i, _)| from + i)
    };
    match m {
        Mutation::Insert(a, t) => text.insert_str(boundary(text, *a), t),
        Mutation::Delete(a, n) => {
            let from = boundary(text, *a);
            text.replace_range(from..end_of(text, from, *n), "");
        }
        Mutation::Replace(a, n, t) => {
            let from = boundary(text, *a);
            text.replace_range(from..end_of(text, from, *n), t);
        }
        Mutation::DuplicateLine(a) | Mutation::DropLine(a) => {
            let at = boundary(text, *a);
            let start = text[..at].rfind('\n').map_or(0, |i| i + 1);
            let end = text[at..].find('\n').map_or(text.len(), |i| at + i + 1);
            let line = text[start..end].to_string();
            if matches!(m, Mutation::DuplicateLine(_)) {
                text.insert_str(start, &line);
            } else {
                text.replace_range(start..end, "");
            }
        }
        Mutation::Truncate(a) => text.truncate(boundary(text, *a)),
    }
}

/// What every outcome of the loader must satisfy.
fn loads_soundly_or_is_refused_in_one_line(text: &str) -> Result<(), TestCaseError> {
    let path = Path::new("fuzz.toml");
    match GridFile::from_toml_str(text, path) {
        Err(e) => {
            let message = e.to_string();
            prop_assert!(!message.contains('\n'), "{message:?}");
            prop_assert!(
                matches!(e, GridError::Syntax { .. } | GridError::Invalid { .. }),
                "{message}"
            );
        }
        Ok(file) => {
            prop_assert_eq!(file.check(), Ok(()));
            let grid = &file.grid;
            let far = grid.far_corner();
            for x in [
                grid.origin,
                far,
                (grid.origin + far) / 2.0,
                Vector3::new(1e3, -1e3, 0.5),
                Vector3::repeat(f64::MAX),
            ] {
                prop_assert!(grid.mass_at(&x).is_finite());
                prop_assert!(grid.gravity_force(&x).iter().all(|c| c.is_finite()));
            }
            // What was loaded saves and loads back the same (the direction, already normalised,
            // may move by an ulp when normalised again).
            let text = file.to_toml_string();
            let mut again = GridFile::from_toml_str(&text, path)
                .map_err(|e| TestCaseError::fail(format!("{e}\n{text}")))?;
            let drift = (again.grid.gravity_direction - grid.gravity_direction).norm();
            prop_assert!(drift < 1e-15);
            again.grid.gravity_direction = grid.gravity_direction;
            prop_assert_eq!(again.to_toml_string(), text);
        }
    }
    Ok(())
}

proptest! {
    #[test]
    fn arbitrary_text_never_panics(text in ".{0,400}") {
        loads_soundly_or_is_refused_in_one_line(&text)?;
    }

    #[test]
    fn token_soup_never_panics(tokens in proptest::collection::vec(token(), 0..60)) {
        loads_soundly_or_is_refused_in_one_line(&tokens.join(" "))?;
    }

    #[test]
    fn mutated_valid_files_never_panic(mutations in proptest::collection::vec(mutation(), 1..6)) {
        let mut text = valid_text();
        for m in &mutations {
            apply(&mut text, m);
        }
        loads_soundly_or_is_refused_in_one_line(&text)?;
    }

    #[test]
    fn arbitrary_values_in_a_valid_shape_never_panic(
        g in near(8.0..12.0), dx in near(-1e-3..1e-3), spacing in near(1e-3..0.5),
        ox in near(-10.0..10.0), nx in -2i64..5,
        masses in proptest::collection::vec(near(-100.0..100.0), 0..10),
        forces in proptest::collection::vec([near(-5.0..5.0), near(-5.0..5.0), near(0.0..20.0)], 0..10),
    ) {
        let text = format!(
            "format = \"hgcd-grid/1\"\ng = {g:?}\ngravity_direction = [{dx:?}, 0.0, 1.0]\n\
             origin = [{ox:?}, 0.0, 0.0]\nspacing = {spacing:?}\ndims = [{nx}, 1, 1]\n\
             masses = {masses:?}\n[vertices]\nforce_vectors = {forces:?}\n"
        )
        .replace("NaN", "nan");
        loads_soundly_or_is_refused_in_one_line(&text)?;
    }

    #[test]
    fn arbitrary_bytes_in_a_file_never_panic(
        bytes in proptest::collection::vec(any::<u8>(), 0..300), valid_prefix in any::<bool>(),
    ) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("dev.toml");
        let mut content = if valid_prefix { valid_text().into_bytes() } else { Vec::new() };
        content.extend_from_slice(&bytes);
        std::fs::write(&path, &content).unwrap();
        match GridFile::load(&path) {
            Ok(file) => prop_assert_eq!(file.check(), Ok(())),
            Err(e) => prop_assert!(!e.to_string().contains('\n')),
        }
    }
}

#[test]
fn the_valid_file_the_mutations_start_from_loads() {
    let file = GridFile::from_toml_str(&valid_text(), Path::new("valid.toml")).unwrap();
    assert_eq!(file.grid, sample());
}
