//! Names the git commit hgcd is built from (`hgcd --version`): `HGCD_GIT_COMMIT` is
//! `git rev-parse --short HEAD`, or "unknown" outside a git checkout (a source tarball).

use std::path::PathBuf;
use std::process::Command;

/// The crate's directory, as Cargo gives it to this run. (Not `env!`, which is where the build
/// script was compiled: a target directory shared with another checkout, as `.ci/package`'s fresh
/// clones share this one's, reruns a build script compiled there, whose directory may be gone.)
fn crate_dir() -> PathBuf {
    PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("Cargo sets CARGO_MANIFEST_DIR"))
}

/// `git ARGS` in the crate's directory: its first line of output, if git ran and succeeded.
fn git(args: &[&str]) -> Option<String> {
    let out = Command::new("git")
        .args(args)
        .current_dir(crate_dir())
        .output()
        .ok()?;
    let text = String::from_utf8(out.stdout).ok()?;
    let line = text.lines().next()?.trim().to_string();
    (out.status.success() && !line.is_empty()).then_some(line)
}

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    let commit = git(&["rev-parse", "--short", "HEAD"]);
    if commit.is_some() {
        // A new commit moves HEAD (detached) or the branch it points at, loose or packed; in a
        // worktree these live in different git directories, which `--git-path` resolves.
        let mut watched = vec!["HEAD".to_string(), "packed-refs".to_string()];
        watched.extend(git(&["symbolic-ref", "-q", "HEAD"]));
        for name in watched {
            if let Some(path) = git(&["rev-parse", "--git-path", &name]) {
                // A path that does not exist would rerun this script at every build.
                let path = crate_dir().join(path);
                if path.exists() {
                    println!("cargo:rerun-if-changed={}", path.display());
                }
            }
        }
    }
    println!(
        "cargo:rustc-env=HGCD_GIT_COMMIT={}",
        commit.as_deref().unwrap_or("unknown")
    );
}
