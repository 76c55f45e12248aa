//! The workspace's integration tests, as one test binary: linking the whole server once
//! instead of once per file. Each former test binary `tests/NAME.rs` is the module `NAME`, so
//! `cargo test --test suite NAME::` runs what `cargo test --test NAME` ran.
//!
//! Nothing here relies on being alone in its process: the servers under test are child
//! processes (or in-process ones on their own ports and runtimes), each test has its own
//! temporary directories, and no test sets an environment variable, the working directory, a
//! global tracing subscriber or a resource limit of this process (limits are set on children
//! with `prlimit`). A test that needs any of those needs a binary of its own, like
//! `server/tests/logs.rs`.
//!
//! `autotests = false` in Cargo.toml: a new `tests/*.rs` file must be added below, or
//! [`every_test_file_is_a_module_of_the_suite`] fails.

#[path = "common/mod.rs"]
mod common;
#[path = "tev_decoder/mod.rs"]
mod tev_decoder;

#[path = "aov_names.rs"]
mod aov_names;
#[path = "aov_passes.rs"]
mod aov_passes;
#[path = "blender_worker.rs"]
mod blender_worker;
#[path = "denoise_oidn.rs"]
mod denoise_oidn;
#[path = "durability_crash.rs"]
mod durability_crash;
#[path = "image_provenance.rs"]
mod image_provenance;
#[path = "live_page.rs"]
mod live_page;
#[path = "merge_memory.rs"]
mod merge_memory;
#[path = "merge_nodes.rs"]
mod merge_nodes;
#[path = "mitsuba_worker.rs"]
mod mitsuba_worker;
#[path = "nginx_farm.rs"]
mod nginx_farm;
#[path = "passes_exr.rs"]
mod passes_exr;
#[path = "passes_layouts.rs"]
mod passes_layouts;
#[path = "python_client_server.rs"]
mod python_client_server;
#[path = "service_auth.rs"]
mod service_auth;
#[path = "service_faults.rs"]
mod service_faults;
#[path = "service_hostile.rs"]
mod service_hostile;
#[path = "service_http.rs"]
mod service_http;
#[path = "service_metrics.rs"]
mod service_metrics;
#[path = "service_need.rs"]
mod service_need;
#[path = "service_passes.rs"]
mod service_passes;
#[path = "service_tev.rs"]
mod service_tev;
#[path = "state_batch_digests.rs"]
mod state_batch_digests;
#[path = "tev_protocol.rs"]
mod tev_protocol;

/// Every `tests/*.rs` is one of the modules above, and every module above is a file there: with
/// `autotests = false` a new file would otherwise never be compiled nor run.
#[test]
fn every_test_file_is_a_module_of_the_suite() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests");
    let mut files: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|n| n.ends_with(".rs") && n != "suite.rs")
        .collect();
    files.sort();
    let suite = std::fs::read_to_string(dir.join("suite.rs")).unwrap();
    let mut modules: Vec<String> = suite
        .lines()
        .filter_map(|l| l.strip_prefix("#[path = \""))
        .filter_map(|l| l.strip_suffix("\"]"))
        .filter(|p| !p.contains('/'))
        .map(str::to_owned)
        .collect();
    modules.sort();
    assert_eq!(
        files, modules,
        "tests/*.rs and the modules of tests/suite.rs"
    );
}
