//! `include/spidar.h` is what cbindgen makes of `src/` now: an exported
//! function or struct changed without the header fails here.
//! `SPIDAR_BLESS=1 cargo test -p spidar-capi --test header` rewrites it.

use std::path::Path;

#[test]
fn header_is_generated() {
    let crate_dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    let config = cbindgen::Config::from_file(crate_dir.join("cbindgen.toml")).unwrap();
    let bindings = cbindgen::Builder::new()
        .with_crate(crate_dir)
        .with_config(config)
        .generate()
        .expect("cbindgen parses src/");
    let mut generated = Vec::new();
    bindings.write(&mut generated);
    let generated = String::from_utf8(generated).unwrap();
    let path = crate_dir.join("include/spidar.h");
    if std::env::var_os("SPIDAR_BLESS").is_some() {
        std::fs::write(&path, &generated).unwrap();
        return;
    }
    let kept = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        kept == generated,
        "{} is out of date with src/: run `SPIDAR_BLESS=1 cargo test -p spidar-capi --test header` and commit it",
        path.display()
    );
    // Every exported function is declared (cbindgen would leave out one
    // that is not `extern "C"` with `#[no_mangle]`).
    let src = std::fs::read_to_string(crate_dir.join("src/lib.rs")).unwrap();
    for line in src
        .lines()
        .filter(|l| l.starts_with("pub extern \"C\" fn "))
    {
        let name = line["pub extern \"C\" fn ".len()..]
            .split('(')
            .next()
            .unwrap();
        let declared = [format!(" {name}("), format!("*{name}(")];
        assert!(
            declared.iter().any(|d| kept.contains(d.as_str())),
            "{name} is not in the header"
        );
    }
}
