//! Resolved frames as OpenEXR.
//!
//! One part, with the layers as channel-name prefixes (`R`, `G`, `B` for the reweighted image,
//! then `mean.R`, `removed.R`, `spp.Y`, and on request `cascade3.R` ...). Every EXR reader
//! understands one part with dotted channel names (OpenEXR's layer convention), which is not
//! true of multi-part files. Samples are 32-bit float; `spp.Y` is exact up to 2^24 samples.
//! Scan lines with ZIP over 16 lines: lossless, compact, read everywhere.

use exr::prelude::*;

use splatd_estimator::Resolved;

/// An extra RGB layer to write beside the resolved ones (for example a raw cascade).
#[derive(Debug, Clone)]
pub struct ExtraLayer {
    /// Layer name, the prefix of its channels.
    pub name: String,
    /// Row-major RGB values.
    pub rgb: Vec<[f32; 3]>,
}

/// The raw cascade layers `cascade0`, `cascade1`, ... from per-cascade means
/// ([`splatd_estimator::FrameState::cascade_means`]), to write beside the resolved layers.
pub fn cascade_layers(means: Vec<Vec<[f32; 3]>>) -> Vec<ExtraLayer> {
    means
        .into_iter()
        .enumerate()
        .map(|(j, rgb)| ExtraLayer {
            name: format!("cascade{j}"),
            rgb,
        })
        .collect()
}

/// Encodes a resolved frame (and any extra layers) as EXR bytes.
///
/// `exr` compresses blocks on a thread pool it starts per call: from async code call this inside
/// `spawn_blocking`.
pub fn encode_exr(resolved: &Resolved, extra: &[ExtraLayer]) -> Result<Vec<u8>> {
    let size = (resolved.width as usize, resolved.height as usize);
    let mut channels: Vec<AnyChannel<FlatSamples>> = Vec::with_capacity(10 + 3 * extra.len());
    push_rgb(&mut channels, "", &resolved.reweighted);
    push_rgb(&mut channels, "mean.", &resolved.mean);
    push_rgb(&mut channels, "removed.", &resolved.removed);
    channels.push(AnyChannel::new(
        "spp.Y",
        FlatSamples::F32(resolved.spp.iter().map(|&n| n as f32).collect()),
    ));
    for layer in extra {
        push_rgb(&mut channels, &format!("{}.", layer.name), &layer.rgb);
    }
    let attributes = LayerAttributes {
        software_name: Some(Text::from("splatd")),
        ..LayerAttributes::default()
    };
    let layer = Layer::new(
        size,
        attributes,
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(SmallVec::from_vec(channels)),
    );
    let mut bytes = Vec::new();
    Image::from_layer(layer)
        .write()
        .to_buffered(std::io::Cursor::new(&mut bytes))?;
    Ok(bytes)
}

fn push_rgb(channels: &mut Vec<AnyChannel<FlatSamples>>, prefix: &str, rgb: &[[f32; 3]]) {
    for (c, name) in ["R", "G", "B"].iter().enumerate() {
        channels.push(AnyChannel::new(
            format!("{prefix}{name}").as_str(),
            FlatSamples::F32(rgb.iter().map(|p| p[c]).collect()),
        ));
    }
}

/// The channels of an EXR read back, by name (for tests and tools).
pub fn decode_exr_channels(bytes: &[u8]) -> Result<Vec<(String, Vec<f32>)>> {
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))?;
    Ok(image
        .layer_data
        .channel_data
        .list
        .into_iter()
        .map(|c| {
            let values = match c.sample_data {
                FlatSamples::F32(v) => v,
                FlatSamples::F16(v) => v.into_iter().map(f16::to_f32).collect(),
                FlatSamples::U32(v) => v.into_iter().map(|x| x as f32).collect(),
            };
            (c.name.to_string(), values)
        })
        .collect())
}
