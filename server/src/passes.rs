//! Sample passes as OpenEXR files, for renderers that cannot stream samples.
//!
//! Cycles, Arnold, Mitsuba and pbrt write images, not sample streams. Rendered with one sample
//! per pixel and a different seed each time, every image they write is one *pass*: each pixel
//! of a pass is **one** Monte Carlo sample of that pixel. [`decode_pass`] reads such a file and
//! [`Pass::records`] turns it into the same [`Record`]s a streaming worker would send, so a pass
//! is accumulated exactly like a batch of `width * height` samples.
//!
//! What is read: the `R`, `G` and `B` channels of the first layer (part) that has all three, as
//! 32-bit floats whatever their stored type (`f16`, `f32` or `u32`). Alpha and every other
//! channel are ignored. The pass must cover exactly its display window: a cropped (border)
//! render or an overscan would put its pixels at the wrong place in the frame, so it is refused
//! rather than guessed at.
//!
//! What is **not** done: values are not checked. Negative, NaN and infinite samples pass through
//! unchanged; the server rejects and counts them with the same checks it applies to streamed
//! samples ([`splatd_estimator::check_sample`]), so a pass and a batch are treated identically.
//!
//! Decoding is CPU work (`exr` decompresses blocks on a thread pool it starts per call): from
//! async code call [`decode_pass`] inside `spawn_blocking`.

use std::io::Cursor;

use exr::meta::attribute::IntegerBounds;
use exr::meta::header::Header;
use exr::meta::MetaData;
use exr::prelude::{read, ReadChannels, ReadLayers};
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

/// One pass: one sample per pixel, decoded from an EXR.
#[derive(Debug, Clone, PartialEq)]
pub struct Pass {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Row-major RGB samples, top row first, `width * height` of them. Not checked: negative,
    /// NaN and infinite values are kept (see the module docs).
    pub rgb: Vec<[f32; 3]>,
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
    #[error("the EXR has no layer with channels R, G and B; {}", describe_layers(.layers))]
    NoRgbLayer {
        /// The channel names of every layer, in file order.
        layers: Vec<Vec<String>>,
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

fn describe_layers(layers: &[Vec<String>]) -> String {
    let list = |names: &Vec<String>| {
        if names.is_empty() {
            "no channels".to_string()
        } else {
            names.join(", ")
        }
    };
    match layers {
        [] => "it has no layers".to_string(),
        [one] => format!("channels found: {}", list(one)),
        many => {
            let parts: Vec<String> = many
                .iter()
                .enumerate()
                .map(|(i, names)| format!("layer {i}: {}", list(names)))
                .collect();
            format!("channels found: {}", parts.join("; "))
        }
    }
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

/// Decodes one pass from the bytes of an EXR file, with the default size limit
/// [`MAX_PASS_PIXELS`].
///
/// Reads `R`, `G`, `B` of the first layer that has all three (see the module docs for what is
/// accepted and what is refused). Values are not checked.
///
/// # Errors
/// [`PassError::NotExr`] for bytes that are not EXR, [`PassError::Exr`] for an EXR that cannot
/// be read, [`PassError::NoRgbLayer`] (listing the channels present), [`PassError::Empty`],
/// [`PassError::TooLarge`] and [`PassError::Window`].
pub fn decode_pass(bytes: &[u8]) -> Result<Pass, PassError> {
    decode_pass_with_limit(bytes, MAX_PASS_PIXELS)
}

/// [`decode_pass`] with a caller-chosen limit on the pass's pixel count, for example the size
/// of the frame the pass is for.
pub fn decode_pass_with_limit(bytes: &[u8], max_pixels: u64) -> Result<Pass, PassError> {
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

    // The header alone first: the layer's size is checked before anything is allocated.
    let meta = MetaData::read_from_buffered(Cursor::new(bytes), false)?;
    let header = meta
        .headers
        .iter()
        .find(|h| !h.deep && has_rgb(h))
        .ok_or_else(|| PassError::NoRgbLayer {
            layers: meta
                .headers
                .iter()
                .map(|h| h.channels.list.iter().map(|c| c.name.to_string()).collect())
                .collect(),
        })?;
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

    // `first_valid_layer` takes the first layer the RGB reader accepts: the one found above.
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .rgb_channels(
            |size, _| RgbBuffer {
                width: size.width(),
                rgb: vec![[0.0; 3]; size.area()],
                writes: vec![0; size.area()],
            },
            |buffer: &mut RgbBuffer, at, (r, g, b): (f32, f32, f32)| {
                let i = at.y() * buffer.width + at.x();
                if let (Some(px), Some(n)) = (buffer.rgb.get_mut(i), buffer.writes.get_mut(i)) {
                    *px = [r, g, b];
                    *n = n.saturating_add(1);
                }
            },
        )
        .first_valid_layer()
        .all_attributes()
        .from_buffered(Cursor::new(bytes))?;
    let layer = image.layer_data;
    let buffer = layer.channel_data.pixels;
    // The header read twice must describe the same layer; anything else is a corrupt file.
    if layer.size.width() != w || layer.size.height() != h || buffer.rgb.len() != w * h {
        return Err(PassError::Exr(exr::error::Error::Invalid(
            "the RGB layer's size changed between the header and the pixel data".into(),
        )));
    }
    buffer.check_coverage()?;
    Ok(Pass {
        width,
        height,
        rgb: buffer.rgb,
    })
}

/// Whether a layer has the three channels a pass needs.
fn has_rgb(header: &Header) -> bool {
    ["R", "G", "B"]
        .iter()
        .all(|name| header.channels.list.iter().any(|c| c.name.eq(name)))
}

/// Pixel storage while `exr` decodes.
struct RgbBuffer {
    width: usize,
    rgb: Vec<[f32; 3]>,
    /// How often each pixel was written. `exr` decodes whatever blocks the offset table points
    /// at, so a table that names one block twice leaves another block's pixels at their initial
    /// zeros without an error; counting writes is what proves each pixel came from its own data
    /// exactly once.
    writes: Vec<u8>,
}

impl RgbBuffer {
    fn check_coverage(&self) -> Result<(), PassError> {
        let (mut missing, mut repeated, mut first_missing) = (0u64, 0u64, None);
        for (i, &n) in self.writes.iter().enumerate() {
            match n {
                1 => {}
                0 => {
                    missing += 1;
                    first_missing.get_or_insert(i / self.width.max(1));
                }
                _ => repeated += 1,
            }
        }
        match first_missing {
            None if repeated == 0 => Ok(()),
            _ => Err(PassError::Coverage {
                missing,
                repeated,
                pixels: self.writes.len() as u64,
                first_missing_row: first_missing.unwrap_or(0) as u64,
            }),
        }
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
mod tests {
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
            PassError::NoRgbLayer { layers } => assert_eq!(layers, &[vec!["Y".to_string()]]),
            other => panic!("expected NoRgbLayer, got {other:?}"),
        }
        assert_eq!(
            err.to_string(),
            "the EXR has no layer with channels R, G and B; channels found: Y"
        );
    }

    #[test]
    fn a_missing_blue_channel_is_refused_naming_the_ones_present() {
        let err = decode_pass(&exr_with(4, 3, &["A", "G", "R"])).unwrap_err();
        assert!(
            err.to_string().ends_with("channels found: A, G, R"),
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
    fn uncompressed(width: usize, height: usize) -> Vec<u8> {
        let values = |c: usize| (0..width * height).map(|i| (i * 10 + c) as f32).collect();
        let layer = Layer::new(
            (width, height),
            LayerAttributes::default(),
            Encoding::UNCOMPRESSED,
            AnyChannels::sort(SmallVec::from_vec(vec![
                AnyChannel::new("B", FlatSamples::F32(values(1))),
                AnyChannel::new("G", FlatSamples::F32(values(2))),
                AnyChannel::new("R", FlatSamples::F32(values(3))),
            ])),
        );
        let mut bytes = Vec::new();
        Image::from_layer(layer)
            .write()
            .to_buffered(std::io::Cursor::new(&mut bytes))
            .unwrap();
        bytes
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
            rgb: vec![[1.0; 3]; 3],
        };
        assert_eq!(pass.records().count(), 0);
        let pass = Pass {
            width: 2,
            height: 1,
            rgb: vec![[1.0; 3]; 3],
        };
        assert_eq!(pass.records().count(), 2);
    }
}
