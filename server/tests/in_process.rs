//! The server crate's integration tests that share a process, as one test binary (each binary
//! links the whole server): each former `server/tests/NAME.rs` binary is the module `NAME`.
//!
//! `logs.rs` stays a binary of its own: it installs the process's global tracing subscriber
//! (tracing caches each call site's interest process-wide, so a capture beside other tests that
//! log without a subscriber sometimes received nothing).
//!
//! `autotests = false` in server/Cargo.toml: a new `server/tests/*.rs` file must be added here
//! or as a `[[test]]` of its own, or [`every_test_file_is_built`] fails.

#[path = "connections.rs"]
mod connections;
#[path = "request_timeout.rs"]
mod request_timeout;

/// Every `server/tests/*.rs` is a module here or a `[[test]]` of its own in server/Cargo.toml:
/// with `autotests = false` a new file would otherwise never be compiled nor run.
#[test]
fn every_test_file_is_built() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let manifest = std::fs::read_to_string(root.join("Cargo.toml")).unwrap();
    let this = std::fs::read_to_string(root.join("tests/in_process.rs")).unwrap();
    for entry in std::fs::read_dir(root.join("tests")).unwrap() {
        let name = entry.unwrap().file_name().into_string().unwrap();
        if !name.ends_with(".rs") {
            continue;
        }
        let target = format!("path = \"tests/{name}\"");
        let module = format!("#[path = \"{name}\"]");
        assert!(
            manifest.contains(&target) || this.contains(&module),
            "server/tests/{name} is neither a [[test]] in server/Cargo.toml nor a module of \
             server/tests/in_process.rs"
        );
    }
}
