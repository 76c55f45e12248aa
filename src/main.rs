//! The `splatd` command line.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};

use splatd::core::{CascadeLayout, FrameState, ResolveParams, Variant};
use splatd::image::encode_exr;
use splatd::quality::{energy_bias, rel_mse};
use splatd::synth::FireflyScene;

#[derive(Parser)]
#[command(
    name = "splatd",
    version,
    about = "Firefly-reweighting sample accumulation service"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Runs the estimator on the built-in firefly-heavy scene and writes EXRs.
    Demo {
        /// Output folder.
        #[arg(long, default_value = "out/demo")]
        out: PathBuf,
        /// Image width and height.
        #[arg(long, default_value_t = 256)]
        size: u32,
        /// Samples per pixel.
        #[arg(long, default_value_t = 64)]
        spp: u64,
    },
}

fn main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .init();
    match Cli::parse().command {
        Command::Demo { out, size, spp } => demo(&out, size, spp),
    }
}

fn demo(out: &std::path::Path, size: u32, spp: u64) -> Result<()> {
    let scene = FireflyScene::new(size, size, 2018);
    let layout = CascadeLayout::with_defaults();
    let mut state = FrameState::new(size, size, layout.clone());
    for pass in 0..spp {
        let report = state.splat_all(scene.pass(pass));
        anyhow::ensure!(
            report.rejected() == 0,
            "synthetic stream produced {report:?}"
        );
    }
    let exact: Vec<[f32; 3]> = (0..size)
        .flat_map(|y| (0..size).map(move |x| scene.mean(x, y).map(|v| v as f32)))
        .collect();
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    println!("built-in firefly scene, {size}x{size}, {spp} spp");
    println!("{:<12} {:>10} {:>12}", "estimate", "relMSE", "energy bias");
    for (name, params) in [
        ("mean", ResolveParams::off()),
        ("reweighted", ResolveParams::with_defaults()),
        (
            "shader",
            ResolveParams::new(Variant::Shader, 4.0, 1.0, 0.0).expect("valid parameters"),
        ),
    ] {
        let resolved = state.resolve(&params);
        let image = &resolved.reweighted;
        println!(
            "{name:<12} {:>10.4} {:>+11.2}%",
            rel_mse(image, &exact),
            100.0 * energy_bias(image, &exact, layout.luminance_weights())
        );
        if name != "shader" {
            let path = out.join(format!("{name}.exr"));
            std::fs::write(&path, encode_exr(&resolved, &[])?)
                .with_context(|| format!("writing {}", path.display()))?;
            println!("{:<12} wrote {}", "", path.display());
        }
    }
    Ok(())
}
