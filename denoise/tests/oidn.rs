//! The run-time-loaded OIDN against OIDN's own command-line denoiser, `oidnDenoise`, from the
//! same `pyoidn` wheel: the same synthetic noisy image, written as PFM for it, must come out the
//! same (an independent path through the library: its own image I/O, device and filter setup).
//! And the errors of a missing or wrong library, which need no OIDN at all.

use std::path::{Path, PathBuf};
use std::process::Command;

use splatd_denoise::{DenoiseError, DenoiseInput, Oidn, Quality};

/// The OIDN library: `SPLATD_OIDN_LIB`, or what `tests/setup/oidn.sh` installs and prints. `None`
/// (said loudly) when it cannot be had outside CI; in CI that is a failure.
fn library() -> Option<PathBuf> {
    if let Some(path) = std::env::var_os("SPLATD_OIDN_LIB").filter(|p| !p.is_empty()) {
        return Some(PathBuf::from(path));
    }
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/setup/oidn.sh");
    let out = Command::new("bash")
        .arg(&script)
        .output()
        .unwrap_or_else(|e| panic!("running {}: {e}", script.display()));
    if out.status.success() {
        return Some(PathBuf::from(
            String::from_utf8_lossy(&out.stdout).trim().to_owned(),
        ));
    }
    let why = format!(
        "OIDN IS NOT AVAILABLE: SPLATD_OIDN_LIB is not set and tests/setup/oidn.sh failed: {}",
        String::from_utf8_lossy(&out.stderr).trim()
    );
    if std::env::var("CI").is_ok_and(|v| v == "true") {
        panic!("{why}");
    }
    eprintln!("\n!!!!!!!!!! {why}\n!!!!!!!!!! THIS TEST CHECKED NOTHING WITH THE REAL OIDN\n");
    None
}

/// A deterministic noisy HDR image with guides: a lit gradient over a checker albedo, with a
/// normal that tilts across the frame, and per-pixel noise with rare bright outliers.
struct Scene {
    width: usize,
    height: usize,
    color: Vec<[f32; 3]>,
    albedo: Vec<[f32; 3]>,
    normal: Vec<[f32; 3]>,
}

fn scene(width: usize, height: usize) -> Scene {
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut uniform = move || {
        // xorshift64*: reproducible everywhere, no dependency.
        state ^= state >> 12;
        state ^= state << 25;
        state ^= state >> 27;
        (state.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 40) as f32 / (1u64 << 24) as f32
    };
    let (mut color, mut albedo, mut normal) = (Vec::new(), Vec::new(), Vec::new());
    for y in 0..height {
        for x in 0..width {
            let checker = if (x / 8 + y / 8) % 2 == 0 { 0.8 } else { 0.3 };
            let a = [checker, checker * 0.9, checker * 0.6];
            let light = 0.2 + 1.5 * x as f32 / width as f32;
            let noise = 0.4 + 1.2 * uniform();
            let spike = if uniform() < 0.01 { 40.0 } else { 1.0 };
            color.push(a.map(|c| c * light * noise * spike));
            albedo.push(a);
            let t = (y as f32 / height as f32 - 0.5) * 1.2;
            let n = [t.sin(), 0.0, t.cos()];
            normal.push(n);
        }
    }
    Scene {
        width,
        height,
        color,
        albedo,
        normal,
    }
}

/// Writes a little-endian colour PFM (bottom row first, as the format says).
fn write_pfm(path: &Path, width: usize, height: usize, rgb: &[[f32; 3]]) {
    let mut bytes = format!("PF\n{width} {height}\n-1.0\n").into_bytes();
    for y in (0..height).rev() {
        for px in &rgb[y * width..(y + 1) * width] {
            for c in px {
                bytes.extend_from_slice(&c.to_le_bytes());
            }
        }
    }
    std::fs::write(path, bytes).unwrap();
}

/// Reads a colour PFM, returning top row first.
fn read_pfm(path: &Path) -> (usize, usize, Vec<[f32; 3]>) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut fields = Vec::new();
    let mut at = 0;
    while fields.len() < 4 {
        while bytes[at].is_ascii_whitespace() {
            at += 1;
        }
        let start = at;
        while !bytes[at].is_ascii_whitespace() {
            at += 1;
        }
        fields.push(String::from_utf8(bytes[start..at].to_vec()).unwrap());
    }
    at += 1; // the single whitespace byte after the scale
    assert_eq!(fields[0], "PF", "a colour PFM");
    let width: usize = fields[1].parse().unwrap();
    let height: usize = fields[2].parse().unwrap();
    let scale: f32 = fields[3].parse().unwrap();
    let little = scale < 0.0;
    let floats: Vec<f32> = bytes[at..]
        .chunks_exact(4)
        .map(|b| {
            let b = [b[0], b[1], b[2], b[3]];
            if little {
                f32::from_le_bytes(b)
            } else {
                f32::from_be_bytes(b)
            }
        })
        .collect();
    assert_eq!(floats.len(), width * height * 3, "PFM size");
    let mut rgb = vec![[0f32; 3]; width * height];
    for (row, line) in floats.chunks_exact(width * 3).enumerate() {
        let y = height - 1 - row;
        for (x, px) in line.chunks_exact(3).enumerate() {
            rgb[y * width + x] = [px[0], px[1], px[2]];
        }
    }
    (width, height, rgb)
}

/// `oidnDenoise` from the wheel (`../bin/` beside the library's directory) on `scene`.
fn oidn_denoise_cli(lib: &Path, scene: &Scene, guided: bool, quality: Quality) -> Vec<[f32; 3]> {
    let lib = std::fs::canonicalize(lib).unwrap();
    let cli = lib.parent().unwrap().join("../bin/oidnDenoise");
    assert!(
        cli.is_file(),
        "{} not found beside the library (the pyoidn wheel ships it)",
        cli.display()
    );
    let dir = tempfile_dir();
    let (w, h) = (scene.width, scene.height);
    write_pfm(&dir.join("color.pfm"), w, h, &scene.color);
    let mut cmd = Command::new(&cli);
    cmd.args([
        "-d",
        "cpu",
        "--affinity",
        "0",
        "-q",
        quality.as_str(),
        "--hdr",
    ])
    .arg(dir.join("color.pfm"));
    if guided {
        write_pfm(&dir.join("albedo.pfm"), w, h, &scene.albedo);
        write_pfm(&dir.join("normal.pfm"), w, h, &scene.normal);
        cmd.arg("--alb")
            .arg(dir.join("albedo.pfm"))
            .arg("--nrm")
            .arg(dir.join("normal.pfm"));
    }
    cmd.arg("-o").arg(dir.join("out.pfm"));
    let out = cmd.output().expect("running oidnDenoise");
    assert!(
        out.status.success(),
        "oidnDenoise failed: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let (ow, oh, rgb) = read_pfm(&dir.join("out.pfm"));
    assert_eq!((ow, oh), (w, h));
    std::fs::remove_dir_all(&dir).unwrap();
    rgb
}

/// A fresh directory under the target's temporary directory (no extra crate for it).
fn tempfile_dir() -> PathBuf {
    use std::sync::atomic::{AtomicU32, Ordering};
    static N: AtomicU32 = AtomicU32::new(0);
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!(
        "oidn-{}-{}",
        std::process::id(),
        N.fetch_add(1, Ordering::Relaxed)
    ));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The largest difference relative to the value's size (plus an absolute floor for dark pixels).
fn max_relative_difference(a: &[[f32; 3]], b: &[[f32; 3]]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(x, y)| (x - y).abs() / (x.abs().max(y.abs()) + 1e-3))
        .fold(0.0, f32::max)
}

fn input(scene: &Scene, guided: bool, quality: Quality) -> DenoiseInput<'_> {
    DenoiseInput {
        width: scene.width,
        height: scene.height,
        color: &scene.color,
        albedo: guided.then_some(&scene.albedo[..]),
        normal: guided.then_some(&scene.normal[..]),
        hdr: true,
        quality,
        clean_aux: false,
        max_memory_mib: None,
    }
}

#[test]
fn denoises_as_oidn_denoise_does_guided_and_unguided() {
    let Some(lib) = library() else { return };
    let oidn = Oidn::load_from(&lib).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(
        oidn.version(),
        "2.5.1",
        "the version tests/setup/oidn.sh pins"
    );
    let scene = scene(96, 64);
    for (guided, quality) in [
        (true, Quality::High),
        (false, Quality::High),
        (true, Quality::Balanced),
    ] {
        let ours = oidn
            .denoise(&input(&scene, guided, quality))
            .unwrap_or_else(|e| panic!("{e}"));
        let theirs = oidn_denoise_cli(&lib, &scene, guided, quality);
        let diff = max_relative_difference(&ours, &theirs);
        eprintln!("guided {guided}, quality {quality}: max relative difference {diff:e}");
        assert!(
            diff < 1e-4,
            "guided {guided}, quality {quality}: the loaded OIDN and oidnDenoise differ by {diff}"
        );
        // It did denoise: the output is finite and far smoother than the input.
        assert!(ours.iter().flatten().all(|v| v.is_finite()));
        let roughness = |img: &[[f32; 3]]| -> f64 {
            img.windows(2)
                .map(|p| f64::from((p[0][1] - p[1][1]).abs()))
                .sum::<f64>()
        };
        assert!(
            roughness(&ours) < 0.25 * roughness(&scene.color),
            "the output is barely smoother than the input"
        );
    }
}

/// A filter's memory cap reaches OIDN: capped below what an image needs untiled, OIDN denoises in
/// tiles and its peak memory falls. The tiles overlap by OIDN's whole receptive field, so the
/// output is the untiled one, bit for bit. (OIDN 2.5.1 tiles no smaller than 768x768, so it
/// never tiles a smaller image, whatever the cap.) Each denoise runs in a child process of this
/// test binary ([`memory_probe`]), whose peak resident memory is its own.
#[test]
fn a_memory_cap_tiles_with_less_memory_and_the_same_output() {
    let Some(lib) = library() else { return };
    let probe = |cap: &str| -> (u64, String) {
        let out = Command::new(std::env::current_exe().unwrap())
            .args(["--exact", "memory_probe", "--nocapture"])
            .env("SPLATD_OIDN_LIB", &lib)
            .env("SPLATD_OIDN_MEMORY_PROBE", cap)
            .output()
            .unwrap();
        let said = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(
            out.status.success(),
            "{said}{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let line = said
            .lines()
            .find_map(|l| l.strip_prefix("probe: "))
            .unwrap_or_else(|| panic!("the probe said {said}"));
        let (grew, digest) = line.split_once(' ').unwrap();
        (grew.parse().unwrap(), digest.to_owned())
    };
    let (untiled, untiled_digest) = probe("none");
    let (tiled, tiled_digest) = probe("16");
    eprintln!("1024x768 high: OIDN's peak {untiled} bytes untiled, {tiled} capped at 16 MiB");
    // Measured: 431.5 MB untiled, 324.5 MB in two tiles.
    assert!(
        tiled + (64 << 20) < untiled,
        "capped at 16 MiB OIDN peaked at {tiled} bytes, untiled at {untiled}: the cap did not \
         reach it"
    );
    assert_eq!(tiled_digest, untiled_digest, "tiling changed OIDN's output");
}

/// The child of [`a_memory_cap_tiles_with_less_memory_and_the_same_output`]: one `high` denoise
/// of a 1024x768 image at the cap `SPLATD_OIDN_MEMORY_PROBE` names (`none` for no cap); prints
/// how much its peak resident memory grew during the denoise and a digest of the output's bits.
#[test]
fn memory_probe() {
    let Some(cap) = std::env::var_os("SPLATD_OIDN_MEMORY_PROBE") else {
        return;
    };
    let cap = cap.to_str().unwrap().parse::<u32>().ok();
    let oidn = Oidn::load().unwrap_or_else(|e| panic!("{e}"));
    let scene = scene(1024, 768);
    let peak = || -> u64 {
        let status = std::fs::read_to_string("/proc/self/status").unwrap();
        let kib = status
            .lines()
            .find_map(|l| l.strip_prefix("VmHWM:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
            .expect("VmHWM in /proc/self/status");
        kib << 10
    };
    let before = peak();
    let out = oidn
        .denoise(&DenoiseInput {
            max_memory_mib: cap,
            ..input(&scene, true, Quality::High)
        })
        .unwrap_or_else(|e| panic!("{e}"));
    let grew = peak() - before;
    let digest = out.iter().flatten().fold(0xcbf2_9ce4_8422_2325u64, |h, v| {
        (h ^ u64::from(v.to_bits())).wrapping_mul(0x0100_0000_01b3)
    });
    println!("probe: {grew} {digest:016x}");
}

#[test]
fn one_device_serves_threads_alike() {
    let Some(lib) = library() else { return };
    let oidn = Oidn::load_from(&lib).unwrap_or_else(|e| panic!("{e}"));
    let scene = scene(48, 40);
    let alone = oidn.denoise(&input(&scene, true, Quality::Fast)).unwrap();
    let together: Vec<Vec<[f32; 3]>> = std::thread::scope(|s| {
        let runs: Vec<_> = (0..3)
            .map(|_| s.spawn(|| oidn.denoise(&input(&scene, true, Quality::Fast)).unwrap()))
            .collect();
        runs.into_iter().map(|r| r.join().unwrap()).collect()
    });
    for image in together {
        assert!(max_relative_difference(&alone, &image) < 1e-5);
    }
}

#[test]
fn load_uses_splatd_oidn_lib() {
    let Some(lib) = library() else { return };
    // In a child process of this test binary, so no thread here sees the environment change.
    let out = Command::new(std::env::current_exe().unwrap())
        .args(["--exact", "load_probe", "--nocapture"])
        .env("SPLATD_OIDN_LIB", &lib)
        .env("SPLATD_OIDN_LOAD_PROBE", "1")
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{said}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        said.contains(&format!("loaded 2.5.1 from {}", lib.display())),
        "{said}"
    );
}

/// What [`load_uses_splatd_oidn_lib`] runs in its child: `Oidn::load()` as the environment says.
#[test]
fn load_probe() {
    if std::env::var_os("SPLATD_OIDN_LOAD_PROBE").is_none() {
        return;
    }
    let oidn = Oidn::load().unwrap_or_else(|e| panic!("{e}"));
    println!("loaded {} from {}", oidn.version(), oidn.path().display());
}

#[test]
fn mismatched_images_are_refused_before_oidn_sees_them() {
    let Some(lib) = library() else { return };
    let oidn = Oidn::load_from(&lib).unwrap();
    let scene = scene(16, 8);
    let mut bad = input(&scene, true, Quality::Default);
    bad.albedo = Some(&scene.albedo[1..]);
    let err = oidn.denoise(&bad).unwrap_err();
    assert!(
        matches!(err, DenoiseError::InvalidInput(_)) && err.to_string().contains("albedo has 127"),
        "{err}"
    );
    let mut bad = input(&scene, true, Quality::Default);
    bad.albedo = None;
    let err = oidn.denoise(&bad).unwrap_err();
    assert!(
        err.to_string().contains("normal guide needs an albedo"),
        "{err}"
    );
}

#[test]
fn a_missing_library_is_an_error_naming_the_path() {
    let path = Path::new("/nonexistent/oidn/libOpenImageDenoise.so.2");
    let err = Oidn::load_from(path).unwrap_err();
    assert!(matches!(err, DenoiseError::Load { .. }), "{err:?}");
    let message = err.to_string();
    assert!(message.contains(&path.display().to_string()), "{message}");
    assert!(message.contains("SPLATD_OIDN_LIB"), "{message}");
}

#[test]
fn a_library_that_is_not_oidn_is_an_error_naming_the_path() {
    // The C maths library is on every Linux system and has no OIDN function.
    let err = Oidn::load_from(Path::new("libm.so.6")).unwrap_err();
    assert!(
        matches!(
            err,
            DenoiseError::Symbol {
                symbol: "oidnNewDevice",
                ..
            }
        ),
        "{err:?}"
    );
    let message = err.to_string();
    assert!(
        message.contains("libm.so.6") && message.contains("oidnNewDevice"),
        "{message}"
    );
}
