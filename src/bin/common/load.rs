//! Synthetic worker load shared by the benchmark binaries (`#[path]`-included, not a binary of its
//! own): batches of records in scan-line runs with a heavy-tailed brightness, as a worker
//! rendering tiles or passes sends them, and whole passes as OpenEXR files.

// Each binary uses a part of this module.
#![allow(dead_code)]

use anyhow::Result;
use splatd_proto::{Batch, Record};
use splatd_scenes::synth::SplitMix64;

/// A heavy-tailed colour, so that every cascade is used.
pub fn heavy_tailed(rng: &mut SplitMix64) -> [f32; 3] {
    let z = (rng.next_f64().powf(-1.0 / 1.5) - 1.0) as f32;
    [z * 0.8, z, z * 0.6]
}

/// `count` batches of `batch` records each for frame `frame`, in scan-line runs over a
/// `width`x`height` frame (wrapping around), with heavy-tailed RGB; batch `i` is sent by worker
/// `i % workers` with sequence number `i`.
pub fn make_batches(
    frame: &str,
    width: u32,
    height: u32,
    batch: usize,
    count: usize,
    workers: usize,
    seed: u64,
) -> Vec<Batch> {
    let mut rng = SplitMix64::new(seed);
    let pixels = width as usize * height as usize;
    let mut at = 0usize;
    (0..count)
        .map(|i| {
            let records = (0..batch)
                .map(|_| {
                    let p = at % pixels;
                    at += 1;
                    Record::new(
                        (p % width as usize) as u32,
                        (p / width as usize) as u32,
                        heavy_tailed(&mut rng),
                    )
                })
                .collect();
            Batch::new(frame, (i % workers.max(1)) as u64, i as u64, records)
                .expect("valid frame id")
        })
        .collect()
}

/// One pass as an OpenEXR file: channels R, G, B as 32-bit floats, compressed with
/// `compression`.
pub fn encode_pass(
    w: usize,
    h: usize,
    pass: &[[f32; 3]],
    compression: exr::compression::Compression,
) -> Result<Vec<u8>> {
    encode_pass_with_aovs(w, h, pass, &[], compression)
}

/// [`encode_pass`] with AOV channels beside the beauty: each a full name (`albedo.R`) and its
/// values, one per pixel, row-major.
pub fn encode_pass_with_aovs(
    w: usize,
    h: usize,
    pass: &[[f32; 3]],
    aovs: &[(String, Vec<f32>)],
    compression: exr::compression::Compression,
) -> Result<Vec<u8>> {
    use exr::prelude::*;
    let channel = |name: &str, c: usize| {
        AnyChannel::new(
            name,
            FlatSamples::F32(pass.iter().map(|rgb| rgb[c]).collect()),
        )
    };
    let encoding = Encoding {
        compression,
        ..Encoding::UNCOMPRESSED
    };
    let mut channels = vec![channel("R", 0), channel("G", 1), channel("B", 2)];
    channels
        .extend(aovs.iter().map(|(name, values)| {
            AnyChannel::new(name.as_str(), FlatSamples::F32(values.clone()))
        }));
    let layer = Layer::new(
        (w, h),
        LayerAttributes::default(),
        encoding,
        AnyChannels::sort(SmallVec::from_vec(channels)),
    );
    let mut bytes = Vec::new();
    Image::from_layer(layer)
        .write()
        .to_buffered(std::io::Cursor::new(&mut bytes))?;
    Ok(bytes)
}

/// The machine's 1-, 5- and 15-minute load averages as `/proc/loadavg` gives them ("" where it
/// cannot be read), for the load figure every benchmark line carries.
pub fn load_averages() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}
