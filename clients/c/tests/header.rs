//! `include/hgcd.h` is committed so C users need no cbindgen: this test regenerates it and fails
//! when the committed one differs. `HGCD_BLESS=1 cargo test -p hgcd-c --test header` rewrites it.

use std::path::Path;

#[test]
fn the_committed_header_is_what_cbindgen_makes_of_the_source() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    let config = cbindgen::Config::from_file(dir.join("cbindgen.toml")).unwrap();
    let mut generated = Vec::new();
    cbindgen::Builder::new()
        .with_config(config)
        .with_src(dir.join("src/lib.rs"))
        .generate()
        .expect("cbindgen reads src/lib.rs")
        .write(&mut generated);
    let path = dir.join("include/hgcd.h");
    let committed = std::fs::read(&path).unwrap_or_default();
    if committed != generated {
        if std::env::var_os("HGCD_BLESS").is_some() {
            std::fs::write(&path, &generated).unwrap();
        } else {
            panic!(
                "{} differs from what cbindgen makes of src/lib.rs: run \
                 `HGCD_BLESS=1 cargo test -p hgcd-c --test header` and commit the header",
                path.display()
            );
        }
    }
}
