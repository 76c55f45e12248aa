//! Sample passes as OpenEXR files, for renderers that cannot stream samples.
//!
//! Cycles, Arnold, Mitsuba and pbrt write images, not sample streams. Rendered with one sample
//! per pixel and a different seed each time, every image they write is one *pass*: each pixel
//! of a pass is **one** Monte Carlo sample of that pixel. [`decode_pass`] reads such a file into
//! one RGB value per pixel (and the values of its AOVs), which the server adds to a frame as
//! the batch of `width * height` samples it is (its records, [`Pass::records`], are what a
//! streaming worker would have sent, and what the pass's digest is computed over).
//!
//! # Which channels are the beauty
//!
//! A file's *layers* are its channels grouped by name: a channel `A.B.R` belongs to layer `A.B`
//! (its name up to the last dot), `R` to the unnamed layer. In a multi-part file the part's
//! name is put in front (`beauty` part, channel `R`: layer `beauty`), unless the channel
//! names already start with it. The beauty is the layer named by the caller (`?layer=` on
//! `POST /v1/frames/{id}/passes`, `--layer` on `splatd post`), or else the first of these that
//! exists, among layers with channels `R`, `G` and `B`:
//!
//! 1. the unnamed layer (channels `R`, `G`, `B`: single-layer files of every renderer);
//! 2. a layer `<view layer>.Combined` (Blender/Cycles' `OPEN_EXR_MULTILAYER`,
//!    `ViewLayer.Combined.R`);
//! 3. a layer named `beauty`, `rgba` or `Combined`, in any case (a part or a channel prefix);
//! 4. the only layer with `R`, `G` and `B`.
//!
//! When a step finds two layers (two view layers, say), or step 4 finds several, nothing is
//! guessed: the pass is refused naming the candidates, and the caller names the layer. A file
//! with no `R`, `G`, `B` layer at all is refused naming every layer it has.
//!
//! Only the beauty's `R`, `G` and `B` are read, as 32-bit floats whatever their stored type
//! (`f16`, `f32` or `u32`), from scanline or tiled parts with any compression the `exr` crate
//! reads: none, RLE, ZIPS, ZIP, PIZ, PXR24, B44, B44A, DWAA, DWAB (not OpenEXR 3.3's HTJ2K and
//! ZSTD, refused as [`PassError::Exr`] "unknown compression method"); of a mip- or rip-mapped
//! part, the full-resolution level. Alpha and other channels are not decoded, except the
//! frame's AOVs ([`decode_pass_with_aovs`]: the channels of the named layers, in any part of the
//! beauty's size); parts holding neither are not decompressed. The pass must cover exactly its
//! display window: a cropped (border) render or an overscan would put its pixels at the wrong
//! place in the frame, so it is refused rather than guessed at.
//!
//! What is **not** done: values are not checked. Negative, NaN and infinite samples pass through
//! unchanged; the server rejects and counts them with the same checks it applies to streamed
//! samples ([`splatd_estimator::check_sample`]), so a pass and a batch are treated identically.
//!
//! Decoding is CPU work (`exr` decompresses blocks on a thread pool it starts per call): from
//! async code call [`decode_pass`] inside `spawn_blocking`.

use std::io::Cursor;

use exr::block::reader::ChunksReader;
use exr::block::UncompressedBlock;
use exr::meta::attribute::{IntegerBounds, SampleType};
use exr::meta::header::Header;
use exr::prelude::{f16, Vec2};
use splatd_proto::api::AovSpec;
use splatd_proto::Record;

/// The four bytes every OpenEXR file starts with.
const EXR_MAGIC: [u8; 4] = [0x76, 0x2f, 0x31, 0x01];

/// The largest pass [`decode_pass`] accepts, in pixels: 2^25, a little more than 8K UHD
/// (7680 x 4320).
///
/// The limit is checked against the header *before* any pixel buffer is allocated: an EXR header
/// of a few bytes can declare a gigapixel image, and its pixel buffers would be allocated in
/// full before the (missing) pixel data is found to be short.
pub const MAX_PASS_PIXELS: u64 = 1 << 25;

/// The layer names step 3 of the automatic choice looks for (compared ignoring ASCII case).
pub const BEAUTY_NAMES: [&str; 3] = ["beauty", "rgba", "Combined"];

/// One pass: one sample per pixel, decoded from an EXR.
#[derive(Debug, Clone, PartialEq)]
pub struct Pass {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// The layer the samples were read from (empty: the unnamed layer, channels `R`, `G`, `B`).
    pub layer: String,
    /// Row-major RGB samples, top row first, `width * height` of them. Not checked: negative,
    /// NaN and infinite values are kept (see the module docs).
    pub rgb: Vec<[f32; 3]>,
    /// The values of the AOVs asked for, when the pass carries them: pixel by pixel (row-major),
    /// each pixel's channels in the order asked for. `None` when the pass carries none of them.
    /// Not checked either.
    pub aovs: Option<Vec<f32>>,
}

/// One layer of an EXR: the channels of one part that share a name prefix.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LayerInfo {
    /// The layer's name (see the module docs); empty for unprefixed channels of an unnamed part.
    pub name: String,
    /// The part (header) it is in.
    pub part: usize,
    /// The channel-name prefix within the part, without its trailing dot (may be empty).
    pub prefix: String,
    /// The channels' names without the prefix (`R`, `G`, `B`, `A`, `Z` ...), in file order.
    pub channels: Vec<String>,
    /// Whether it can be a beauty: `R`, `G` and `B` present, flat (not deep) data.
    pub rgb: bool,
}

impl std::fmt::Display for LayerInfo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let channels = if self.channels.is_empty() {
            "no channels".to_string()
        } else {
            self.channels.join(", ")
        };
        if self.name.is_empty() {
            write!(f, "unnamed ({channels})")
        } else {
            write!(f, "{:?} ({channels})", self.name)
        }
    }
}

/// Why a pass could not be read or used.
#[derive(Debug, thiserror::Error)]
pub enum PassError {
    /// The bytes do not start with the OpenEXR magic number.
    #[error(
        "not an OpenEXR file: it starts with {found}, not the OpenEXR magic number 76 2f 31 01"
    )]
    NotExr {
        /// The first bytes found, in hex.
        found: String,
    },
    /// The file looks like an EXR but `exr` could not read it (truncated, corrupt, deep data,
    /// subsampled channels ...).
    #[error("could not read the OpenEXR pass: {0}")]
    Exr(#[from] exr::error::Error),
    /// No layer has all of the channels `R`, `G` and `B`.
    #[error("the EXR has no layer with channels R, G and B; layers found: {}", list(.layers))]
    NoRgbLayer {
        /// Every layer of the file, in file order.
        layers: Vec<LayerInfo>,
    },
    /// Several layers could be the beauty, and none was named.
    #[error(
        "the EXR has several layers that could be the beauty ({}); name the one to use \
         (`layer` query parameter, `splatd post --layer`); layers found: {}",
        names(.candidates), list(.layers)
    )]
    Ambiguous {
        /// The layers found by the first step of the automatic choice that found any.
        candidates: Vec<String>,
        /// Every layer of the file, in file order.
        layers: Vec<LayerInfo>,
    },
    /// The layer the caller named is not in the file.
    #[error("the EXR has no layer {asked:?}; layers found: {}", list(.layers))]
    UnknownLayer {
        /// The name asked for.
        asked: String,
        /// Every layer of the file, in file order.
        layers: Vec<LayerInfo>,
    },
    /// The layer the caller named has no `R`, `G` and `B` (or is deep data).
    #[error("layer {} cannot be the beauty: it needs flat channels R, G and B", .layer)]
    NotRgb {
        /// The layer named.
        layer: LayerInfo,
    },
    /// A channel of the beauty's part is subsampled (`exr` cannot lay out such blocks).
    #[error("channel {channel:?} is subsampled ({x}x{y}); subsampled passes are not supported")]
    Subsampled {
        /// The channel's full name.
        channel: String,
        /// Horizontal sampling.
        x: usize,
        /// Vertical sampling.
        y: usize,
    },
    /// The RGB layer has no pixels.
    #[error("the pass is empty ({width}x{height})")]
    Empty {
        /// Width of the layer.
        width: u64,
        /// Height of the layer.
        height: u64,
    },
    /// The RGB layer has more pixels than allowed.
    #[error("the pass is {width}x{height}, more than the {max_pixels} pixels allowed")]
    TooLarge {
        /// Width of the layer.
        width: u64,
        /// Height of the layer.
        height: u64,
        /// The limit it broke.
        max_pixels: u64,
    },
    /// The pixels do not cover exactly the display window (a cropped or overscanned render).
    #[error(
        "the pass's data window {} is not its display window {}: cropped and overscanned \
         passes are not supported (render the full frame)",
        show_window(.data), show_window(.display)
    )]
    Window {
        /// The data window: where the pixels are.
        data: IntegerBounds,
        /// The display window: the frame.
        display: IntegerBounds,
    },
    /// Some pixels were decoded more than once and others never: the file's offset table points
    /// at the same block twice (a corrupt or hostile file). Zeros in the missing pixels would
    /// be accepted as black samples, so the pass is refused.
    #[error(
        "the pass's blocks do not cover it: {missing} of {pixels} pixels have no data and \
         {repeated} were decoded more than once (first missing row: {first_missing_row}); \
         the file's offset table is corrupt"
    )]
    Coverage {
        /// Pixels never decoded.
        missing: u64,
        /// Pixels decoded more than once.
        repeated: u64,
        /// Pixels in the pass.
        pixels: u64,
        /// The first row with a missing pixel.
        first_missing_row: u64,
    },
    /// The pass carries some of the frame's AOV channels but not all.
    #[error(
        "the pass has some of the frame's AOVs but not {}: a pass carries every AOV channel of \
         its frame or none; layers found: {}",
        names(.missing), list(.layers)
    )]
    MissingAovs {
        /// The AOV channels (`layer.channel`) not found.
        missing: Vec<String>,
        /// Every layer of the file, in file order.
        layers: Vec<LayerInfo>,
    },
    /// An AOV layer that cannot be read with the beauty.
    #[error("AOV layer {layer:?} cannot be read: {reason}")]
    BadAov {
        /// The layer.
        layer: String,
        /// Why.
        reason: String,
    },
    /// The pass does not have the frame's size.
    #[error("pass is {pass_width}x{pass_height} but the frame is {frame_width}x{frame_height}")]
    SizeMismatch {
        /// Width of the pass.
        pass_width: u32,
        /// Height of the pass.
        pass_height: u32,
        /// Width of the frame.
        frame_width: u32,
        /// Height of the frame.
        frame_height: u32,
    },
}

fn list(layers: &[LayerInfo]) -> String {
    if layers.is_empty() {
        return "none".to_string();
    }
    let all: Vec<String> = layers.iter().map(ToString::to_string).collect();
    all.join("; ")
}

fn names(names: &[String]) -> String {
    let quoted: Vec<String> = names.iter().map(|n| format!("{n:?}")).collect();
    quoted.join(", ")
}

fn show_window(w: &IntegerBounds) -> String {
    format!(
        "({}, {}) size {}x{}",
        w.position.x(),
        w.position.y(),
        w.size.width(),
        w.size.height()
    )
}

/// The layers of a file, part by part, each part's in the order of its (sorted) channels.
pub fn layers(headers: &[Header]) -> Vec<LayerInfo> {
    let mut layers: Vec<LayerInfo> = Vec::new();
    for (part, header) in headers.iter().enumerate() {
        let part_name = header
            .own_attributes
            .layer_name
            .as_ref()
            .map(ToString::to_string);
        let first = layers.len();
        for channel in &header.channels.list {
            let full = channel.name.to_string();
            let (prefix, base) = match full.rsplit_once('.') {
                Some((prefix, base)) => (prefix.to_string(), base.to_string()),
                None => (String::new(), full),
            };
            match layers[first..].iter_mut().find(|l| l.prefix == prefix) {
                Some(layer) => layer.channels.push(base),
                None => layers.push(LayerInfo {
                    name: layer_name(part_name.as_deref(), &prefix),
                    part,
                    prefix,
                    channels: vec![base],
                    rgb: false,
                }),
            }
        }
        if layers.len() == first {
            // A part without channels is still a layer the file has.
            layers.push(LayerInfo {
                name: part_name.unwrap_or_default(),
                part,
                prefix: String::new(),
                channels: Vec::new(),
                rgb: false,
            });
        }
        for layer in &mut layers[first..] {
            layer.rgb = !header.deep
                && ["R", "G", "B"]
                    .iter()
                    .all(|c| layer.channels.iter().any(|have| have == c));
        }
    }
    layers
}

/// A layer's name from its part's name and its channel prefix.
fn layer_name(part: Option<&str>, prefix: &str) -> String {
    match part {
        None | Some("") => prefix.to_string(),
        Some(part) if prefix.is_empty() => part.to_string(),
        Some(part) if prefix == part || prefix.starts_with(&format!("{part}.")) => {
            prefix.to_string()
        }
        Some(part) => format!("{part}.{prefix}"),
    }
}

/// Picks the beauty among `layers`: the one named `asked`, or the automatic choice (see the
/// module docs).
///
/// # Errors
/// [`PassError::UnknownLayer`] and [`PassError::NotRgb`] for a named layer;
/// [`PassError::NoRgbLayer`] and [`PassError::Ambiguous`] for the automatic choice.
pub fn choose_beauty(layers: &[LayerInfo], asked: Option<&str>) -> Result<usize, PassError> {
    if let Some(asked) = asked {
        let index =
            layers
                .iter()
                .position(|l| l.name == asked)
                .ok_or_else(|| PassError::UnknownLayer {
                    asked: asked.to_string(),
                    layers: layers.to_vec(),
                })?;
        if !layers[index].rgb {
            return Err(PassError::NotRgb {
                layer: layers[index].clone(),
            });
        }
        return Ok(index);
    }
    let rules: [&dyn Fn(&str) -> bool; 4] = [
        &|name| name.is_empty(),
        &|name| {
            name.strip_suffix(".Combined")
                .is_some_and(|view| !view.is_empty() && !view.contains('.'))
        },
        &|name| BEAUTY_NAMES.iter().any(|b| name.eq_ignore_ascii_case(b)),
        &|_| true,
    ];
    for rule in rules {
        let found: Vec<usize> = (0..layers.len())
            .filter(|&i| layers[i].rgb && rule(&layers[i].name))
            .collect();
        match found.as_slice() {
            [] => continue,
            [one] => return Ok(*one),
            many => {
                return Err(PassError::Ambiguous {
                    candidates: many.iter().map(|&i| layers[i].name.clone()).collect(),
                    layers: layers.to_vec(),
                })
            }
        }
    }
    Err(PassError::NoRgbLayer {
        layers: layers.to_vec(),
    })
}

/// Decodes one pass from the bytes of an EXR file: the automatically chosen beauty, with the
/// default size limit [`MAX_PASS_PIXELS`].
///
/// # Errors
/// See [`decode_pass_with`].
pub fn decode_pass(bytes: &[u8]) -> Result<Pass, PassError> {
    decode_pass_with(bytes, None, MAX_PASS_PIXELS)
}

/// Where each AOV channel asked for is: `(part, channel index in the part)`, in the order
/// asked for; `None` when the file has none of them.
///
/// # Errors
/// [`PassError::MissingAovs`] when it has some but not all; [`PassError::BadAov`] for an AOV
/// in a deep part.
fn find_aovs(
    headers: &[Header],
    all: &[LayerInfo],
    aovs: &[AovSpec],
) -> Result<Option<Vec<(usize, usize)>>, PassError> {
    let mut found = Vec::new();
    let mut missing = Vec::new();
    for aov in aovs {
        let layer = all.iter().find(|l| l.name == aov.name);
        for c in &aov.channels {
            let full = match layer {
                Some(l) if l.prefix.is_empty() => c.clone(),
                Some(l) => format!("{}.{c}", l.prefix),
                None => String::new(),
            };
            let at = layer.and_then(|l| {
                headers[l.part]
                    .channels
                    .list
                    .iter()
                    .position(|ch| ch.name.eq(full.as_str()))
                    .map(|i| (l.part, i))
            });
            match at {
                Some((part, _)) if headers[part].deep => {
                    return Err(PassError::BadAov {
                        layer: aov.name.clone(),
                        reason: "it is deep data".into(),
                    })
                }
                Some(at) => found.push(at),
                None => missing.push(format!("{}.{c}", aov.name)),
            }
        }
    }
    match (found.is_empty(), missing.is_empty()) {
        (true, _) => Ok(None),
        (false, true) => Ok(Some(found)),
        (false, false) => Err(PassError::MissingAovs {
            missing,
            layers: all.to_vec(),
        }),
    }
}

/// [`decode_pass`] with a caller-chosen limit on the pass's pixel count, for example the size
/// of the frame the pass is for.
pub fn decode_pass_with_limit(bytes: &[u8], max_pixels: u64) -> Result<Pass, PassError> {
    decode_pass_with(bytes, None, max_pixels)
}

/// Decodes one pass: `R`, `G`, `B` of the layer named `layer`, or of the automatically chosen
/// beauty when `layer` is `None` (see the module docs). Values are not checked.
///
/// # Errors
/// [`PassError::NotExr`] for bytes that are not EXR, [`PassError::Exr`] for an EXR that cannot
/// be read; the beauty not found: [`PassError::NoRgbLayer`], [`PassError::Ambiguous`],
/// [`PassError::UnknownLayer`], [`PassError::NotRgb`] (each listing the layers present); a
/// beauty that cannot be a pass: [`PassError::Subsampled`], [`PassError::Empty`],
/// [`PassError::TooLarge`], [`PassError::Window`]; blocks that do not cover it exactly once:
/// [`PassError::Coverage`].
pub fn decode_pass_with(
    bytes: &[u8],
    layer: Option<&str>,
    max_pixels: u64,
) -> Result<Pass, PassError> {
    decode_pass_with_aovs(bytes, layer, max_pixels, &[])
}

/// [`decode_pass_with`], also reading the AOV channels `aovs` (a frame's AOVs) into
/// [`Pass::aovs`] when the pass carries them. An AOV layer may be in any part of the same size
/// as the beauty's (covering its display window, not subsampled).
///
/// # Errors
/// As [`decode_pass_with`]; and [`PassError::MissingAovs`] for a pass with some of the AOV
/// channels but not all, [`PassError::BadAov`] for an AOV that cannot be read with the beauty.
pub fn decode_pass_with_aovs(
    bytes: &[u8],
    layer: Option<&str>,
    max_pixels: u64,
    aovs: &[AovSpec],
) -> Result<Pass, PassError> {
    decode_pass_reusing(bytes, layer, max_pixels, aovs, &mut Scratch::default())
}

/// The buffers one decode fills: its write counts and the interleaved samples.
///
/// A 1080p pass needs 13 bytes per pixel of them (27 MB); allocated fresh for every pass,
/// they are large enough to be mapped and unmapped by the allocator each time, and the server's
/// ingest threads spent a third of their time in the page faults of touching them. Decoding into
/// a [`Scratch`] kept from an earlier pass reuses memory that is already mapped.
///
/// A pass's AOV values (50 MB for a 1080p pass with an albedo and a normal) are kept the same
/// way: given away with each pass and freed after it, they were a fresh mapping for every pass.
#[derive(Debug, Default)]
pub struct Scratch {
    writes: Vec<Vec<u8>>,
    rgb: Vec<[f32; 3]>,
    aovs: Vec<f32>,
}

impl Scratch {
    /// Takes back the samples and AOV values of a pass decoded into this scratch (or any pass),
    /// to reuse them.
    pub fn recycle(&mut self, pass: Pass) {
        keep_larger(&mut self.rgb, pass.rgb);
        if let Some(aovs) = pass.aovs {
            keep_larger(&mut self.aovs, aovs);
        }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        let writes: usize = self.writes.iter().map(Vec::capacity).sum();
        writes + self.rgb.capacity() * 12 + self.aovs.capacity() * 4
    }

    /// Room for `n` samples, from the spare one when there is one. Its values are whatever a
    /// pass before left there: the decode writes every pixel or fails (its write counts prove
    /// which), so they are not cleared first.
    fn rgb(&mut self, n: usize) -> Vec<[f32; 3]> {
        reuse(&mut self.rgb, n, [0.0; 3])
    }

    /// Room for `n` AOV values, as [`Scratch::rgb`] (a block holds every channel of its
    /// pixels, so the blocks that write a pixel's beauty write its AOVs of the same part, and
    /// each other part's writes are counted on their own).
    fn aovs(&mut self, n: usize) -> Vec<f32> {
        reuse(&mut self.aovs, n, 0.0)
    }

    /// `n` write counts at zero, from spare ones when there are.
    fn counts(&mut self, n: usize) -> Vec<u8> {
        let mut counts = self.writes.pop().unwrap_or_default();
        counts.clear();
        counts.reserve_exact(n);
        counts.resize(n, 0);
        counts
    }

    /// Keeps a decode's samples (unless the pass took them) and counts for the next one.
    fn keep(&mut self, planes: Planes) {
        keep_larger(&mut self.rgb, planes.rgb);
        keep_larger(&mut self.aovs, planes.aovs);
        self.writes
            .extend(planes.writes.into_iter().filter(|w| w.capacity() > 0));
    }
}

/// Keeps `buf` as `spare` if it has more room.
fn keep_larger<T>(spare: &mut Vec<T>, buf: Vec<T>) {
    if buf.capacity() > spare.capacity() {
        *spare = buf;
    }
}

/// `spare` as a buffer of `n` values: the values it holds, or where its length differs, `fill`.
fn reuse<T: Copy>(spare: &mut Vec<T>, n: usize, fill: T) -> Vec<T> {
    let mut buf = std::mem::take(spare);
    if buf.len() != n {
        buf.clear();
        // Exactly: a pass a little larger than the last must not double the buffer.
        buf.reserve_exact(n);
        buf.resize(n, fill);
    }
    buf
}

/// A few [`Scratch`]es kept between requests, so that passes decode into memory that is
/// already mapped (see [`crate::scratch`]).
///
/// A scratch in use is covered by its request's working-memory reservation (see the
/// `passes` route's `decoding_bytes`); the ones kept idle are bounded by `keep` times the
/// largest pass decoded.
pub type ScratchPool = crate::scratch::Pool<Scratch>;

impl crate::scratch::Reusable for Scratch {
    fn bytes(&self) -> usize {
        Scratch::bytes(self)
    }
}

/// [`decode_pass_with_aovs`] into the buffers of `scratch`: the pass's `rgb` is the scratch's
/// (give it back with [`Scratch::recycle`]), and the decoder's planes stay in the scratch for
/// the next decode. The result is the same, bit for bit.
///
/// # Errors
/// As [`decode_pass_with_aovs`].
pub fn decode_pass_reusing(
    bytes: &[u8],
    layer: Option<&str>,
    max_pixels: u64,
    aovs: &[AovSpec],
    scratch: &mut Scratch,
) -> Result<Pass, PassError> {
    if bytes.len() < EXR_MAGIC.len() || bytes[..EXR_MAGIC.len()] != EXR_MAGIC {
        let found: Vec<String> = bytes.iter().take(4).map(|b| format!("{b:02x}")).collect();
        return Err(PassError::NotExr {
            found: if found.is_empty() {
                "nothing (0 bytes)".to_string()
            } else {
                found.join(" ")
            },
        });
    }

    // The headers alone first: the beauty's size is checked before anything is allocated.
    let reader = exr::block::read(Cursor::new(bytes), false)?;
    let all = layers(reader.headers());
    let beauty = all[choose_beauty(&all, layer)?].clone();
    let aov_channels = find_aovs(reader.headers(), &all, aovs)?;
    let part = beauty.part;
    let header = &reader.headers()[part];
    let (w, h) = (header.layer_size.width(), header.layer_size.height());
    let (width64, height64) = (w as u64, h as u64);
    if w == 0 || h == 0 {
        return Err(PassError::Empty {
            width: width64,
            height: height64,
        });
    }
    // Fitting the limit also makes the size fit u32 (the limit is far below 2^32 per side in
    // practice; a caller-given limit above that is still checked here).
    let (Ok(width), Ok(height)) = (u32::try_from(w), u32::try_from(h)) else {
        return Err(PassError::TooLarge {
            width: width64,
            height: height64,
            max_pixels,
        });
    };
    if width64.saturating_mul(height64) > max_pixels {
        return Err(PassError::TooLarge {
            width: width64,
            height: height64,
            max_pixels,
        });
    }
    let data = header.data_window();
    let display = header.shared_attributes.display_window;
    if data != display {
        return Err(PassError::Window { data, display });
    }
    check_sampling(header)?;
    // The parts holding AOVs must lie exactly over the beauty's pixels.
    for &(aov_part, _) in aov_channels.iter().flatten() {
        let other = &reader.headers()[aov_part];
        if aov_part == part {
            continue;
        }
        let name = all
            .iter()
            .find(|l| l.part == aov_part)
            .map_or_else(String::new, |l| l.name.clone());
        if other.data_window() != data || other.shared_attributes.display_window != display {
            return Err(PassError::BadAov {
                layer: name,
                reason: format!(
                    "its part's data window {} is not the beauty's {}",
                    show_window(&other.data_window()),
                    show_window(&data)
                ),
            });
        }
        check_sampling(other)?;
    }
    let full_name = |base: &str| {
        if beauty.prefix.is_empty() {
            base.to_string()
        } else {
            format!("{}.{base}", beauty.prefix)
        }
    };
    let mut rgb_channels = [0usize; 3];
    for (slot, base) in rgb_channels.iter_mut().zip(["R", "G", "B"]) {
        let name = full_name(base);
        *slot = header
            .channels
            .list
            .iter()
            .position(|c| c.name.eq(name.as_str()))
            .ok_or_else(|| PassError::NotRgb {
                layer: beauty.clone(),
            })?;
    }

    let mut wanted: Vec<(usize, usize)> = rgb_channels.iter().map(|&c| (part, c)).collect();
    wanted.extend(aov_channels.iter().flatten().copied());
    let aov_count = aov_channels.as_ref().map_or(0, Vec::len);
    let mut buffer = Planes::new(w, h, reader.headers().len(), &wanted, aov_count, scratch);
    // Only the parts read, full resolution: other parts are never decompressed.
    let parts: Vec<bool> = (0..reader.headers().len())
        .map(|p| wanted.iter().any(|&(q, _)| q == p))
        .collect();
    let chunks = reader.filter_chunks(false, |_, _, block| {
        parts.get(block.layer).copied().unwrap_or(false) && block.level == Vec2(0, 0)
    })?;
    let decoded = chunks
        .decompress_parallel(false, |meta, block| {
            let header = meta
                .headers
                .get(block.index.layer)
                .ok_or_else(|| exr::error::Error::Invalid("a block of no part".into()))?;
            buffer.insert(header, &block)
        })
        .map_err(PassError::from)
        .and_then(|()| buffer.check_coverage());
    if let Err(e) = decoded {
        scratch.keep(buffer);
        return Err(e);
    }
    let rgb = std::mem::take(&mut buffer.rgb);
    let aovs = aov_channels.map(|_| std::mem::take(&mut buffer.aovs));
    scratch.keep(buffer);
    Ok(Pass {
        width,
        height,
        layer: beauty.name,
        rgb,
        aovs,
    })
}

/// Refuses a part with a subsampled channel (`exr` cannot lay out such blocks).
fn check_sampling(header: &Header) -> Result<(), PassError> {
    match header
        .channels
        .list
        .iter()
        .find(|c| c.sampling != Vec2(1, 1))
    {
        Some(c) => Err(PassError::Subsampled {
            channel: c.name.to_string(),
            x: c.sampling.x(),
            y: c.sampling.y(),
        }),
        None => Ok(()),
    }
}

/// Pixel storage while `exr` decodes: each channel read goes straight to its place in the
/// interleaved samples (the beauty's `R`, `G`, `B` in [`Pass::rgb`], the AOV channels in
/// [`Pass::aovs`]). Decoding into one plane per channel and interleaving them afterwards
/// wrote and read every value once more, and read them from the file through a reader per
/// value: a tenth of the server's CPU under `loadgen`'s pass ingest.
struct Planes {
    width: usize,
    height: usize,
    /// Per part, the channels read from it: `(channel index in the part, wanted index)`, where
    /// wanted channels `0..3` are the beauty's `R`, `G`, `B` and the rest the AOVs' in order.
    by_part: Vec<Vec<(usize, usize)>>,
    rgb: Vec<[f32; 3]>,
    /// AOV values, pixel by pixel (`aov_count` per pixel).
    aovs: Vec<f32>,
    aov_count: usize,
    /// Per part read, how often each pixel was written. `exr` decodes whatever blocks the
    /// offset table points at, so a table that names one block twice leaves another block's
    /// pixels unwritten without an error; counting writes is what proves each pixel came
    /// from its own data exactly once.
    writes: Vec<Vec<u8>>,
}

impl Planes {
    /// Storage for `wanted` channels `(part, channel index)` of a `width x height` pass: the
    /// beauty's `R`, `G`, `B`, then `aov_count` AOV channels. The buffers are taken from
    /// `scratch` when it has them.
    fn new(
        width: usize,
        height: usize,
        parts: usize,
        wanted: &[(usize, usize)],
        aov_count: usize,
        scratch: &mut Scratch,
    ) -> Planes {
        debug_assert_eq!(wanted.len(), 3 + aov_count);
        let mut by_part = vec![Vec::new(); parts];
        for (plane, &(part, channel)) in wanted.iter().enumerate() {
            by_part[part].push((channel, plane));
        }
        let writes = by_part
            .iter()
            .map(|w| {
                if w.is_empty() {
                    Vec::new()
                } else {
                    scratch.counts(width * height)
                }
            })
            .collect();
        Planes {
            width,
            height,
            by_part,
            rgb: scratch.rgb(width * height),
            aovs: scratch.aovs(width * height * aov_count),
            aov_count,
            writes,
        }
    }

    /// Wanted channel `plane`'s values from pixel `start` on, in `rgb` or `aovs` (`aov_count`
    /// per pixel): a slice whose every `stride`-th value is one pixel's.
    fn target<'b>(
        (rgb, aovs, aov_count): (&'b mut [[f32; 3]], &'b mut [f32], usize),
        plane: usize,
        start: usize,
    ) -> (&'b mut [f32], usize) {
        if plane < 3 {
            (&mut rgb.as_flattened_mut()[3 * start + plane..], 3)
        } else {
            (&mut aovs[aov_count * start + plane - 3..], aov_count)
        }
    }

    /// Copies the wanted channels of one decompressed block.
    fn insert(&mut self, header: &Header, block: &UncompressedBlock) -> exr::error::UnitResult {
        let index = block.index;
        // The chunk names its own part and level; a corrupt table can point at another's.
        let wanted = match self.by_part.get(index.layer) {
            Some(w) if !w.is_empty() && index.level == Vec2(0, 0) => w,
            _ => {
                return Err(exr::error::Error::Invalid(
                    "a block of another part or resolution level where the pass's was expected"
                        .into(),
                ))
            }
        };
        let (x0, y0) = (index.pixel_position.x(), index.pixel_position.y());
        let (bw, bh) = (index.pixel_size.width(), index.pixel_size.height());
        if x0 + bw > self.width || y0 + bh > self.height {
            return Err(exr::error::Error::Invalid(
                "a block outside the data window".into(),
            ));
        }
        let per_pixel: usize = header
            .channels
            .list
            .iter()
            .map(|c| c.sample_type.bytes_per_sample())
            .sum();
        if block.data.len() != bw * bh * per_pixel {
            return Err(exr::error::Error::Invalid("a block's size".into()));
        }
        // Writes are counted on the part's first wanted channel.
        let counted = wanted.iter().map(|&(c, _)| c).min();
        let writes = &mut self.writes[index.layer];
        let (pixels, width) = (&mut self.rgb[..], self.width);
        let line_bytes = bw * per_pixel;
        let fused = Planes::insert_rgb(
            pixels,
            writes,
            width,
            (wanted, counted),
            (block, line_bytes),
            header,
        );
        for line in block.lines(&header.channels) {
            let channel = line.location.channel;
            let Some(&(_, plane)) = wanted.iter().find(|&&(c, _)| c == channel) else {
                continue;
            };
            if fused && plane < 3 {
                continue;
            }
            let (x, y) = (line.location.position.x(), line.location.position.y());
            let (start, n) = (y * self.width + x, line.location.sample_count);
            let sample_type = header.channels.list[channel].sample_type;
            if line.value.len() != n * sample_type.bytes_per_sample() {
                return Err(exr::error::Error::Invalid("a line's size".into()));
            }
            // A decompressed block holds its samples in this machine's byte order.
            let to = (&mut self.rgb[..], &mut self.aovs[..], self.aov_count);
            let (values, stride) = Planes::target(to, plane, start);
            let values = values.iter_mut().step_by(stride);
            match sample_type {
                SampleType::F16 => widen(values, line.value, from_f16),
                SampleType::F32 => widen(values, line.value, f32::from_ne_bytes),
                SampleType::U32 => widen(values, line.value, from_u32),
            }
            if Some(channel) == counted {
                count_writes(&mut writes[start..start + n]);
            }
        }
        Ok(())
    }

    /// Copies the beauty's `R`, `G`, `B` of a block of a part holding them (the channels
    /// `wanted` of it, as in [`Planes::by_part`], the one whose writes are `counted`) if the
    /// three have one sample type, into `pixels` of a `width`-wide frame, line by line, each
    /// pixel's three values at once (and counts the part's `writes` if one of them is the
    /// counted channel); returns whether it did. The loop in [`Planes::insert`] copies a
    /// channel at a time, every third value: an uncompressed 1080p pass took 7.4-7.6 ms to
    /// decode that way, 4.9-5.4 ms this way (the best of 40, three runs each).
    ///
    /// The caller has checked the block's position and size against the header, and gives
    /// the length of its lines in bytes (every channel's samples of one line of pixels).
    fn insert_rgb(
        pixels: &mut [[f32; 3]],
        writes: &mut [u8],
        width: usize,
        (wanted, counted): (&[(usize, usize)], Option<usize>),
        (block, line_bytes): (&UncompressedBlock, usize),
        header: &Header,
    ) -> bool {
        let index = block.index;
        let channels = &header.channels.list;
        // The beauty's channels, if this is its part.
        let mut rgb = [None; 3];
        for &(channel, plane) in wanted {
            if plane < 3 {
                rgb[plane] = Some(channel);
            }
        }
        let [Some(r), Some(g), Some(b)] = rgb else {
            return false;
        };
        let rgb = [r, g, b];
        let sample_type = channels[r].sample_type;
        if rgb.iter().any(|&c| channels[c].sample_type != sample_type) {
            return false;
        }
        // A line holds each channel's samples in turn (no channel is subsampled: checked when
        // the pass was opened), each `bw` samples long.
        let (x0, y0) = (index.pixel_position.x(), index.pixel_position.y());
        let bw = index.pixel_size.width();
        let offset = |channel: usize| -> usize {
            channels[..channel]
                .iter()
                .map(|c| bw * c.sample_type.bytes_per_sample())
                .sum()
        };
        let at = rgb.map(offset);
        let bytes = bw * sample_type.bytes_per_sample();
        let counts = counted.is_some_and(|c| rgb.contains(&c));
        for (row, line) in block.data.chunks_exact(line_bytes).enumerate() {
            let start = (y0 + row) * width + x0;
            let out = &mut pixels[start..start + bw];
            let values = at.map(|at| &line[at..at + bytes]);
            // A decompressed block holds its samples in this machine's byte order.
            match sample_type {
                SampleType::F16 => interleave(out, values, from_f16),
                SampleType::F32 => interleave(out, values, f32::from_ne_bytes),
                SampleType::U32 => interleave(out, values, from_u32),
            }
            if counts {
                count_writes(&mut writes[start..start + bw]);
            }
        }
        true
    }

    fn check_coverage(&self) -> Result<(), PassError> {
        for writes in self.writes.iter().filter(|w| !w.is_empty()) {
            let (mut missing, mut repeated, mut first_missing) = (0u64, 0u64, None);
            for (i, &n) in writes.iter().enumerate() {
                match n {
                    1 => {}
                    0 => {
                        missing += 1;
                        first_missing.get_or_insert(i / self.width.max(1));
                    }
                    _ => repeated += 1,
                }
            }
            if first_missing.is_some() || repeated > 0 {
                return Err(PassError::Coverage {
                    missing,
                    repeated,
                    pixels: writes.len() as u64,
                    first_missing_row: first_missing.unwrap_or(0) as u64,
                });
            }
        }
        Ok(())
    }
}

/// Counts one more write of each pixel of `writes` (see [`Planes::writes`]).
fn count_writes(writes: &mut [u8]) {
    for n in writes {
        *n = n.saturating_add(1);
    }
}

/// A half-float sample's value, from its bytes in this machine's order (as a decompressed block
/// holds them).
fn from_f16(bytes: [u8; 2]) -> f32 {
    f16::from_ne_bytes(bytes).to_f32()
}

/// An unsigned-integer sample's value, from its bytes in this machine's order.
fn from_u32(bytes: [u8; 4]) -> f32 {
    u32::from_ne_bytes(bytes) as f32
}

/// Each of `out` from the next value of `line` (`N` bytes each, read by `value`).
#[inline(always)]
fn widen<'v, const N: usize>(
    out: impl Iterator<Item = &'v mut f32>,
    line: &[u8],
    value: impl Fn([u8; N]) -> f32,
) {
    for (v, bytes) in out.zip(line.chunks_exact(N)) {
        *v = value(bytes.try_into().expect("N bytes"));
    }
}

/// Each pixel of `out` from the values of its `R`, `G` and `B` in `rgb` (`N` bytes each, read
/// by `value`).
#[inline(always)]
fn interleave<const N: usize>(
    out: &mut [[f32; 3]],
    [r, g, b]: [&[u8]; 3],
    value: impl Fn([u8; N]) -> f32,
) {
    let value = |bytes: &[u8]| value(bytes.try_into().expect("N bytes"));
    let values = r
        .chunks_exact(N)
        .zip(g.chunks_exact(N))
        .zip(b.chunks_exact(N));
    for (pixel, ((r, g), b)) in out.iter_mut().zip(values) {
        *pixel = [value(r), value(g), value(b)];
    }
}

impl Pass {
    /// One record per pixel, row-major (top row first, left to right): pixel `(x, y)` with
    /// its sample. Values are passed through unchecked.
    ///
    /// Yields `min(rgb.len(), width * height)` records, so a hand-built `Pass` whose `rgb` does
    /// not match its size never yields a pixel outside it.
    pub fn records(&self) -> impl Iterator<Item = Record> + '_ {
        let width = self.width.max(1) as usize;
        let pixels = self.width as usize * self.height as usize;
        self.rgb
            .iter()
            .take(pixels)
            .enumerate()
            .map(move |(i, &rgb)| Record::new((i % width) as u32, (i / width) as u32, rgb))
    }

    /// Checks that the pass has the size of the frame it is added to.
    ///
    /// # Errors
    /// [`PassError::SizeMismatch`], for example "pass is 64x32 but the frame is 128x128".
    pub fn check(&self, width: u32, height: u32) -> Result<(), PassError> {
        if (self.width, self.height) == (width, height) {
            Ok(())
        } else {
            Err(PassError::SizeMismatch {
                pass_width: self.width,
                pass_height: self.height,
                frame_width: width,
                frame_height: height,
            })
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use exr::prelude::*;

    /// Writes a single-part EXR with the given f32 channels with the `exr` crate.
    fn exr_with(width: usize, height: usize, names: &[&str]) -> Vec<u8> {
        let channels: Vec<AnyChannel<FlatSamples>> = names
            .iter()
            .enumerate()
            .map(|(c, name)| {
                let values = (0..width * height).map(|i| (i * 10 + c) as f32).collect();
                AnyChannel::new(*name, FlatSamples::F32(values))
            })
            .collect();
        let layer = Layer::new(
            (width, height),
            LayerAttributes::default(),
            Encoding::SMALL_LOSSLESS,
            AnyChannels::sort(SmallVec::from_vec(channels)),
        );
        let mut bytes = Vec::new();
        Image::from_layer(layer)
            .write()
            .to_buffered(std::io::Cursor::new(&mut bytes))
            .expect("writing a test EXR to memory");
        bytes
    }

    /// A beauty whose channels differ in sample type is read a channel at a time (the path
    /// [`Planes::insert_rgb`] leaves to [`Planes::insert`]), to the same values.
    #[test]
    fn a_beauty_of_mixed_sample_types_is_read_value_for_value() {
        let (width, height) = (7, 5);
        let value = |i: usize, c: usize| (i * 10 + c) as f32;
        let channels = ["B", "G", "R"].iter().enumerate().map(|(c, name)| {
            let values = (0..width * height).map(|i| value(i, c));
            let samples = if *name == "G" {
                FlatSamples::F16(values.map(f16::from_f32).collect())
            } else {
                FlatSamples::F32(values.collect())
            };
            AnyChannel::new(*name, samples)
        });
        let layer = Layer::new(
            (width, height),
            LayerAttributes::default(),
            Encoding::UNCOMPRESSED,
            AnyChannels::sort(channels.collect()),
        );
        let mut bytes = Vec::new();
        Image::from_layer(layer)
            .write()
            .to_buffered(std::io::Cursor::new(&mut bytes))
            .expect("writing a test EXR to memory");
        let pass = decode_pass(&bytes).unwrap();
        for (i, px) in pass.rgb.iter().enumerate() {
            let g = f16::from_f32(value(i, 1)).to_f32();
            assert_eq!(*px, [value(i, 2), g, value(i, 0)], "pixel {i}");
        }
    }

    #[test]
    fn garbage_is_refused_by_its_first_bytes() {
        let err = decode_pass(b"GIF89a not an exr").unwrap_err();
        assert!(matches!(err, PassError::NotExr { .. }), "{err:?}");
        assert!(err.to_string().contains("47 49 46 38"), "{err}");
        let err = decode_pass(&[]).unwrap_err();
        assert!(err.to_string().contains("0 bytes"), "{err}");
    }

    #[test]
    fn a_truncated_exr_is_an_exr_error_not_a_panic() {
        let bytes = exr_with(8, 8, &["R", "G", "B"]);
        for cut in [4, 20, bytes.len() / 2, bytes.len() - 1] {
            let err = decode_pass(&bytes[..cut]).unwrap_err();
            assert!(matches!(err, PassError::Exr(_)), "cut at {cut}: {err:?}");
        }
    }

    #[test]
    fn a_luminance_only_exr_is_refused_naming_its_channels() {
        let err = decode_pass(&exr_with(4, 3, &["Y"])).unwrap_err();
        match &err {
            PassError::NoRgbLayer { layers } => {
                assert_eq!(layers.len(), 1);
                assert_eq!(
                    (layers[0].name.as_str(), &layers[0].channels),
                    ("", &vec!["Y".to_string()])
                );
            }
            other => panic!("expected NoRgbLayer, got {other:?}"),
        }
        assert_eq!(
            err.to_string(),
            "the EXR has no layer with channels R, G and B; layers found: unnamed (Y)"
        );
    }

    #[test]
    fn a_missing_blue_channel_is_refused_naming_the_ones_present() {
        let err = decode_pass(&exr_with(4, 3, &["A", "G", "R"])).unwrap_err();
        assert!(
            err.to_string().ends_with("layers found: unnamed (A, G, R)"),
            "{err}"
        );
    }

    #[test]
    fn rgb_is_read_row_major_and_alpha_and_others_ignored() {
        let pass = decode_pass(&exr_with(3, 2, &["A", "B", "G", "R", "Z"])).unwrap();
        assert_eq!((pass.width, pass.height), (3, 2));
        // Channels are written sorted, value = pixel * 10 + channel index: B = 1, G = 2, R = 3.
        for (i, px) in pass.rgb.iter().enumerate() {
            let v = (i * 10) as f32;
            assert_eq!(*px, [v + 3.0, v + 2.0, v + 1.0], "pixel {i}");
        }
        let records: Vec<Record> = pass.records().collect();
        assert_eq!(records.len(), 6);
        assert_eq!(records[4], Record::new(1, 1, [43.0, 42.0, 41.0]));
    }

    /// Where the offset table of a single-part scanline EXR with `blocks` blocks starts: the
    /// first entry points just past the table itself.
    fn offset_table(bytes: &[u8], blocks: usize) -> usize {
        (8..bytes.len() - 8)
            .find(|&at| {
                let v = u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap());
                v == (at + 8 * blocks) as u64
            })
            .expect("an offset table")
    }

    fn set_offset(bytes: &mut [u8], table: usize, block: usize, value: u64) {
        bytes[table + 8 * block..table + 8 * block + 8].copy_from_slice(&value.to_le_bytes());
    }

    fn offset(bytes: &[u8], table: usize, block: usize) -> u64 {
        u64::from_le_bytes(bytes[table + 8 * block..][..8].try_into().unwrap())
    }

    /// Uncompressed scanline EXRs store one row per block.
    use crate::testing::uncompressed_rgb;

    fn uncompressed(width: usize, height: usize) -> Vec<u8> {
        uncompressed_rgb(width, height, |i| [3, 2, 1].map(|c| (i * 10 + c) as f32))
    }

    #[test]
    fn a_reused_scratch_decodes_what_a_fresh_one_does_and_keeps_its_memory() {
        let mut scratch = Scratch::default();
        let decode = |bytes: &[u8], scratch: &mut Scratch| {
            decode_pass_reusing(bytes, None, MAX_PASS_PIXELS, &[], scratch)
        };
        // A larger pass with other values first, then a refused one (row 1 read twice, row 2
        // missing: its stale planes and counts must not make it look covered), then passes of
        // other sizes: each is what a fresh decode makes.
        let big = exr_with(9, 7, &["A", "B", "G", "R"]);
        let pass = decode(&big, &mut scratch).unwrap();
        assert_eq!(pass, decode_pass(&big).unwrap());
        scratch.recycle(pass);
        let held = scratch.bytes();
        assert!(held >= 9 * 7 * (1 + 12), "{held} bytes kept");

        let good = uncompressed(5, 16);
        let table = offset_table(&good, 16);
        let mut twice = good.clone();
        set_offset(&mut twice, table, 1, offset(&good, table, 0));
        let err = decode(&twice, &mut scratch).unwrap_err();
        assert!(err.to_string().contains("5 of 80 pixels"), "{err}");

        for bytes in [good, exr_with(3, 2, &["B", "G", "R"]), big] {
            let pass = decode(&bytes, &mut scratch).unwrap();
            assert_eq!(pass, decode_pass(&bytes).unwrap());
            scratch.recycle(pass);
        }
        // The buffers grew to the largest pass and were reused since, not replaced.
        assert_eq!(scratch.bytes(), held.max(5 * 16 * (1 + 12)));

        let pool = ScratchPool::new(1);
        pool.give(scratch);
        pool.give(Scratch::default());
        assert_eq!(
            pool.idle_bytes(),
            held.max(5 * 16 * 13),
            "one kept, the other dropped"
        );
        assert!(pool.take().bytes() > 0);
        assert_eq!(pool.take().bytes(), 0, "none left: a new, empty one");
    }

    #[test]
    fn a_reused_scratch_decodes_aovs_as_a_fresh_one_does_in_the_same_memory() {
        let aovs = [AovSpec::new("albedo", &["R", "G", "B"])];
        let mut scratch = Scratch::default();
        let decode = |bytes: &[u8], scratch: &mut Scratch| {
            decode_pass_reusing(bytes, None, MAX_PASS_PIXELS, &aovs, scratch).unwrap()
        };
        let fresh =
            |bytes: &[u8]| decode_pass_with_aovs(bytes, None, MAX_PASS_PIXELS, &aovs).unwrap();
        let first = exr_with(6, 4, &["albedo.B", "albedo.G", "albedo.R", "B", "G", "R"]);
        let pass = decode(&first, &mut scratch);
        assert_eq!(pass, fresh(&first));
        let values = pass.aovs.as_ref().expect("AOVs").as_ptr();
        scratch.recycle(pass);
        assert!(
            scratch.bytes() >= 6 * 4 * (1 + 12 + 12),
            "the AOV values are kept"
        );

        // A pass without the AOVs in between keeps their buffer for the next that has them.
        let plain = exr_with(6, 4, &["B", "G", "R"]);
        let pass = decode(&plain, &mut scratch);
        assert_eq!((&pass, pass.aovs.is_none()), (&fresh(&plain), true));
        scratch.recycle(pass);

        // Other values (the channels given in another order): the pass's own, in the memory
        // the first pass's AOVs had.
        let other = exr_with(6, 4, &["B", "G", "R", "albedo.B", "albedo.G", "albedo.R"]);
        let pass = decode(&other, &mut scratch);
        assert_eq!(pass, fresh(&other));
        assert_ne!(pass.aovs, fresh(&first).aovs);
        assert_eq!(pass.aovs.as_ref().expect("AOVs").as_ptr(), values);
    }

    /// An AOV whose channels sort before the beauty's in the beauty's part: its first channel
    /// is the one whose writes are counted (the beauty's three are copied apart from the other
    /// channels, [`Planes::insert_rgb`]), and every value comes back where it was written.
    #[test]
    fn an_aov_sorted_before_the_beauty_in_its_part_reads_back_value_for_value() {
        let (w, h) = (6, 4);
        let aovs = [AovSpec::new("Albedo", &["R", "G", "B"])];
        // Each value is pixel * 10 + its channel's place in this list.
        let names = ["Albedo.B", "Albedo.G", "Albedo.R", "B", "G", "R"];
        let pass =
            decode_pass_with_aovs(&exr_with(w, h, &names), None, MAX_PASS_PIXELS, &aovs).unwrap();
        let aov_values = pass.aovs.as_deref().expect("the AOV's values");
        for i in 0..w * h {
            let v = |c: usize| (i * 10 + c) as f32;
            assert_eq!(pass.rgb[i], [v(5), v(4), v(3)], "pixel {i}'s beauty");
            assert_eq!(
                aov_values[3 * i..3 * i + 3],
                [v(2), v(1), v(0)],
                "pixel {i}'s albedo"
            );
        }
    }

    #[test]
    fn a_block_read_twice_and_a_block_missing_are_refused() {
        let (w, h) = (5, 16);
        let good = uncompressed(w, h);
        assert!(decode_pass(&good).is_ok());
        let table = offset_table(&good, h);

        // Row 1's entry points at row 0's block: row 0 is decoded twice, row 1 never.
        let mut twice = good.clone();
        set_offset(&mut twice, table, 1, offset(&good, table, 0));
        let err = decode_pass(&twice).unwrap_err();
        assert!(matches!(err, PassError::Coverage { .. }), "{err:?}");
        assert!(err.to_string().contains("5 of 80 pixels"), "{err}");

        // Every entry at block 0: one row decoded 16 times, 15 rows missing.
        let mut all_first = good.clone();
        for block in 1..h {
            set_offset(&mut all_first, table, block, offset(&good, table, 0));
        }
        let err = decode_pass(&all_first).unwrap_err();
        assert!(err.to_string().contains("75 of 80 pixels"), "{err}");
    }

    #[test]
    fn the_size_limit_is_checked_before_decoding() {
        let bytes = exr_with(16, 16, &["B", "G", "R"]);
        let err = decode_pass_with_limit(&bytes, 255).unwrap_err();
        assert_eq!(
            err.to_string(),
            "the pass is 16x16, more than the 255 pixels allowed"
        );
        assert!(decode_pass_with_limit(&bytes, 256).is_ok());
    }

    #[test]
    fn a_size_mismatch_names_both_sizes() {
        let pass = Pass {
            width: 64,
            height: 32,
            layer: String::new(),
            aovs: None,
            rgb: vec![[0.0; 3]; 64 * 32],
        };
        assert!(pass.check(64, 32).is_ok());
        assert_eq!(
            pass.check(128, 128).unwrap_err().to_string(),
            "pass is 64x32 but the frame is 128x128"
        );
    }

    #[test]
    fn negative_and_nan_samples_pass_through() {
        let pass = Pass {
            width: 2,
            height: 1,
            layer: String::new(),
            aovs: None,
            rgb: vec![[-1.0, f32::NAN, f32::INFINITY], [0.0; 3]],
        };
        let r: Vec<Record> = pass.records().collect();
        assert_eq!(r[0].rgb[0], -1.0);
        assert!(r[0].rgb[1].is_nan());
        assert_eq!(r[0].rgb[2], f32::INFINITY);
    }

    #[test]
    fn records_never_leave_the_pass() {
        let pass = Pass {
            width: 0,
            height: 5,
            layer: String::new(),
            aovs: None,
            rgb: vec![[1.0; 3]; 3],
        };
        assert_eq!(pass.records().count(), 0);
        let pass = Pass {
            width: 2,
            height: 1,
            layer: String::new(),
            aovs: None,
            rgb: vec![[1.0; 3]; 3],
        };
        assert_eq!(pass.records().count(), 2);
    }

    fn layer(name: &str, part: usize, channels: &[&str]) -> LayerInfo {
        let rgb = ["R", "G", "B"].iter().all(|c| channels.contains(c));
        LayerInfo {
            name: name.to_string(),
            part,
            prefix: name.to_string(),
            channels: channels.iter().map(|c| c.to_string()).collect(),
            rgb,
        }
    }

    #[test]
    fn the_beauty_is_found_in_the_documented_order() {
        let rgb = ["R", "G", "B"];
        let albedo = layer("ViewLayer.DiffCol", 0, &rgb);
        let depth = layer("ViewLayer.Depth", 0, &["Z"]);
        let cycles = layer("ViewLayer.Combined", 0, &["A", "B", "G", "R"]);
        let unnamed = layer("", 0, &rgb);
        let beauty = layer("BEAUTY", 1, &rgb);
        let pick =
            |layers: &[LayerInfo]| choose_beauty(layers, None).map(|i| layers[i].name.clone());
        // 1. unprefixed RGB before everything else
        let all = [
            albedo.clone(),
            beauty.clone(),
            cycles.clone(),
            unnamed.clone(),
        ];
        assert_eq!(pick(&all).unwrap(), "");
        // 2. Cycles' <view layer>.Combined before a layer named beauty
        let all = [
            albedo.clone(),
            beauty.clone(),
            cycles.clone(),
            depth.clone(),
        ];
        assert_eq!(pick(&all).unwrap(), "ViewLayer.Combined");
        // 3. beauty, rgba, Combined, in any case
        let all = [albedo.clone(), depth.clone(), beauty.clone()];
        assert_eq!(pick(&all).unwrap(), "BEAUTY");
        // 4. the only RGB layer
        let all = [depth.clone(), albedo.clone()];
        assert_eq!(pick(&all).unwrap(), "ViewLayer.DiffCol");
        // Two view layers: nothing is guessed.
        let other = layer("Background.Combined", 0, &rgb);
        let err = pick(&[cycles.clone(), other]).unwrap_err();
        assert!(
            err.to_string().starts_with(
                "the EXR has several layers that could be the beauty \
                 (\"ViewLayer.Combined\", \"Background.Combined\"); name the one to use"
            ),
            "{err}"
        );
        // Two RGB AOVs and no beauty name: refused, naming them.
        let normal = layer("N", 0, &rgb);
        let err = pick(&[albedo.clone(), normal, depth.clone()]).unwrap_err();
        assert!(matches!(&err, PassError::Ambiguous { candidates, .. } if candidates.len() == 2));
        // A depth-only file: no RGB at all.
        let err = pick(std::slice::from_ref(&depth)).unwrap_err();
        assert_eq!(
            err.to_string(),
            "the EXR has no layer with channels R, G and B; layers found: \"ViewLayer.Depth\" (Z)"
        );
    }

    #[test]
    fn a_named_layer_is_taken_as_asked_or_refused_by_name() {
        let rgb = ["R", "G", "B"];
        let all = [
            layer("", 0, &rgb),
            layer("diffuse", 0, &rgb),
            layer("Z", 0, &["Z"]),
        ];
        assert_eq!(choose_beauty(&all, Some("diffuse")).unwrap(), 1);
        assert_eq!(choose_beauty(&all, Some("")).unwrap(), 0);
        let err = choose_beauty(&all, Some("Diffuse")).unwrap_err();
        assert_eq!(
            err.to_string(),
            "the EXR has no layer \"Diffuse\"; layers found: unnamed (R, G, B); \
             \"diffuse\" (R, G, B); \"Z\" (Z)"
        );
        let err = choose_beauty(&all, Some("Z")).unwrap_err();
        assert_eq!(
            err.to_string(),
            "layer \"Z\" (Z) cannot be the beauty: it needs flat channels R, G and B"
        );
    }

    #[test]
    fn layer_names_join_part_and_prefix_once() {
        assert_eq!(layer_name(None, "ViewLayer.Combined"), "ViewLayer.Combined");
        assert_eq!(layer_name(Some("beauty"), ""), "beauty");
        assert_eq!(layer_name(Some("beauty"), "beauty"), "beauty");
        assert_eq!(
            layer_name(Some("ViewLayer"), "ViewLayer.Combined"),
            "ViewLayer.Combined"
        );
        assert_eq!(layer_name(Some("aovs"), "albedo"), "aovs.albedo");
        assert_eq!(layer_name(Some(""), "albedo"), "albedo");
    }

    #[test]
    fn only_the_named_layer_is_read_from_a_single_part_file() {
        // Channels sorted: albedo.B, albedo.G, albedo.R, B, G, R (value = pixel * 10 + index).
        let bytes = exr_with(3, 2, &["albedo.B", "albedo.G", "albedo.R", "B", "G", "R"]);
        let pass = decode_pass_with(&bytes, Some("albedo"), MAX_PASS_PIXELS).unwrap();
        assert_eq!(pass.layer, "albedo");
        assert_eq!(pass.rgb[1], [12.0, 11.0, 10.0]);
        let pass = decode_pass(&bytes).unwrap();
        assert_eq!(pass.layer, "");
        assert_eq!(pass.rgb[1], [15.0, 14.0, 13.0]);
    }
}
