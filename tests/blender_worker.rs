//! The Blender worker end to end, on two Blenders: Debian's Blender 3.4 run as a command
//! (`blender -b scene.blend --python blender_worker.py -- ...`) and Blender 5.0 as a Python module
//! (PyPI's `bpy` wheel, `python blender_worker.py --blend scene.blend ...`). Each renders Cycles
//! passes of a tiny scene with a small bright lamp (the worker's demo scene, saved as a .blend
//! by that Blender) and posts them to a durable server with the installed Python client holding
//! only a `write` token. The served `mean` is the mean of the passes as Blender wrote them, `spp`
//! is the pass count, and the mean of the passes agrees with a high-spp box-filtered render
//! within noise, over the whole image, at the lamp and along edges (where a fixed sub-pixel
//! position is biased). The passes carry Cycles' albedo, normal and depth passes as AOVs
//! (multilayer EXRs: one part on 3.4, one part per pass on 5.0); the frame declares the layers
//! the passes have, under the names that Blender gives them, and serves their exact means.
//! Then: two jobs of one frame, a job run twice, `--until-converged`, no temporary files left,
//! and wrong use failing with a message.
//!
//! Blender is installed by `tests/setup/blender.sh` (Debian's) and `tests/setup/bpy.sh` (the
//! bpy module, in a venv of its own). When that cannot be done the test says why and skips, or,
//! on CI (`CI=true`), where it must be installed, fails.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use crate::common::{
    durable_args, python_package_venv, run_setup, runtime, skip_unless_ci, venv_site_packages,
    Server,
};
use splatd_proto::api::{ImageQuery, WaitingOn};
use splatd_proto::Client;

const WRITE: &str = "w-blender-0123456789abcdef";
const READ: &str = "r-blender-0123456789abcdef";
/// `--until-converged` reads the frame's convergence: a token with both roles.
const READ_WRITE: &str = "rw-blender-0123456789abcdef";
const PASSES: usize = 256;
const REFERENCE_SPP: usize = 4096;

/// How the worker runs Blender.
enum Blender {
    /// The `blender` executable: the worker is a `--python` script, its arguments after `--`.
    Command(PathBuf),
    /// A Python with the `bpy` module: the worker is the program.
    Module(PathBuf),
}

/// The Blender a setup script installs, or `None` when it could not be installed: then the
/// test skips, saying so loudly, or on CI, where it must run, fails.
fn install(test: &str, script: &str, what: &str) -> Option<String> {
    match run_setup(script) {
        Ok(path) => Some(path),
        Err(e) => {
            let why = format!("{what} could not be installed (tests/setup/{script}): {e}");
            skip_unless_ci(test, &why);
            None
        }
    }
}

#[test]
fn blender_as_a_command_converges_to_the_antialiased_image() {
    let test = "blender_as_a_command_converges_to_the_antialiased_image";
    if let Some(blender) = install(test, "blender.sh", "Debian's Blender") {
        check_worker(Blender::Command(blender.into()));
    }
}

#[test]
fn blender_as_the_bpy_module_converges_to_the_antialiased_image() {
    let test = "blender_as_the_bpy_module_converges_to_the_antialiased_image";
    if let Some(python) = install(test, "bpy.sh", "Blender as a Python module (bpy)") {
        check_worker(Blender::Module(python.into()));
    }
}

/// A copy of `proto/python` (so no build files land in the checkout) installed by `python`'s
/// pip into `dir/client` without dependencies: the bpy module's environment has numpy already,
/// at the version its Blender was built with. Returns the folder to put on `PYTHONPATH`.
fn client_without_dependencies(python: &Path, dir: &Path) -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let source = dir.join("client-src");
    std::fs::create_dir_all(source.join("splatd_client")).unwrap();
    for file in ["pyproject.toml", "README.md"] {
        std::fs::copy(root.join("proto/python").join(file), source.join(file)).unwrap();
    }
    for entry in std::fs::read_dir(root.join("proto/python/splatd_client")).unwrap() {
        let path = entry.unwrap().path();
        if path.is_file() {
            let to = source.join("splatd_client").join(path.file_name().unwrap());
            std::fs::copy(&path, to).unwrap();
        }
    }
    let target = dir.join("client");
    let out = Command::new(python)
        .args([
            "-m",
            "pip",
            "install",
            "--quiet",
            "--disable-pip-version-check",
        ])
        .args(["--no-deps", "--target"])
        .arg(&target)
        .arg(&source)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "pip install --target of the client failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    target
}

fn text(out: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

fn check_worker(blender: Blender) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().unwrap();
    let pythonpath = match &blender {
        Blender::Command(_) => venv_site_packages(&python_package_venv(dir.path())),
        Blender::Module(python) => client_without_dependencies(python, dir.path())
            .display()
            .to_string(),
    };
    // The worker's temporary passes go here: it must leave nothing behind.
    let tmp = dir.path().join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    let data = dir.path().join("data");
    let server = Server::start_with_env(
        &durable_args(&data)
            .iter()
            .map(String::as_str)
            .collect::<Vec<_>>(),
        &[(
            "SPLATD_TOKENS",
            &format!("write {WRITE};read {READ};read,write {READ_WRITE}"),
        )],
    );
    let worker = root.join("proto/python/blender_worker.py");
    let scene = dir.path().join("demo.blend");
    // Runs `script` with `args` in this Blender, with `scene` open unless it is None.
    let blender_cmd = |script: &Path, blend: Option<&Path>, args: &[&str]| {
        let mut cmd = match &blender {
            Blender::Command(exe) => {
                let mut cmd = Command::new(exe);
                // No audio device: Blender's sound system otherwise starts PulseAudio's
                // client, which leaves a `pulse-*` folder in TMPDIR now and then.
                cmd.args(["-b", "-noaudio"]);
                match blend {
                    Some(blend) => cmd.arg(blend),
                    None => cmd.arg("--factory-startup"),
                };
                cmd.args(["--python-exit-code", "1", "--python-use-system-env"])
                    .arg("--python")
                    .arg(script)
                    .arg("--");
                cmd
            }
            Blender::Module(python) => {
                let mut cmd = Command::new(python);
                cmd.arg(script);
                if let Some(blend) = blend {
                    cmd.arg("--blend").arg(blend);
                }
                cmd
            }
        };
        cmd.args(args)
            .env("PYTHONPATH", &pythonpath)
            .env("SPLATD_TOKEN", WRITE)
            .env("TMPDIR", &tmp);
        cmd.output()
            .unwrap_or_else(|e| panic!("{}: {e}", script.display()))
    };
    let run_ok = |script: &Path, blend: Option<&Path>, args: &[&str], what: &str| {
        let out = blender_cmd(script, blend, args);
        let all = text(&out);
        assert!(
            out.status.success() && !all.contains("Traceback"),
            "{what} failed ({}):\n{all}",
            out.status
        );
        all
    };
    let saved = run_ok(
        &root.join("tests/py/save_demo_scene.py"),
        None,
        &[
            root.join("proto/python").to_str().unwrap(),
            scene.to_str().unwrap(),
        ],
        "saving the demo scene",
    );
    let version = saved
        .lines()
        .find_map(|l| l.split_once(" with Blender "))
        .map(|(_, v)| v.trim().to_owned())
        .unwrap_or_else(|| panic!("no version in {saved}"));
    eprintln!("Blender {version}: {saved}");

    let worker_run = |args: &[&str], what: &str| {
        let mut all = vec!["--url", server.url.as_str()];
        all.extend_from_slice(args);
        run_ok(&worker, Some(&scene), &all, what)
    };
    let passes_dir = dir.path().join("passes");
    let passes = PASSES.to_string();
    let started = std::time::Instant::now();
    worker_run(
        &[
            "--frame",
            "cycles",
            "--passes",
            &passes,
            "--aovs",
            "albedo,normal,depth",
            "--keep-dir",
            passes_dir.to_str().unwrap(),
        ],
        "the Blender worker",
    );
    let worker_time = started.elapsed();
    let reference = dir.path().join("reference.exr");
    run_ok(
        &worker,
        Some(&scene),
        &[
            "--reference",
            &REFERENCE_SPP.to_string(),
            "--output",
            reference.to_str().unwrap(),
        ],
        "the reference render",
    );

    let rt = runtime();
    let read = Client::new(&server.url).unwrap().with_token(READ);
    let served = rt
        .block_on(read.image("cycles", &ImageQuery::default()))
        .unwrap();
    std::fs::write(dir.path().join("served.exr"), &served).unwrap();
    let info = rt.block_on(read.frame_info("cycles")).unwrap();
    assert_eq!((info.spp_min, info.spp_max), (PASSES as u64, PASSES as u64));

    let out = Command::new("python3")
        .arg(root.join("tests/py/blender_stats.py"))
        .arg(dir.path())
        .arg(&passes)
        .arg(REFERENCE_SPP.to_string())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "blender_stats.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stats: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    eprintln!(
        "Blender {version}: {PASSES} passes in {:.1} s; passes against the reference: {stats}",
        worker_time.as_secs_f64()
    );
    let f = |v: &serde_json::Value| v.as_f64().unwrap();

    // The frame declares the layers the passes have beside the beauty, as OpenEXR reads them,
    // under this Blender's names.
    let mut declared: Vec<(String, Vec<String>)> = info
        .aovs
        .iter()
        .map(|a| {
            let mut channels = a.channels.clone();
            channels.sort();
            (a.name.clone(), channels)
        })
        .collect();
    declared.sort();
    let mut in_passes: Vec<(String, Vec<String>)> = stats["layers"]
        .as_object()
        .unwrap()
        .iter()
        .map(|(name, channels)| {
            let mut channels: Vec<String> = channels
                .as_array()
                .unwrap()
                .iter()
                .map(|c| c.as_str().unwrap().to_owned())
                .collect();
            channels.sort();
            (name.clone(), channels)
        })
        .collect();
    in_passes.sort();
    assert_eq!(declared, in_passes, "{stats}");
    assert_eq!(declared.len(), 3, "{declared:?}");
    // What the two Blenders tested here call their diffuse colour pass.
    let albedo = match version.split('.').next() {
        Some("3") => Some("ViewLayer.DiffCol"),
        Some("5") => Some("ViewLayer.Diffuse Color"),
        _ => None,
    };
    if let Some(albedo) = albedo {
        assert!(
            declared.iter().any(|(name, _)| name == albedo),
            "Blender {version}'s diffuse colour pass is {albedo}: {declared:?}"
        );
    }

    // The served mean is the passes' mean, to the fixed point's rounding.
    assert!(
        f(&stats["served_vs_passes"]["max_rel"]) < 1e-5
            || f(&stats["served_vs_passes"]["max_abs"]) < 1e-6,
        "{stats}"
    );
    // Every AOV channel of the passes is served, as their mean to the fixed point's step.
    assert_eq!(stats["aovs"].as_array().unwrap().len(), 7, "{stats}");
    assert!(f(&stats["aovs_worst"]) <= 1.0, "{stats}");
    assert_eq!(f(&stats["spp_min"]), PASSES as f64, "{stats}");
    assert_eq!(f(&stats["spp_max"]), PASSES as f64, "{stats}");
    // No systematic offset: over the image, at the lamp and along edges, within 5 standard
    // deviations. (Passes that all sample the pixel centres, as Cycles' own seeds do, are 24 %
    // too bright at this lamp: hundreds of standard deviations.)
    for region in ["global", "lamp", "edges"] {
        let r = &stats[region];
        assert!(
            f(&r["sum"]).abs() <= 5.0 * f(&r["sigma"]),
            "{region}: the passes' mean is off the reference by {} (sigma {}, reference {})",
            f(&r["sum"]),
            f(&r["sigma"]),
            f(&r["reference"])
        );
    }

    // Two jobs of one frame: each renders its share under a worker id of its own, so together
    // they post every pass of the budget once; a job run again adds nothing and says so.
    for job in ["0", "1"] {
        worker_run(
            &[
                "--frame",
                "jobs",
                "--passes",
                "5",
                "--job-index",
                job,
                "--job-count",
                "2",
            ],
            "a job",
        );
    }
    let jobs = rt.block_on(read.frame_info("jobs")).unwrap();
    assert_eq!((jobs.spp_min, jobs.spp_max, jobs.batches), (5, 5, 5));
    let again = worker_run(
        &[
            "--frame",
            "jobs",
            "--passes",
            "5",
            "--job-index",
            "0",
            "--job-count",
            "2",
        ],
        "a job run again",
    );
    assert!(
        again.contains("3 of 3 passes were already in frame jobs"),
        "{again}"
    );

    // Until converged: the worker stops at the first pass after which the server says the
    // frame has converged (the demo scene converges within a few passes), below the budget,
    // and the frame holds exactly the passes it posted.
    let until = worker_run(
        &[
            "--frame",
            "until",
            "--passes",
            "64",
            "--until-converged",
            "--token",
            READ_WRITE,
        ],
        "--until-converged",
    );
    let done = rt.block_on(read.frame_info("until")).unwrap();
    let verdict = done.convergence.as_ref().map(|c| c.converged);
    assert_eq!(verdict, Some(true), "{until}");
    assert!(
        done.spp_max < 64 && until.contains("has converged"),
        "{until}"
    );
    // The verdict came while the next pass rendered, which was then left out.
    assert!(
        until.contains("rendered meanwhile and is not posted"),
        "{until}"
    );
    let posted = until.lines().filter(|l| l.starts_with("pass ")).count() as u64;
    assert_eq!(posted, done.spp_max, "{until}");

    // A budget spent first: the job says what the frame still waits on, as the server does
    // (two passes are far below the 16 samples a pixel from which each pixel's own count).
    let short = worker_run(
        &[
            "--frame",
            "until-short",
            "--passes",
            "2",
            "--until-converged",
            "--token",
            READ_WRITE,
        ],
        "--until-converged with a budget of 2 passes",
    );
    let c = rt
        .block_on(read.frame_info("until-short"))
        .unwrap()
        .convergence
        .expect("figures of two passes");
    let why = match c.waiting_on.expect("not converged at two passes") {
        WaitingOn::PixelsWithoutSamples => "some pixels have no samples",
        WaitingOn::RemovedEnergy => "the resolve removes",
        WaitingOn::OwnSamples => "short of each pixel's own samples",
    };
    assert!(
        short.contains("2 passes rendered, the budget, and it has not converged: ")
            && short.contains(why),
        "{c:?}\n{short}"
    );

    // Nothing left in the temporary folder.
    let left: Vec<_> = std::fs::read_dir(&tmp).unwrap().collect();
    assert!(left.is_empty(), "the worker left {left:?} in TMPDIR");

    // Wrong use is an error with a message and a non-zero exit, never a default render.
    let fails = |script_args: &[&str], blend: Option<&Path>, expect: &str| {
        let out = blender_cmd(&worker, blend, script_args);
        let all = text(&out);
        assert!(
            !out.status.success() && all.contains(expect),
            "{script_args:?} should fail saying {expect:?} ({}):\n{all}",
            out.status
        );
    };
    let url = server.url.as_str();
    fails(
        &["--url", url, "--frame", "until2", "--until-converged"],
        Some(&scene),
        "needs a token with the read role",
    );
    fails(
        &["--url", url, "--passes", "many"],
        Some(&scene),
        "argument --passes",
    );
    fails(&["--url", url, "--frame", "x"], None, "no scene");
    fails(
        &[
            "--url",
            url,
            "--frame",
            "cycles",
            "--resolution",
            "16",
            "12",
        ],
        Some(&scene),
        "frame_exists",
    );
    let info = rt.block_on(read.frame_info("cycles")).unwrap();
    assert_eq!(
        info.spp_max, PASSES as u64,
        "a refused run changed the frame"
    );
}
