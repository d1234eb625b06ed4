//! What the fuzz properties share (`docs/fuzzing.md`): case counts, and for the text formats
//! tokens and edits that mutate a valid file.

use proptest::prelude::*;
use proptest::test_runner::Config;

/// Cases per property of the wire codecs in a plain `cargo test`.
pub const DEFAULT_CASES: u32 = 4096;

/// `DEFAULT_CASES` cases, or `PROPTEST_CASES` when it is set (a long campaign).
pub fn config() -> Config {
    cases(DEFAULT_CASES)
}

/// `default` cases, or `PROPTEST_CASES` when it is set.
pub fn cases(default: u32) -> Config {
    let mut config = Config::default();
    if std::env::var_os("PROPTEST_CASES").is_none() {
        config.cases = default;
    }
    config
}

/// Pieces of TOML a mutation should insert: extreme numbers, strings, brackets, dates.
pub fn toml_token() -> BoxedStrategy<String> {
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
        Just("[".to_string()),
        Just("]".to_string()),
        Just("[[".to_string()),
        Just("{ a = 1 }".to_string()),
        Just(",".to_string()),
        Just("=".to_string()),
        Just("\n".to_string()),
        Just("#".to_string()),
        Just("true".to_string()),
        Just("1979-05-27T07:32:00Z".to_string()),
        "[a-z_]{1,12}",
        number(),
        ".{0,8}",
    ]
    .boxed()
}

/// A decimal number of any length and exponent, as text.
pub fn number() -> impl Strategy<Value = String> {
    "-?[0-9]{1,25}(\\.[0-9]{1,20})?(e-?[0-9]{1,3})?"
}

/// Mostly values in `range` (so that some files load), sometimes any value at all.
pub fn near(range: std::ops::Range<f64>) -> impl Strategy<Value = f64> {
    prop_oneof![3 => range, 1 => any::<f64>()]
}

/// As [`near`], for files of many numbers: any value at all one time in 30.
pub fn mostly(range: std::ops::Range<f64>) -> impl Strategy<Value = f64> {
    prop_oneof![29 => range, 1 => any::<f64>()]
}

/// One edit of a text, at a position given as a fraction of its length.
#[derive(Clone, Debug)]
pub enum Mutation {
    Insert(f64, String),
    Delete(f64, usize),
    Replace(f64, usize, String),
    DuplicateLine(f64),
    DropLine(f64),
    Truncate(f64),
}

/// An edit that inserts or replaces with pieces drawn from `token`.
pub fn mutation(token: BoxedStrategy<String>) -> impl Strategy<Value = Mutation> {
    let at = 0.0..1.0f64;
    prop_oneof![
        (at.clone(), token.clone()).prop_map(|(a, t)| Mutation::Insert(a, t)),
        (at.clone(), 1..40usize).prop_map(|(a, n)| Mutation::Delete(a, n)),
        (at.clone(), 1..12usize, token).prop_map(|(a, n, t)| Mutation::Replace(a, n, t)),
        at.clone().prop_map(Mutation::DuplicateLine),
        at.clone().prop_map(Mutation::DropLine),
        at.prop_map(Mutation::Truncate),
    ]
}

/// `text` after `mutations`, in order.
pub fn mutated(mut text: String, mutations: &[Mutation]) -> String {
    for m in mutations {
        apply(&mut text, m);
    }
    text
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

/// The properties every text format's fuzzer has, with `config`: arbitrary text, a soup of
/// `token()`s, and a valid file drawn from `seed` (a strategy of `String`) after a few
/// mutations; `check` (text to a `Result<(), TestCaseError>`) says what each outcome keeps.
macro_rules! text_properties {
    ($config:expr, $check:path, $token:path, $seed:expr) => {
        proptest::proptest! {
            #![proptest_config($config)]

            #[test]
            fn arbitrary_text_never_panics(text in ".{0,400}") {
                $check(&text)?;
            }

            #[test]
            fn token_soup_never_panics(tokens in proptest::collection::vec($token(), 0..60)) {
                $check(&tokens.join(" "))?;
            }

            #[test]
            fn mutated_valid_files_never_panic(
                seed in $seed,
                mutations in proptest::collection::vec(
                    $crate::protocol::fuzz::mutation($token()), 1..6,
                ),
            ) {
                $check(&$crate::protocol::fuzz::mutated(seed, &mutations))?;
            }
        }
    };
}
pub(crate) use text_properties;
