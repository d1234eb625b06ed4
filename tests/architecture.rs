//! The dependency direction of ARCHITECTURE.md, checked on the source: every `crate::module` path
//! outside comments must name a module of a lower layer than the file's own.

use std::path::{Path, PathBuf};

/// Layers, lowest first. A module may use modules of lower layers only.
const LAYERS: &[&[&str]] = &[
    &["protocol", "newest", "estimate", "sys", "figure", "arm"],
    &["config"],
    &["grid", "profile"],
    &["fit"],
    &["sim", "control"],
    &["transport", "mailbox"],
    &["servo"],
    &["app"],
    &["calibrate"],
    &["daemon"],
    &["validate", "discrepancy"],
];

fn layer(module: &str) -> Option<usize> {
    LAYERS.iter().position(|l| l.contains(&module))
}

/// The top-level module a source file belongs to (None for the binary's own files and lib.rs).
fn module_of(path: &Path, src: &Path) -> Option<String> {
    let rel = path.strip_prefix(src).ok()?;
    let first = rel.components().next()?.as_os_str().to_str()?;
    let name = first.strip_suffix(".rs").unwrap_or(first);
    (!matches!(name, "main" | "ctl" | "progress" | "lib")).then(|| name.to_string())
}

/// Every import against the layering in `text`, a file of `module`: (line number, used module).
fn back_imports(module: &str, text: &str) -> Vec<(usize, String)> {
    let own = layer(module).unwrap_or_else(|| panic!("module `{module}` has no layer"));
    let mut found = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let code = line.split("//").next().unwrap_or("");
        let mut rest = code;
        while let Some(at) = rest.find("crate::") {
            rest = &rest[at + "crate::".len()..];
            let used: String = rest
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect();
            if used == module {
                continue;
            }
            match layer(&used) {
                Some(l) if l < own => {}
                _ => found.push((n + 1, used)),
            }
        }
    }
    found
}

fn sources(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            sources(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

#[test]
fn every_module_uses_only_lower_layers() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    sources(&src, &mut files);
    let mut violations = Vec::new();
    for file in files {
        let Some(module) = module_of(&file, &src) else {
            continue;
        };
        let text = std::fs::read_to_string(&file).unwrap();
        for (line, used) in back_imports(&module, &text) {
            violations.push(format!(
                "{}:{line}: `{module}` uses `{used}`",
                file.display()
            ));
        }
    }
    assert!(
        violations.is_empty(),
        "imports against ARCHITECTURE.md's dependency direction:\n{}",
        violations.join("\n")
    );
}

#[test]
fn a_back_import_is_caught() {
    // The servo loop must not know the daemon, nor the mailbox the application server.
    assert_eq!(
        back_imports("servo", "use crate::daemon::controller::Arbiter;"),
        vec![(1, "daemon".to_string())]
    );
    assert_eq!(
        back_imports("mailbox", "    x: crate::app::server::Registry,\n"),
        vec![(1, "app".to_string())]
    );
    // Downward imports and comments are fine.
    assert!(back_imports("daemon", "use crate::servo::ServoReport; // crate::daemon").is_empty());
    assert!(back_imports("servo", "/// see [`crate::daemon::run`]").is_empty());
}
