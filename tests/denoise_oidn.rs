//! Denoised finals with the real Open Image Denoise: `splatd serve` processes loading OIDN 2.5.1
//! (`SPLATD_OIDN_LIB`, installed by `tests/setup/oidn.sh`), frames whose passes (written by
//! OpenEXR's Python package, `tests/py/write_denoise_passes.py`) carry albedo and normal AOVs,
//! and `image.exr?denoise=oidn` read back with OpenEXR's Python reader.
//!
//! The `denoised` layer is checked against OIDN run another way: OIDN's own `oidnDenoise`
//! (from the same wheel) on the denoiser input rebuilt from the served layers, written as PFM.
//! The rebuild follows the default design, `paper(kappa=2)+ratio`: the paper's resolve at a
//! fixed `kappa = 2` and the plain mean (both served by `image.exr?variant=paper&kappa=2&
//! kappa_exponent=0`), each denoised by `oidnDenoise`, combined by the ratio rule computed here
//! from its definition. What holds for any design is checked too: finite, energy near the
//! mean's, and far less variance than the input on the flat wall.
//!
//! Without OIDN the tests say so loudly and check nothing, except in CI (`CI=true`), where that
//! fails them; the refusal of a server whose library path is wrong needs no OIDN.

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::common;
use crate::common::{
    parse_metrics, read_exr_attributes_with_python, read_exr_with_python, run_setup, runtime,
    scrape_metrics, Log, Options, Server, ServerProcess,
};
use bytes::Bytes;
use splatd_formats::preview;
use splatd_proto::api::{AovSpec, CreateFrame, Denoise, DenoiseGuides, DenoiseQuality, ImageQuery};
use splatd_proto::{Batch, Client, ClientError, Record, Variant};

const W: u32 = 64;
const H: u32 = 48;
const PASSES: u64 = 16;

/// The OIDN library to start servers with, or `None` (said loudly) outside CI.
fn oidn_library() -> Option<String> {
    if let Some(path) = std::env::var("SPLATD_OIDN_LIB")
        .ok()
        .filter(|p| !p.is_empty())
    {
        return Some(path);
    }
    match run_setup("oidn.sh") {
        Ok(path) => Some(path),
        Err(e) => {
            let why = format!("OIDN IS NOT AVAILABLE (tests/setup/oidn.sh failed: {e})");
            common::skip_unless_ci("denoise_oidn", &why);
            None
        }
    }
}

fn aovs() -> Vec<AovSpec> {
    vec![
        AovSpec::new("ViewLayer.DiffCol", &["R", "G", "B"]),
        AovSpec::new("ViewLayer.Normal", &["X", "Y", "Z"]),
    ]
}

/// A frame that declares Blender's DiffCol and Normal, the guides chosen by name.
fn guided_frame(id: &str) -> CreateFrame {
    CreateFrame {
        aovs: aovs(),
        ..CreateFrame::new(id, W, H)
    }
}

fn write_passes(dir: &Path) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/py/write_denoise_passes.py");
    let out = Command::new("python3")
        .arg(script)
        .arg(dir)
        .args(["--width", &W.to_string(), "--height", &H.to_string()])
        .args(["--passes", &PASSES.to_string()])
        .output()
        .expect("running python3 (tests/run.sh installs its packages)");
    assert!(
        out.status.success(),
        "write_denoise_passes.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Creates `frame` and posts every pass to it.
async fn fill(client: &Client, passes: &Path, frame: &CreateFrame) {
    client.create_frame(frame).await.unwrap();
    for k in 0..PASSES {
        let body = Bytes::from(std::fs::read(passes.join(format!("pass_{k}.exr"))).unwrap());
        let ack = client.post_pass(&frame.id, 1, k, body).await.unwrap();
        assert_eq!(ack.accepted, u64::from(W * H));
    }
}

/// An EXR as OpenEXR's Python package reads it: channels by name, and the header attributes.
struct Exr {
    channels: Vec<(String, Vec<f64>)>,
    attributes: serde_json::Value,
}

impl Exr {
    fn read(dir: &Path, name: &str, bytes: &[u8]) -> Exr {
        let path = dir.join(name);
        std::fs::write(&path, bytes).unwrap();
        let (w, h, channels) = read_exr_with_python(&path);
        assert_eq!((w, h), (W, H));
        Exr {
            channels,
            attributes: read_exr_attributes_with_python(&path),
        }
    }

    fn has(&self, name: &str) -> bool {
        self.channels.iter().any(|(n, _)| n == name)
    }

    fn channel(&self, name: &str) -> &[f64] {
        &self
            .channels
            .iter()
            .find(|(n, _)| n == name)
            .unwrap_or_else(|| panic!("no channel {name}"))
            .1
    }

    /// Layer `prefix` (`""` for the unnamed one) as RGB triples, with channels `c0 c1 c2`.
    fn rgb(&self, prefix: &str, names: [&str; 3]) -> Vec<[f32; 3]> {
        let planes = names.map(|c| self.channel(&format!("{prefix}{c}")).to_vec());
        (0..planes[0].len())
            .map(|i| [0, 1, 2].map(|c| planes[c][i] as f32))
            .collect()
    }

    /// The guide layers `albedo` (`R G B`) and `normal` (`X Y Z`), where named.
    fn guides(&self, albedo: Option<&str>, normal: Option<&str>) -> GuideLayers {
        GuideLayers {
            albedo: albedo.map(|a| self.rgb(&format!("{a}."), ["R", "G", "B"])),
            normal: normal.map(|n| self.rgb(&format!("{n}."), ["X", "Y", "Z"])),
        }
    }

    fn text(&self, name: &str) -> &str {
        self.attributes[name]
            .as_str()
            .unwrap_or_else(|| panic!("no string attribute {name} in {}", self.attributes))
    }
}

/// Writes a little-endian colour PFM (bottom row first).
fn write_pfm(path: &Path, rgb: &[[f32; 3]]) {
    let (w, h) = (W as usize, H as usize);
    let mut bytes = format!("PF\n{w} {h}\n-1.0\n").into_bytes();
    for y in (0..h).rev() {
        for px in &rgb[y * w..(y + 1) * w] {
            for c in px {
                bytes.extend_from_slice(&c.to_le_bytes());
            }
        }
    }
    std::fs::write(path, bytes).unwrap();
}

/// Reads the little-endian colour PFM `oidnDenoise` writes, top row first.
fn read_pfm(path: &Path) -> Vec<[f32; 3]> {
    let bytes = std::fs::read(path).unwrap();
    let header = format!("PF\n{W} {H}\n-1.0\n");
    assert!(
        bytes.starts_with(header.as_bytes()),
        "a {W}x{H} little-endian PFM"
    );
    let floats: Vec<f32> = bytes[header.len()..]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    let (w, h) = (W as usize, H as usize);
    assert_eq!(floats.len(), w * h * 3);
    let mut rgb = vec![[0f32; 3]; w * h];
    for (row, line) in floats.chunks_exact(w * 3).enumerate() {
        for (x, px) in line.chunks_exact(3).enumerate() {
            rgb[(h - 1 - row) * w + x] = [px[0], px[1], px[2]];
        }
    }
    rgb
}

/// An albedo, and a normal beside it, for `oidnDenoise`.
type Guides<'a> = Option<(&'a [[f32; 3]], Option<&'a [[f32; 3]]>)>;

/// Guide layers read from a served image.
struct GuideLayers {
    albedo: Option<Vec<[f32; 3]>>,
    normal: Option<Vec<[f32; 3]>>,
}

impl GuideLayers {
    fn for_oidn(&self) -> Guides<'_> {
        self.albedo.as_deref().map(|a| (a, self.normal.as_deref()))
    }
}

/// OIDN's own command on `color` (and the guides), at `quality`.
fn oidn_denoise(
    lib: &str,
    dir: &Path,
    color: &[[f32; 3]],
    guides: Guides<'_>,
    quality: &str,
) -> Vec<[f32; 3]> {
    let lib = std::fs::canonicalize(lib).unwrap();
    let cli: PathBuf = lib.parent().unwrap().join("../bin/oidnDenoise");
    write_pfm(&dir.join("color.pfm"), color);
    let mut cmd = Command::new(&cli);
    cmd.args(["-d", "cpu", "--affinity", "0", "-q", quality, "--hdr"])
        .arg(dir.join("color.pfm"));
    if let Some((albedo, normal)) = guides {
        write_pfm(&dir.join("albedo.pfm"), albedo);
        cmd.arg("--alb").arg(dir.join("albedo.pfm"));
        if let Some(normal) = normal {
            write_pfm(&dir.join("normal.pfm"), normal);
            cmd.arg("--nrm").arg(dir.join("normal.pfm"));
        }
    }
    cmd.arg("-o").arg(dir.join("out.pfm"));
    let out = cmd
        .output()
        .unwrap_or_else(|e| panic!("{}: {e}", cli.display()));
    assert!(
        out.status.success(),
        "oidnDenoise failed: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    read_pfm(&dir.join("out.pfm"))
}

fn max_relative_difference(a: &[[f32; 3]], b: &[[f32; 3]]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(x, y)| (x - y).abs() / (x.abs().max(y.abs()) + 1e-3))
        .fold(0.0, f32::max)
}

fn luminance_sum(rgb: &[[f32; 3]]) -> f64 {
    rgb.iter()
        .map(|p| 0.2126 * f64::from(p[0]) + 0.7152 * f64::from(p[1]) + 0.0722 * f64::from(p[2]))
        .sum()
}

/// Variance of the green channel over the flat wall (the left half, away from its edges).
fn flat_variance(rgb: &[[f32; 3]]) -> f64 {
    let values: Vec<f64> = (4..H as usize - 4)
        .flat_map(|y| (4..W as usize / 2 - 4).map(move |x| (x, y)))
        .map(|(x, y)| f64::from(rgb[y * W as usize + x][1]))
        .collect();
    let mean = values.iter().sum::<f64>() / values.len() as f64;
    values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / values.len() as f64
}

/// What holds for any denoiser input: the `denoised` layer is finite, keeps most of the mean's
/// energy (the input design may leave out some of what the resolve removes as fireflies: the
/// `paper` input kept 86 % at 8 spp of this scene; OIDN's own part is checked against its
/// input in [`check_against_oidn_denoise`]), and on the flat wall has far less variance than
/// the plain mean.
fn check_denoised_plausibly(exr: &Exr, what: &str) {
    let denoised = exr.rgb("denoised.", ["R", "G", "B"]);
    let mean = exr.rgb("mean.", ["R", "G", "B"]);
    assert!(
        denoised.iter().flatten().all(|v| v.is_finite()),
        "{what}: a non-finite denoised value"
    );
    let energy = luminance_sum(&denoised) / luminance_sum(&mean);
    assert!(
        (0.8..=1.05).contains(&energy),
        "{what}: the denoised final has {energy} of the mean's energy"
    );
    let (before, after) = (flat_variance(&mean), flat_variance(&denoised));
    assert!(
        after < 0.2 * before,
        "{what}: the flat wall's variance went from {before} to {after} only"
    );
    eprintln!(
        "{what}: energy {energy:.4} of the mean's, flat-wall variance {before:.4} -> {after:.5}"
    );
}

/// The `denoised` layer against `oidnDenoise` on the input the test rebuilds: for the design
/// `paper`, the paper's resolve (`variant=paper` of the same frame, served as float32, exact)
/// with the guides served as AOV layers.
#[allow(clippy::too_many_arguments)]
fn check_against_oidn_denoise(
    lib: &str,
    dir: &Path,
    exr: &Exr,
    paper: &Exr,
    albedo: Option<&str>,
    normal: Option<&str>,
    quality: &str,
    what: &str,
) {
    let design = exr.text("splatd:denoiseInput");
    assert_eq!(
        design, "paper(kappa=2)+ratio",
        "{what}: the default input design changed; teach this test to rebuild it"
    );
    assert_eq!(exr.attributes["splatd:denoiseInputImages"], 2);
    let color = paper.rgb("", ["R", "G", "B"]);
    let mean = paper.rgb("mean.", ["R", "G", "B"]);
    let layers = exr.guides(albedo, normal);
    let guides = layers.for_oidn();
    let denoised_paper = oidn_denoise(lib, dir, &color, guides, quality);
    let denoised_mean = oidn_denoise(lib, dir, &mean, guides, quality);
    let theirs = ratio_final(&denoised_paper, &denoised_mean);
    let ours = exr.rgb("denoised.", ["R", "G", "B"]);
    let diff = max_relative_difference(&ours, &theirs);
    eprintln!("{what}: denoised layer vs oidnDenoise: max relative difference {diff:e}");
    assert!(
        diff < 1e-4,
        "{what}: the denoised layer differs from oidnDenoise on the same input by {diff}"
    );
    let kept = luminance_sum(&denoised_paper) / luminance_sum(&color);
    eprintln!("{what}: OIDN kept {kept:.4} of its input's energy");
    assert!(
        (0.97..=1.03).contains(&kept),
        "{what}: OIDN kept {kept} of its input's energy"
    );
}

/// The image whose layers are the default design's inputs: the paper's resolve at a fixed
/// `kappa = 2` (`R`, `G`, `B`) and the plain mean (`mean.*`); for the design `paper`, the
/// frame's own kappa settings would be asked for instead.
fn first_input() -> ImageQuery {
    ImageQuery {
        variant: Some(Variant::Paper),
        kappa: Some(2.0),
        kappa_exponent: Some(0.0),
        ..ImageQuery::default()
    }
}

/// The default design's final from the two denoised images, computed here from its definition
/// (docs/ALGORITHM.md, "The denoiser's input"): the denoised paper times the ratio of the
/// denoised mean's to the denoised paper's Rec. 709 luminance (negative values as 0), each
/// summed over the 5x5 window around the pixel (clipped to the frame), the ratio clamped to
/// [1, 1.5].
fn ratio_final(paper: &[[f32; 3]], mean: &[[f32; 3]]) -> Vec<[f32; 3]> {
    let (w, h) = (W as usize, H as usize);
    let lum = |p: &[f32; 3]| {
        (0.2126 * f64::from(p[0]) + 0.7152 * f64::from(p[1]) + 0.0722 * f64::from(p[2])).max(0.0)
    };
    let window = |img: &[[f32; 3]], x: usize, y: usize| -> f64 {
        let mut sum = 0.0;
        for yy in y.saturating_sub(2)..(y + 3).min(h) {
            for xx in x.saturating_sub(2)..(x + 3).min(w) {
                sum += lum(&img[yy * w + xx]);
            }
        }
        sum
    };
    (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            let kept = window(paper, x, y);
            let gain = if kept > 0.0 {
                (window(mean, x, y) / kept).clamp(1.0, 1.5)
            } else {
                1.0
            };
            paper[i].map(|v| (f64::from(v) * gain) as f32)
        })
        .collect()
}

fn rejected(e: ClientError) -> (u16, String, String) {
    match e {
        ClientError::Rejected { status, body } => (status, body.error, body.message),
        other => panic!("expected a refusal, got {other}"),
    }
}

fn query(denoise: Option<Denoise>) -> ImageQuery {
    ImageQuery {
        denoise,
        ..ImageQuery::default()
    }
}

/// What the tests of denoised passes start from: Blender-named passes written in a temporary
/// directory (which also holds what the test reads back), a server that loads OIDN from the
/// library given, a client of it, a runtime, and two frames for the same passes: guided by
/// name (it declares Blender's DiffCol and Normal) and unguided (no AOVs declared, so the
/// passes' AOV layers are not read).
struct DenoisedPasses {
    dir: tempfile::TempDir,
    passes: PathBuf,
    server: ServerProcess,
    client: Client,
    rt: tokio::runtime::Runtime,
    guided: CreateFrame,
    unguided: CreateFrame,
}

impl DenoisedPasses {
    fn start(lib: &str) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let passes = dir.path().join("passes");
        write_passes(&passes);
        let server = Server::start_with_env(&[], &[("SPLATD_OIDN_LIB", lib)]);
        let client = Client::new(&server.url).unwrap();
        DenoisedPasses {
            dir,
            passes,
            server,
            client,
            rt: runtime(),
            guided: guided_frame("guided"),
            unguided: CreateFrame::new("unguided", W, H),
        }
    }
}

#[test]
fn denoised_finals_guided_unguided_and_by_default() {
    let Some(lib) = oidn_library() else { return };
    let DenoisedPasses {
        dir,
        passes,
        server,
        client,
        rt,
        guided,
        unguided,
    } = DenoisedPasses::start(&lib);
    // Denoised by default, guided by the albedo alone, chosen explicitly.
    let by_default = CreateFrame {
        aovs: aovs(),
        denoise: Denoise::Oidn,
        denoise_guides: Some(DenoiseGuides {
            albedo: Some("ViewLayer.DiffCol".into()),
            normal: None,
        }),
        ..CreateFrame::new("by-default", W, H)
    };
    let (info, images) = rt.block_on(async {
        for frame in [&guided, &unguided, &by_default] {
            fill(&client, &passes, frame).await;
        }
        let info = client.frame_info("guided").await.unwrap();
        let mut images = Vec::new();
        for (frame, q) in [
            ("guided", query(Some(Denoise::Oidn))),
            ("guided", query(None)),
            ("guided", first_input()),
            (
                "guided",
                ImageQuery {
                    denoise_quality: Some(DenoiseQuality::Fast),
                    ..query(Some(Denoise::Oidn))
                },
            ),
            ("unguided", query(Some(Denoise::Oidn))),
            ("unguided", first_input()),
            ("by-default", query(None)),
            ("by-default", query(Some(Denoise::None))),
        ] {
            images.push(client.image(frame, &q).await.unwrap());
        }
        (info, images)
    });
    let d = dir.path();
    let [guided_exr, guided_plain, guided_paper, guided_fast, unguided_exr, unguided_paper, default_exr, default_off] =
        [0, 1, 2, 3, 4, 5, 6, 7].map(|i| Exr::read(d, &format!("image{i}.exr"), &images[i]));

    // The frame shows the guides chosen by name.
    assert_eq!(
        info.denoise_guides,
        DenoiseGuides {
            albedo: Some("ViewLayer.DiffCol".into()),
            normal: Some("ViewLayer.Normal".into()),
        }
    );
    assert_eq!(info.denoise, Denoise::None);

    // Guided: the header says how, and the layer is OIDN's on the rebuilt input.
    for (name, want) in [
        ("splatd:denoiser", "oidn"),
        ("splatd:denoiserVersion", "2.5.1"),
        ("splatd:denoiseQuality", "high"),
        ("splatd:denoiseAlbedo", "ViewLayer.DiffCol"),
        ("splatd:denoiseNormal", "ViewLayer.Normal"),
    ] {
        assert_eq!(guided_exr.text(name), want, "{name}");
    }
    assert!(!guided_exr.text("splatd:denoiseInput").is_empty());
    check_denoised_plausibly(&guided_exr, "guided");
    check_against_oidn_denoise(
        &lib,
        d,
        &guided_exr,
        &guided_paper,
        Some("ViewLayer.DiffCol"),
        Some("ViewLayer.Normal"),
        "high",
        "guided",
    );
    // The other layers are the plain image's, bit for bit, and the plain image has no
    // `denoised` layer nor denoise attributes.
    for (name, values) in &guided_plain.channels {
        assert_eq!(guided_exr.channel(name), &values[..], "{name}");
    }
    assert!(!guided_plain.has("denoised.R"));
    assert!(guided_plain.attributes.get("splatd:denoiser").is_none());

    // Another quality is another denoise, said in the header.
    assert_eq!(guided_fast.text("splatd:denoiseQuality"), "fast");
    check_against_oidn_denoise(
        &lib,
        d,
        &guided_fast,
        &guided_paper,
        Some("ViewLayer.DiffCol"),
        Some("ViewLayer.Normal"),
        "fast",
        "guided, fast",
    );

    // Unguided.
    assert_eq!(unguided_exr.text("splatd:denoiseAlbedo"), "none");
    assert_eq!(unguided_exr.text("splatd:denoiseNormal"), "none");
    check_denoised_plausibly(&unguided_exr, "unguided");
    check_against_oidn_denoise(
        &lib,
        d,
        &unguided_exr,
        &unguided_paper,
        None,
        None,
        "high",
        "unguided",
    );

    // The frame's default: denoised without asking, guided by the albedo it names only; and
    // `denoise=none` turns it off.
    assert!(default_exr.has("denoised.G"));
    assert_eq!(
        default_exr.text("splatd:denoiseAlbedo"),
        "ViewLayer.DiffCol"
    );
    assert_eq!(default_exr.text("splatd:denoiseNormal"), "none");
    check_denoised_plausibly(&default_exr, "by default, albedo only");
    check_against_oidn_denoise(
        &lib,
        d,
        &default_exr,
        &guided_paper,
        Some("ViewLayer.DiffCol"),
        None,
        "high",
        "by default, albedo only",
    );
    assert!(!default_off.has("denoised.G"));
    assert!(default_off.attributes.get("splatd:denoiser").is_none());

    // The preview shows the denoised final too (the same OIDN run on the same input, at the
    // quality `image.exr` has by default), at the reweighted layer's exposure, as every layer.
    let preview = reqwest::blocking::get(format!(
        "{}/v1/frames/guided/preview.png?layer=denoised",
        server.url
    ))
    .unwrap();
    assert_eq!(preview.status(), 200);
    assert_eq!(preview.headers()["content-type"], "image/png");
    let png = preview.bytes().unwrap();
    let mut reader = png::Decoder::new(&png[..]).read_info().unwrap();
    let mut shown = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut shown).unwrap();
    assert_eq!(
        (info.width, info.height, info.color_type),
        (W, H, png::ColorType::Rgb)
    );
    let exposure = preview::auto_exposure(&guided_exr.rgb("", ["R", "G", "B"]));
    let denoised = guided_exr.rgb("denoised.", ["R", "G", "B"]);
    let want: Vec<u8> = preview::tonemap(&denoised, exposure)
        .into_iter()
        .flatten()
        .collect();
    assert!(
        shown == want,
        "the preview is the denoised layer at the reweighted layer's exposure"
    );
}

#[test]
fn guides_that_do_not_fit_are_refused_at_creation() {
    // No OIDN needed: the guides are checked when the frame is created, on any server.
    let server = Server::start(&[]);
    let client = Client::new(&server.url).unwrap();
    let rt = runtime();
    for (guides, want) in [
        (
            DenoiseGuides {
                albedo: Some("albedo".into()),
                normal: None,
            },
            "\"albedo\" is not one of the frame's AOVs",
        ),
        (
            DenoiseGuides {
                albedo: None,
                normal: Some("ViewLayer.Normal".into()),
            },
            "needs an albedo",
        ),
    ] {
        let frame = CreateFrame {
            aovs: aovs(),
            denoise_guides: Some(guides),
            ..CreateFrame::new("f", W, H)
        };
        let (status, code, message) =
            rejected(rt.block_on(client.create_frame(&frame)).unwrap_err());
        assert_eq!(
            (status, code.as_str()),
            (400, "invalid_parameters"),
            "{message}"
        );
        assert!(message.contains(want), "{message}");
    }
}

#[test]
fn a_server_without_a_usable_oidn_refuses_denoising_and_nothing_else() {
    let missing = "/nonexistent/oidn/lib/libOpenImageDenoise.so.2";
    let log = tempfile::NamedTempFile::new().unwrap();
    let server = ServerProcess::launch(&Options {
        env: &[("SPLATD_OIDN_LIB", missing)],
        log: Log::File(log.path()),
        log_level: "info",
        ..Options::new(env!("CARGO_BIN_EXE_splatd"), &[])
    })
    .unwrap_or_else(|e| panic!("{e}"));
    let client = Client::new(&server.url).unwrap();
    let rt = runtime();
    let frame = CreateFrame {
        denoise: Denoise::Oidn,
        ..CreateFrame::new("d", 8, 4)
    };
    rt.block_on(async {
        client.create_frame(&frame).await.unwrap();
        client
            .create_frame(&CreateFrame::new("plain", 8, 4))
            .await
            .unwrap();
        // Asked for, or the frame's default: 501 naming the path and how to give one.
        for (id, q) in [("plain", query(Some(Denoise::Oidn))), ("d", query(None))] {
            let (status, code, message) = rejected(client.image(id, &q).await.unwrap_err());
            assert_eq!(
                (status, code.as_str()),
                (501, "denoiser_unavailable"),
                "{message}"
            );
            assert!(
                message.contains(missing)
                    && message.contains("--oidn-lib")
                    && message.contains("SPLATD_OIDN_LIB"),
                "{message}"
            );
        }
        // Everything else is served as ever.
        client.image("plain", &query(None)).await.unwrap();
        client
            .image("d", &query(Some(Denoise::None)))
            .await
            .unwrap();
    });
    let preview = reqwest::blocking::get(format!(
        "{}/v1/frames/plain/preview.png?layer=denoised",
        server.url
    ))
    .unwrap();
    assert_eq!(preview.status(), 501);
    let body: serde_json::Value = preview.json().unwrap();
    assert_eq!(body["error"], "denoiser_unavailable");
    let said = std::fs::read_to_string(log.path()).unwrap();
    assert!(
        said.contains("Open Image Denoise not loaded") && said.contains(missing),
        "the log says why at start: {said}"
    );
}

/// `splatd_denoised_images_total` by its `memory` label, from a server's `/metrics`.
fn denoised_images(url: &str) -> (f64, f64) {
    let m = parse_metrics(&scrape_metrics(url));
    let count = |memory: &str| {
        m.get(&format!(
            "splatd_denoised_images_total{{memory=\"{memory}\"}}"
        ))
        .copied()
        .unwrap_or(0.0)
    };
    (count("untiled"), count("tiled"))
}

/// OIDN gets the working memory an image needs untiled when the server has it free, and denoises
/// in tiles when capped below that (`--oidn-max-memory-mib`); the final is the same, byte for
/// byte. A 1024x768 frame needs 480 MiB by splatd's estimate, above the 64 MiB floor given
/// here; OIDN 2.5.1 at `fast` takes 228 MB for it untiled and 171 MB in two tiles.
#[test]
fn a_denoise_gets_free_working_memory_and_tiles_only_when_short() {
    let Some(lib) = oidn_library() else { return };
    let (w, h) = (1024u32, 768u32);
    let env = [("SPLATD_OIDN_LIB", lib.as_str())];
    let roomy = Server::start_with_env(&["--oidn-min-memory-mib", "64"], &env);
    let capped = Server::start_with_env(
        &[
            "--oidn-min-memory-mib",
            "64",
            "--oidn-max-memory-mib",
            "100",
        ],
        &env,
    );
    let q = ImageQuery {
        denoise: Some(Denoise::Oidn),
        denoise_quality: Some(DenoiseQuality::Fast),
        ..ImageQuery::default()
    };
    let rt = runtime();
    let finals: Vec<Bytes> = [&roomy, &capped]
        .map(|server| {
            let client = Client::new(&server.url).unwrap();
            rt.block_on(async {
                client
                    .create_frame(&CreateFrame::new("big", w, h))
                    .await
                    .unwrap();
                // Two samples a pixel: a gradient times noise, with a rare firefly.
                let mut rng = 0x2545_f491_4f6c_dd1du64;
                for seq in 0..2 {
                    let records = (0..w * h)
                        .map(|i| {
                            rng ^= rng << 13;
                            rng ^= rng >> 7;
                            rng ^= rng << 17;
                            let u = (rng >> 40) as f32 / (1u64 << 24) as f32;
                            let (x, y) = (i % w, i / w);
                            let base = 0.2 + 0.6 * x as f32 / w as f32;
                            let v = if u > 0.999 { 500.0 } else { base * 2.0 * u };
                            Record::new(x, y, [v, v * 0.8, v * 0.6])
                        })
                        .collect();
                    client
                        .post_batch(&Batch::new("big", 1, seq, records).unwrap())
                        .await
                        .unwrap();
                }
                client.image("big", &q).await.unwrap()
            })
        })
        .into();
    let (untiled, tiled) = denoised_images(&roomy.url);
    assert!(
        untiled > 0.0 && tiled == 0.0,
        "with the working memory free: {untiled} images untiled, {tiled} tiled"
    );
    let (untiled_capped, tiled_capped) = denoised_images(&capped.url);
    assert_eq!(
        (untiled_capped, tiled_capped),
        (0.0, untiled),
        "capped at 100 MiB: every image tiled"
    );
    assert!(
        finals[0] == finals[1],
        "the tiled final differs from the untiled one ({} and {} bytes)",
        finals[0].len(),
        finals[1].len()
    );
}

/// OIDN runs with the frame's kept resolve free: while a denoise of a frame is held just before
/// OIDN (the failpoint `denoise:before_oidn=pause`), samples posted to the frame are answered,
/// and so are its preview, its plain `image.exr` (holding the new samples) and its need map,
/// which all render from the kept resolve. The denoise finishes once let go.
#[test]
fn a_frame_being_denoised_is_served_to_everyone_else() {
    let Some(lib) = oidn_library() else { return };
    let dir = tempfile::tempdir().unwrap();
    let points = dir.path().to_str().unwrap();
    let server = Server::start_with_env(
        &[],
        &[
            ("SPLATD_OIDN_LIB", &lib),
            ("SPLATD_FAILPOINTS", "denoise:before_oidn=pause@1"),
            ("SPLATD_FAILPOINT_DIR", points),
        ],
    );
    let client = Client::new(&server.url).unwrap();
    let rt = runtime();
    let batch = |seq: u64, value: f32| {
        let records = (0..W * H)
            .map(|i| Record::new(i % W, i / W, [value; 3]))
            .collect();
        Batch::new("f", 1, seq, records).unwrap()
    };
    rt.block_on(async {
        client
            .create_frame(&CreateFrame::new("f", W, H))
            .await
            .unwrap();
        client.post_batch(&batch(0, 1.0)).await.unwrap();
    });
    let http = reqwest::blocking::Client::builder()
        .timeout(std::time::Duration::from_secs(20))
        .build()
        .unwrap();
    let url = server.url.clone();
    let denoise = std::thread::spawn(move || {
        reqwest::blocking::Client::builder()
            .timeout(std::time::Duration::from_secs(120))
            .build()
            .unwrap()
            .get(format!("{url}/v1/frames/f/image.exr?denoise=oidn"))
            .send()
            .map(|r| r.status().as_u16())
    });
    let reached = dir.path().join("denoise:before_oidn.reached");
    let mut waited = 0;
    while !reached.exists() {
        assert!(waited < 6000, "the denoise never reached OIDN");
        std::thread::sleep(std::time::Duration::from_millis(10));
        waited += 1;
    }
    // The denoise holds its input; the frame changes and is watched meanwhile.
    rt.block_on(client.post_batch(&batch(1, 3.0))).unwrap();
    for path in ["preview.png", "need"] {
        let response = http
            .get(format!("{}/v1/frames/f/{path}", server.url))
            .send()
            .unwrap_or_else(|e| panic!("{path} while the frame is denoised: {e}"));
        assert_eq!(response.status(), 200, "{path}");
    }
    let plain = rt
        .block_on(client.image("f", &query(Some(Denoise::None))))
        .unwrap();
    let exr = Exr::read(dir.path(), "plain.exr", &plain);
    let mean = exr.channel("mean.G");
    assert!(
        mean.iter().all(|&v| v == 2.0),
        "the plain image holds both batches (mean 2): {:?}",
        &mean[..4]
    );
    std::fs::write(dir.path().join("denoise:before_oidn.release"), b"").unwrap();
    assert_eq!(denoise.join().unwrap().unwrap(), 200);
}

/// A frame whose denoise needs more than the whole working memory is denoised alone, not
/// refused: every image a denoise holds is reserved before it starts. (When the plan's second
/// image was reserved later, the request's own first reservation made it 503 `busy` every time;
/// a 3840x2160 frame does that on a server with the default 2048 MiB.)
#[test]
fn a_denoise_larger_than_the_working_memory_runs_alone() {
    let Some(lib) = oidn_library() else { return };
    let server = Server::start_with_env(&["--work-memory-mib", "1"], &[("SPLATD_OIDN_LIB", &lib)]);
    let client = Client::new(&server.url).unwrap();
    let rt = runtime();
    let image = rt.block_on(async {
        client
            .create_frame(&CreateFrame::new("f", W, H))
            .await
            .unwrap();
        // Eight samples a pixel, all alike: enough for the resolve to keep them all.
        for seq in 0..8 {
            let records = (0..W * H)
                .map(|i| Record::new(i % W, i / W, [1.0, 0.5, 0.25]))
                .collect();
            client
                .post_batch(&Batch::new("f", 1, seq, records).unwrap())
                .await
                .unwrap();
        }
        client.image("f", &query(Some(Denoise::Oidn))).await
    });
    let image = image.unwrap_or_else(|e| panic!("a denoise alone on the server: {e}"));
    let dir = tempfile::tempdir().unwrap();
    let exr = Exr::read(dir.path(), "alone.exr", &image);
    assert_eq!(exr.attributes["splatd:denoiseInputImages"], 2);
    let denoised = exr.rgb("denoised.", ["R", "G", "B"]);
    for (c, want) in [1.0, 0.5, 0.25].into_iter().enumerate() {
        let mean = denoised.iter().map(|p| f64::from(p[c])).sum::<f64>() / denoised.len() as f64;
        assert!(
            (mean / want - 1.0).abs() < 0.05,
            "a flat frame denoises to about itself: channel {c} {mean}, not {want}"
        );
    }
}

/// A farm's first passes: after one pass and after two, guided and unguided, the denoised final
/// keeps the energy of OIDN on the plain mean (what a farm without splatd would ship), and is
/// OIDN's output on the rebuilt input. With one sample a pixel the paper's resolve once took
/// out everything, so a frame's first pass denoised to black (and the quality benchmark's farm
/// table measured two passes 26-52 % dark).
#[test]
fn a_frames_first_passes_denoise_with_their_energy() {
    let Some(lib) = oidn_library() else { return };
    let DenoisedPasses {
        dir,
        passes,
        server: _server,
        client,
        rt,
        guided,
        unguided,
    } = DenoisedPasses::start(&lib);
    let images = rt.block_on(async {
        let mut images = Vec::new();
        for frame in [&guided, &unguided] {
            client.create_frame(frame).await.unwrap();
        }
        for k in 0..2 {
            let body = Bytes::from(std::fs::read(passes.join(format!("pass_{k}.exr"))).unwrap());
            for frame in ["guided", "unguided"] {
                client.post_pass(frame, 1, k, body.clone()).await.unwrap();
                let denoised = client
                    .image(frame, &query(Some(Denoise::Oidn)))
                    .await
                    .unwrap();
                let input = client.image(frame, &first_input()).await.unwrap();
                images.push((format!("{frame}, {} pass(es)", k + 1), denoised, input));
            }
        }
        images
    });
    for (i, (what, denoised, input)) in images.iter().enumerate() {
        let d = dir.path();
        let exr = Exr::read(d, &format!("final{i}.exr"), denoised);
        let paper = Exr::read(d, &format!("input{i}.exr"), input);
        let guided = what.starts_with("guided");
        let (albedo, normal) = if guided {
            (Some("ViewLayer.DiffCol"), Some("ViewLayer.Normal"))
        } else {
            (None, None)
        };
        check_against_oidn_denoise(&lib, d, &exr, &paper, albedo, normal, "high", what);
        // OIDN on the plain mean, as `oidnDenoise` runs it.
        let mean = exr.rgb("mean.", ["R", "G", "B"]);
        let guides = exr.guides(albedo, normal);
        let oidn_mean = oidn_denoise(&lib, d, &mean, guides.for_oidn(), "high");
        let energy =
            luminance_sum(&exr.rgb("denoised.", ["R", "G", "B"])) / luminance_sum(&oidn_mean);
        eprintln!("{what}: the denoised final has {energy:.4} of OIDN(mean)'s energy");
        assert!(
            (0.98..=1.02).contains(&energy),
            "{what}: the denoised final has {energy} of OIDN(mean)'s energy"
        );
    }
}
