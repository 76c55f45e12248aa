//! Resolved frames as OpenEXR.
//!
//! One part, with the layers as channel-name prefixes (`R`, `G`, `B` for the reweighted image,
//! then `mean.R`, `removed.R`, `spp.Y`, and on request `cascade3.R` ...). Every EXR reader
//! understands one part with dotted channel names (OpenEXR's layer convention), which is not
//! true of multi-part files. Samples are 32-bit float; `spp.Y` is exact up to 2^24 samples.
//! Scan lines with ZIP over 16 lines: lossless, compact, read everywhere (deflated at a fast
//! level on every core, see the `zip` module).
//!
//! The header says how the image was made ([`Provenance`]): the standard `software` attribute
//! (`splatd 0.1.0`), then `splatd:` attributes for the estimator and its parameters and the
//! sample counts, all deterministic (no time stamps), so the same state always gives the same
//! bytes:
//!
//! | attribute | type | value |
//! |-----------|------|-------|
//! | `software` | string | `splatd <version>` (of the `splatd-server` crate) |
//! | `splatd:estimator` | string | the variant: `paper`, `shader` or `off` |
//! | `splatd:kappa`, `splatd:kappaMin`, `splatd:kappaExponent` | double | its parameters |
//! | `splatd:cascadeBase`, `splatd:cascadeLowestScale` | double | the cascade layout |
//! | `splatd:cascades` | int | number of cascades |
//! | `splatd:luminance` | v3f | the luminance weights of R, G, B |
//! | `splatd:samples` | double | samples in the image (exact below 2^53) |
//! | `splatd:sppMin`, `splatd:sppMean`, `splatd:sppMax` | double | samples per pixel |
//!
//! An image with the `denoised` layer adds how it was made (see the server's denoise module):
//!
//! | attribute | type | value |
//! |-----------|------|-------|
//! | `splatd:denoiser`, `splatd:denoiserVersion` | string | `oidn`, OIDN's version (`2.5.1`) |
//! | `splatd:denoiseQuality` | string | OIDN's quality mode: `high`, `balanced`, `fast`, `default` |
//! | `splatd:denoiseInput` | string | the denoiser input's design (`DenoisePlan::name`) |
//! | `splatd:denoiseInputImages` | int | how many images OIDN denoised for it |
//! | `splatd:denoiseAlbedo`, `splatd:denoiseNormal` | string | the AOVs that guided it, or `none` |

use exr::prelude::*;

mod zip;

use splatd_estimator::{CascadeLayout, ResolveParams, Resolved};
use splatd_proto::api::Variant;

/// What an image was made with, written into its header.
#[derive(Debug, Clone, Copy)]
pub struct Provenance<'a> {
    /// The frame's cascade layout.
    pub layout: &'a CascadeLayout,
    /// The resolve parameters the image was resolved with.
    pub params: &'a ResolveParams,
}

/// A header attribute's value, in the OpenEXR types the provenance uses.
#[derive(Debug, Clone, PartialEq)]
pub enum HeaderValue {
    /// `string`
    Text(String),
    /// `double`
    Double(f64),
    /// `int`
    Int(i32),
    /// `v3f`
    V3f([f32; 3]),
}

impl HeaderValue {
    /// The OpenEXR type name and the value's bytes (little-endian).
    fn encode(&self) -> (&'static str, Vec<u8>) {
        match self {
            HeaderValue::Text(s) => ("string", s.as_bytes().to_vec()),
            HeaderValue::Double(v) => ("double", v.to_le_bytes().to_vec()),
            HeaderValue::Int(v) => ("int", v.to_le_bytes().to_vec()),
            HeaderValue::V3f(v) => ("v3f", v.iter().flat_map(|c| c.to_le_bytes()).collect()),
        }
    }
}

impl Provenance<'_> {
    /// The header attributes (see the module docs): `software`, then the `splatd:` ones by name.
    pub fn attributes(&self, resolved: &Resolved) -> Vec<(&'static str, HeaderValue)> {
        let (mut min, mut max, mut samples) = (u64::MAX, 0u64, 0u128);
        for &n in &resolved.spp {
            min = min.min(n);
            max = max.max(n);
            samples += u128::from(n);
        }
        let pixels = resolved.spp.len();
        let mean = if pixels == 0 {
            min = 0;
            0.0
        } else {
            samples as f64 / pixels as f64
        };
        let variant = Variant::from_estimator(self.params.variant());
        let cascades = i32::try_from(self.layout.cascades()).unwrap_or(i32::MAX);
        use HeaderValue as V;
        vec![
            (
                "software",
                V::Text(format!("splatd {}", env!("CARGO_PKG_VERSION"))),
            ),
            ("splatd:cascadeBase", V::Double(self.layout.base())),
            (
                "splatd:cascadeLowestScale",
                V::Double(self.layout.lowest_scale()),
            ),
            ("splatd:cascades", V::Int(cascades)),
            ("splatd:estimator", V::Text(variant.as_str().to_owned())),
            ("splatd:kappa", V::Double(self.params.kappa())),
            (
                "splatd:kappaExponent",
                V::Double(self.params.kappa_exponent()),
            ),
            ("splatd:kappaMin", V::Double(self.params.kappa_min())),
            (
                "splatd:luminance",
                V::V3f(self.layout.luminance_weights().map(|w| w as f32)),
            ),
            ("splatd:samples", V::Double(samples as f64)),
            ("splatd:sppMax", V::Double(max as f64)),
            ("splatd:sppMean", V::Double(mean)),
            ("splatd:sppMin", V::Double(min as f64)),
        ]
    }
}

/// Longest name (attribute, type or channel) an EXR without the long-names flag may have.
const SHORT_NAME_BYTES: usize = 31;
/// The long-names flag's bit in the version field (bytes 4 to 7 of the file, little-endian).
const LONG_NAMES_BIT: u32 = 10;

/// Adds attributes to the header of a single-part EXR written by `exr`, keeping their order, and
/// sets the long-names flag when a channel name needs it.
///
/// `exr` keeps extra attributes in a `HashMap` and writes them in its (per-process random)
/// order, which would make the same image different bytes from one resolve to the next; so they
/// are inserted here, in the given order, at the end of the header, and the offset table that
/// follows the header (absolute positions of the pixel blocks) is moved by as many bytes.
fn add_attributes(bytes: Vec<u8>, attributes: &[(&str, HeaderValue)]) -> Result<Vec<u8>> {
    let invalid = |what: &str| Error::Invalid(format!("splatd's own EXR: {what}").into());
    let meta = exr::meta::MetaData::read_from_buffered(std::io::Cursor::new(&bytes), false)?;
    let header = meta.headers.first().ok_or_else(|| invalid("no header"))?;
    let chunks = header.chunk_count;
    // OpenEXR's rule: the version field's long-names flag (bit 10) is set when a name is longer
    // than 31 bytes. `exr` sets it for long attribute names only, not for channel names.
    let long_names = header
        .channels
        .list
        .iter()
        .any(|c| c.name.as_slice().len() > SHORT_NAME_BYTES)
        || attributes
            .iter()
            .any(|(name, _)| name.len() > SHORT_NAME_BYTES);
    let end = zip::scan_header(&bytes)?.end;
    let at = end + 1; // the offset table
    let mut added = Vec::new();
    for (name, value) in attributes {
        let (kind, data) = value.encode();
        added.extend_from_slice(name.as_bytes());
        added.push(0);
        added.extend_from_slice(kind.as_bytes());
        added.push(0);
        let size = i32::try_from(data.len()).map_err(|_| invalid("attribute too large"))?;
        added.extend_from_slice(&size.to_le_bytes());
        added.extend_from_slice(&data);
    }
    let table = at..at + 8 * chunks;
    if bytes.len() < table.end {
        return Err(invalid("offset table cut short"));
    }
    let shift = added.len() as u64;
    // The attributes, the header's end and the moved offset table replace the header's end
    // and the table in place: the pixel blocks move up in the same buffer (which
    // `compress_scan_lines` leaves room for), not into a fresh copy of the file.
    let mut head = Vec::with_capacity(added.len() + 1 + 8 * chunks);
    head.extend_from_slice(&added);
    head.push(0);
    for offset in bytes[table.clone()].chunks_exact(8) {
        let offset = u64::from_le_bytes(offset.try_into().expect("8 bytes"));
        head.extend_from_slice(&(offset + shift).to_le_bytes());
    }
    let mut bytes = bytes;
    if long_names {
        bytes[5] |= 1 << (LONG_NAMES_BIT - 8);
    }
    bytes.splice(end..table.end, head);
    Ok(bytes)
}

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

/// The AOV channels of `image.exr`: `name.channel` and the per-pixel means, in declaration
/// order, from a whole frame's AOV sums.
pub fn aov_planes(
    specs: &[splatd_proto::api::AovSpec],
    sums: &splatd_estimator::AovSums,
) -> Vec<(String, Vec<f32>)> {
    let names = specs
        .iter()
        .flat_map(|a| a.channels.iter().map(move |c| format!("{}.{c}", a.name)));
    names.zip(sums.means()).collect()
}

/// Encodes a resolved frame (and any extra layers and AOV channels, see [`aov_planes`]) as EXR
/// bytes, with its provenance in the header.
///
/// `exr` compresses blocks on a thread pool it starts per call: from async code call this inside
/// `spawn_blocking`.
pub fn encode_exr(
    resolved: &Resolved,
    extra: &[ExtraLayer],
    aovs: &[(String, Vec<f32>)],
    provenance: &Provenance<'_>,
) -> Result<Vec<u8>> {
    encode_exr_with(resolved, extra, aovs, provenance, Vec::new())
}

/// [`encode_exr`] with more header attributes (`splatd:` names; for example how the `denoised`
/// layer was made, the server's `DenoiseRun::attributes`), written among the provenance's
/// in order of name.
pub fn encode_exr_with(
    resolved: &Resolved,
    extra: &[ExtraLayer],
    aovs: &[(String, Vec<f32>)],
    provenance: &Provenance<'_>,
    more_attributes: Vec<(&'static str, HeaderValue)>,
) -> Result<Vec<u8>> {
    let mut scratch = ExrScratch::default();
    encode_exr_in(
        resolved,
        extra,
        aovs,
        provenance,
        more_attributes,
        &mut scratch,
    )
}

/// [`encode_exr_with`] in the buffers of `scratch`, which keeps them for the next image: the
/// same bytes.
pub fn encode_exr_in(
    resolved: &Resolved,
    extra: &[ExtraLayer],
    aovs: &[(String, Vec<f32>)],
    provenance: &Provenance<'_>,
    more_attributes: Vec<(&'static str, HeaderValue)>,
    scratch: &mut ExrScratch,
) -> Result<Vec<u8>> {
    let size = (resolved.width as usize, resolved.height as usize);
    let mut channels: Vec<AnyChannel<FlatSamples>> = Vec::with_capacity(10 + 3 * extra.len());
    push_rgb(&mut channels, scratch, "", &resolved.reweighted);
    push_rgb(&mut channels, scratch, "mean.", &resolved.mean);
    push_rgb(&mut channels, scratch, "removed.", &resolved.removed);
    let mut spp = scratch.plane(resolved.spp.len());
    spp.extend(resolved.spp.iter().map(|&n| n as f32));
    channels.push(AnyChannel::new("spp.Y", FlatSamples::F32(spp)));
    for layer in extra {
        push_rgb(
            &mut channels,
            scratch,
            &format!("{}.", layer.name),
            &layer.rgb,
        );
    }
    for (name, plane) in aovs {
        // A frame's AOV names were checked at its creation; a state read offline was not, and
        // `exr` would panic on a character above U+00FF and garble a NUL.
        crate::names::check_exr_name(name)
            .map_err(|rule| Error::Invalid(format!("AOV channel {name:?}: {rule}").into()))?;
        let mut copy = scratch.plane(plane.len());
        copy.extend_from_slice(plane);
        channels.push(AnyChannel::new(name.as_str(), FlatSamples::F32(copy)));
    }
    let bytes = write_one_part_in(size, LayerAttributes::default(), channels, scratch)?;
    let mut attributes = provenance.attributes(resolved);
    attributes.extend(more_attributes);
    attributes.sort_by_key(|(name, _)| *name);
    add_attributes(bytes, &attributes)
}

/// The buffers an image's encoding reuses ([`encode_exr_in`], [`write_one_part_in`]): its
/// channels' planes and the uncompressed file, 160 MB at 1080p, which fresh cost a page fault
/// per 4 KiB on every image (see [`crate::scratch`]).
#[derive(Debug, Default)]
pub struct ExrScratch {
    planes: Vec<Vec<f32>>,
    uncompressed: Vec<u8>,
}

impl ExrScratch {
    /// An empty plane with room for `n` values, from a spare one when there is one.
    fn plane(&mut self, n: usize) -> Vec<f32> {
        let mut plane = self.planes.pop().unwrap_or_default();
        plane.clear();
        plane.reserve_exact(n);
        plane
    }
}

impl crate::scratch::Reusable for ExrScratch {
    fn bytes(&self) -> usize {
        let planes: usize = self.planes.iter().map(|p| p.capacity() * 4).sum();
        planes + self.uncompressed.capacity()
    }
}

/// One part of `size` pixels holding `channels`, in the layout of the module docs (scan lines,
/// ZIP over 16 lines, deflated on every core: see the `zip` module). Like [`encode_exr`], call it
/// off the async threads.
pub fn write_one_part(
    size: (usize, usize),
    attributes: LayerAttributes,
    channels: Vec<AnyChannel<FlatSamples>>,
) -> Result<Vec<u8>> {
    write_one_part_in(size, attributes, channels, &mut ExrScratch::default())
}

/// [`write_one_part`] with the uncompressed file in `scratch`, which also takes back the
/// channels' `f32` planes once they are written.
pub fn write_one_part_in(
    size: (usize, usize),
    attributes: LayerAttributes,
    channels: Vec<AnyChannel<FlatSamples>>,
    scratch: &mut ExrScratch,
) -> Result<Vec<u8>> {
    let first_y = attributes.layer_position.y();
    let encoding = Encoding {
        compression: Compression::Uncompressed,
        blocks: Blocks::ScanLines,
        line_order: LineOrder::Increasing,
    };
    let layer = Layer::new(
        size,
        attributes,
        encoding,
        AnyChannels::sort(SmallVec::from_vec(channels)),
    );
    // Room for the whole file from the start: grown by doubling, the buffer of a 1080p image
    // with ten channels was copied into fresh pages four times over, and faulting those in
    // took a third of an `image.exr`'s time. (A header larger than the room only costs a copy.)
    let sample_bytes: usize = layer
        .channel_data
        .list
        .iter()
        .map(|c| match c.sample_data {
            FlatSamples::F16(_) => 2,
            FlatSamples::F32(_) | FlatSamples::U32(_) => 4,
        })
        .sum();
    let bytes = &mut scratch.uncompressed;
    bytes.clear();
    bytes.reserve(size.0 * size.1 * sample_bytes + 16 * size.1 + (1 << 16));
    let image = Image::from_layer(layer);
    image
        .write()
        .non_parallel()
        .to_buffered(std::io::Cursor::new(&mut *bytes))?;
    for channel in image.layer_data.channel_data.list {
        if let FlatSamples::F32(plane) = channel.sample_data {
            scratch.planes.push(plane);
        }
    }
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    zip::compress_scan_lines(&scratch.uncompressed, first_y, size.1, threads)
}

fn push_rgb(
    channels: &mut Vec<AnyChannel<FlatSamples>>,
    scratch: &mut ExrScratch,
    prefix: &str,
    rgb: &[[f32; 3]],
) {
    for (c, name) in ["R", "G", "B"].iter().enumerate() {
        let mut plane = scratch.plane(rgb.len());
        plane.extend(rgb.iter().map(|p| p[c]));
        channels.push(AnyChannel::new(
            format!("{prefix}{name}").as_str(),
            FlatSamples::F32(plane),
        ));
    }
}

/// The first layer of an EXR, every channel and attribute, as `exr` reads it.
fn read_first_layer(bytes: &[u8]) -> Result<Image<Layer<AnyChannels<FlatSamples>>>> {
    read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))
}

/// The channels of an EXR read back, by name (for tests and tools).
pub fn decode_exr_channels(bytes: &[u8]) -> Result<Vec<(String, Vec<f32>)>> {
    let image = read_first_layer(bytes)?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use splatd_estimator::FrameState;

    /// An image encoded in a scratch is the same bytes as one encoded fresh, the second time in
    /// the same memory: every plane and the uncompressed file are the ones the first left.
    #[test]
    fn a_scratch_encodes_the_same_bytes_in_the_same_memory() {
        let layout = CascadeLayout::with_defaults();
        let mut state = FrameState::new(33, 20, layout.clone());
        for i in 0..33 * 20 * 3 {
            let v = (i * 7919 % 1000) as f32 * 0.01;
            state.splat(i % 33, i / 33 % 20, [v, 1.0, v * v]).unwrap();
        }
        let params = ResolveParams::with_defaults();
        let resolved = state.resolve(&params);
        let provenance = Provenance {
            layout: &layout,
            params: &params,
        };
        let extra = [ExtraLayer {
            name: "denoised".into(),
            rgb: resolved.mean.clone(),
        }];
        let aovs = vec![("albedo.R".to_owned(), vec![0.5f32; 33 * 20])];
        let encode = |scratch: &mut ExrScratch| {
            encode_exr_in(&resolved, &extra, &aovs, &provenance, Vec::new(), scratch).unwrap()
        };
        let fresh = encode_exr_with(&resolved, &extra, &aovs, &provenance, Vec::new()).unwrap();
        let mut scratch = ExrScratch::default();
        assert!(encode(&mut scratch) == fresh);
        let memory = |s: &ExrScratch| {
            let mut planes: Vec<*const f32> = s.planes.iter().map(|p| p.as_ptr()).collect();
            planes.sort();
            (planes, s.uncompressed.as_ptr())
        };
        let kept = memory(&scratch);
        assert_eq!(kept.0.len(), 14, "10 channels, 3 of the extra layer, 1 AOV");
        assert!(encode(&mut scratch) == fresh);
        assert_eq!(memory(&scratch), kept);
    }

    /// The attributes inserted after `exr` wrote the file are read back by `exr` (a reader that
    /// follows the moved offset table), with the pixels unchanged, and the bytes are the same
    /// from one encode to the next.
    #[test]
    fn provenance_is_read_back_and_pixels_are_unchanged() {
        let layout = CascadeLayout::with_defaults();
        let mut state = FrameState::new(7, 37, layout.clone());
        for y in 0..37 {
            for x in 0..7 {
                let v = (x * 37 + y) as f32 * 0.25;
                state.splat(x, y, [v, v * 2.0, 1.0]).unwrap();
                if (x + y) % 3 == 0 {
                    state.splat(x, y, [v * 100.0, 0.0, 0.5]).unwrap();
                }
            }
        }
        let params = ResolveParams::with_defaults();
        let resolved = state.resolve(&params);
        let provenance = Provenance {
            layout: &layout,
            params: &params,
        };
        let bytes = encode_exr(&resolved, &[], &[], &provenance).unwrap();
        assert!(bytes == encode_exr(&resolved, &[], &[], &provenance).unwrap());

        let image = read_first_layer(&bytes).unwrap();
        let attributes = &image.layer_data.attributes;
        let version = format!("splatd {}", env!("CARGO_PKG_VERSION"));
        assert_eq!(attributes.software_name, Some(Text::from(version.as_str())));
        let other = |name: &str| {
            attributes
                .other
                .get(&Text::from(name))
                .or_else(|| image.attributes.other.get(&Text::from(name)))
                .unwrap_or_else(|| panic!("no attribute {name}"))
                .clone()
        };
        use exr::meta::attribute::AttributeValue as A;
        let pixels = 7.0 * 37.0;
        let samples: u64 = resolved.spp.iter().sum();
        let variant = Variant::from_estimator(params.variant()).as_str();
        assert_eq!(other("splatd:estimator"), A::Text(Text::from(variant)));
        assert_eq!(other("splatd:kappa"), A::F64(params.kappa()));
        assert_eq!(other("splatd:cascades"), A::I32(layout.cascades() as i32));
        assert_eq!(other("splatd:samples"), A::F64(samples as f64));
        assert_eq!(other("splatd:sppMin"), A::F64(1.0));
        assert_eq!(other("splatd:sppMax"), A::F64(2.0));
        assert_eq!(other("splatd:sppMean"), A::F64(samples as f64 / pixels));
        let [r, g, b] = layout.luminance_weights().map(|w| w as f32);
        assert_eq!(other("splatd:luminance"), A::FloatVec3((r, g, b)));

        let channels = decode_exr_channels(&bytes).unwrap();
        let mean_g = channels.iter().find(|(n, _)| n == "mean.G").unwrap();
        let want: Vec<f32> = resolved.mean.iter().map(|p| p[1]).collect();
        assert_eq!(mean_g.1, want);
        let spp = channels.iter().find(|(n, _)| n == "spp.Y").unwrap();
        assert_eq!(
            spp.1,
            resolved.spp.iter().map(|&n| n as f32).collect::<Vec<_>>()
        );
    }
}
