//! Tone mapping and PNG encoding, for previews and the demo's side-by-side picture.
//!
//! A resolved frame is linear, unbounded radiance; a preview is 8-bit sRGB. [`tonemap`] does the
//! conversion: multiply by an exposure, compress highlights with a filmic curve (Narkowicz's
//! fit of the ACES reference rendering transform) and apply the sRGB transfer function.
//! [`auto_exposure`] picks an exposure from the median luminance, which fireflies cannot move:
//! computed once (say, from the reweighted image) and applied to every image of a comparison,
//! it shows the mean and the reweighted estimate on the same scale. [`side_by_side`] puts
//! images next to each other and [`encode_png`] writes 8-bit RGB PNG bytes.
//!
//! Everything here is pure: bytes are returned, never written.

/// The colour of the gap between panels of [`side_by_side`]: dark grey, so that a black image
/// edge is still visible.
pub const GAP_COLOUR: [u8; 3] = [40, 40, 40];

/// Linear value the median luminance is mapped to by [`auto_exposure`]: a little above the
/// photographic mid grey (0.18), because the filmic curve darkens mid-tones somewhat.
pub const AUTO_EXPOSURE_KEY: f32 = 0.3;

/// Largest linear value (after exposure) that is tone mapped as such; anything brighter maps to
/// white anyway, and clamping keeps the curve's `x^2` from overflowing to `inf / inf`.
const MAX_LINEAR: f32 = 1e4;

/// Why a preview could not be encoded.
#[derive(Debug, thiserror::Error)]
pub enum PreviewError {
    /// Width or height is 0; PNG cannot store an empty image.
    #[error("cannot encode a {width}x{height} image: PNG needs at least one pixel")]
    Empty {
        /// The width given.
        width: u32,
        /// The height given.
        height: u32,
    },
    /// The pixel buffer does not hold `width * height` pixels.
    #[error("a {width}x{height} image needs {expected} pixels, got {actual}")]
    SizeMismatch {
        /// The width given.
        width: u32,
        /// The height given.
        height: u32,
        /// `width * height`.
        expected: u64,
        /// The pixels given.
        actual: usize,
    },
    /// The PNG encoder failed.
    #[error("PNG encoding failed: {0}")]
    Png(#[from] png::EncodingError),
}

/// Rec. 709 / sRGB luminance of linear RGB.
#[inline]
fn luminance(c: [f32; 3]) -> f32 {
    splatd_estimator::rec709_luminance(c.map(f64::from)) as f32
}

/// Narkowicz's ACES filmic fit, for `x >= 0`; monotonic, 0 at 0, reaching 1 near `x = 16`.
#[inline]
fn filmic(x: f32) -> f32 {
    let (a, b, c, d, e) = (2.51, 0.03, 2.43, 0.59, 0.14);
    ((x * (a * x + b)) / (x * (c * x + d) + e)).clamp(0.0, 1.0)
}

/// The sRGB opto-electronic transfer function (IEC 61966-2-1), for `v` in `[0, 1]`.
#[inline]
fn srgb_oetf(v: f32) -> f32 {
    if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

/// One linear channel value, already multiplied by the exposure, to an 8-bit sRGB code.
#[inline]
fn encode_channel(v: f32) -> u8 {
    // `>` is false for NaN, so NaN (and negatives) become 0; +inf is clamped to white.
    let v = if v > 0.0 { v.min(MAX_LINEAR) } else { 0.0 };
    // In [0, 255] by construction (filmic clamps to [0, 1]), so the cast cannot saturate.
    (srgb_oetf(filmic(v)) * 255.0).round() as u8
}

/// Tone maps linear RGB to 8-bit sRGB: `exposure` multiply, filmic highlight compression per
/// channel, then the sRGB transfer function.
///
/// Black stays black and very bright values become white (255). NaN, negative and (after the
/// exposure) zero values become 0; `+inf` becomes 255. A non-finite or negative `exposure`
/// gives black wherever the product is NaN or negative.
pub fn tonemap(rgb: &[[f32; 3]], exposure: f32) -> Vec<[u8; 3]> {
    rgb.iter()
        .map(|p| p.map(|c| encode_channel(c * exposure)))
        .collect()
}

/// An exposure for [`tonemap`] that maps the median luminance of `rgb` to
/// [`AUTO_EXPOSURE_KEY`].
///
/// The median ignores fireflies and small bright lights entirely, so the exposure of a noisy
/// mean image and of its reweighted version are nearly the same; for a fair comparison compute
/// it once and use it for both. Only finite, positive luminances count; if there are none
/// (an empty or black image) the exposure is 1.
pub fn auto_exposure(rgb: &[[f32; 3]]) -> f32 {
    let mut lum: Vec<f32> = rgb
        .iter()
        .map(|&p| luminance(p))
        .filter(|l| l.is_finite() && *l > 0.0)
        .collect();
    if lum.is_empty() {
        return 1.0;
    }
    let mid = lum.len() / 2;
    let (_, median, _) = lum.select_nth_unstable_by(mid, f32::total_cmp);
    let exposure = AUTO_EXPOSURE_KEY / *median;
    // A median of a subnormal luminance would overflow the exposure to infinity.
    if exposure.is_finite() {
        exposure
    } else {
        1.0
    }
}

/// Encodes `pixels` (row-major, top row first, `width * height` of them) as an 8-bit RGB PNG.
pub fn encode_png(width: u32, height: u32, pixels: &[[u8; 3]]) -> Result<Vec<u8>, PreviewError> {
    if width == 0 || height == 0 {
        return Err(PreviewError::Empty { width, height });
    }
    let expected = u64::from(width) * u64::from(height);
    if pixels.len() as u64 != expected {
        return Err(PreviewError::SizeMismatch {
            width,
            height,
            expected,
            actual: pixels.len(),
        });
    }
    // Previews are small next to the frames they show: worth fast compression, not best.
    let mut bytes = Vec::with_capacity(pixels.len() + 1024);
    let mut encoder = png::Encoder::new(&mut bytes, width, height);
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Fast);
    // The bytes are sRGB-encoded; say so, so that viewers do not guess.
    encoder.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
    let mut writer = encoder.write_header()?;
    writer.write_image_data(pixels.as_flattened())?;
    writer.finish()?;
    Ok(bytes)
}

/// Places `panels`, each `width` x `height` pixels, left to right with `gap` columns of
/// [`GAP_COLOUR`] between neighbours. Returns the combined width, height and pixels.
///
/// No panels give a `0` x `height` image.
///
/// # Panics
/// If a panel does not hold exactly `width * height` pixels (a caller's bug: panels come from
/// images of one frame), or if the combined width overflows `u32`.
pub fn side_by_side(
    width: u32,
    height: u32,
    panels: &[&[[u8; 3]]],
    gap: u32,
) -> (u32, u32, Vec<[u8; 3]>) {
    let panel_len = width as usize * height as usize;
    for (i, panel) in panels.iter().enumerate() {
        assert_eq!(
            panel.len(),
            panel_len,
            "panel {i} has {} pixels, not {width}x{height}",
            panel.len()
        );
    }
    let n = panels.len() as u32;
    let total_width = n
        .checked_mul(width)
        .and_then(|w| w.checked_add(n.saturating_sub(1).checked_mul(gap)?))
        .expect("side-by-side width overflows u32");
    let mut out = Vec::with_capacity(total_width as usize * height as usize);
    for y in 0..height as usize {
        for (i, panel) in panels.iter().enumerate() {
            if i > 0 {
                out.extend(std::iter::repeat_n(GAP_COLOUR, gap as usize));
            }
            let row = y * width as usize;
            out.extend_from_slice(&panel[row..row + width as usize]);
        }
    }
    (total_width, height, out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode(bytes: &[u8]) -> (u32, u32, Vec<u8>) {
        let decoder = png::Decoder::new(bytes);
        let mut reader = decoder.read_info().expect("PNG header decodes");
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).expect("PNG image decodes");
        assert_eq!(info.color_type, png::ColorType::Rgb);
        assert_eq!(info.bit_depth, png::BitDepth::Eight);
        buf.truncate(info.buffer_size());
        (info.width, info.height, buf)
    }

    #[test]
    fn png_bytes_decode_to_the_same_size_and_pixels() {
        let (w, h) = (7u32, 5u32);
        let pixels: Vec<[u8; 3]> = (0..w * h)
            .map(|i| [(i * 37) as u8, (i * 11 + 3) as u8, (255 - i * 5) as u8])
            .collect();
        let bytes = encode_png(w, h, &pixels).expect("encodes");
        assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
        let (dw, dh, data) = decode(&bytes);
        assert_eq!((dw, dh), (w, h));
        assert_eq!(data, pixels.as_flattened());
    }

    #[test]
    fn png_refuses_empty_and_mis_sized_images() {
        assert!(matches!(
            encode_png(0, 3, &[]),
            Err(PreviewError::Empty {
                width: 0,
                height: 3
            })
        ));
        let err = encode_png(2, 2, &[[0; 3]; 3]).expect_err("3 pixels are not 2x2");
        assert!(matches!(
            err,
            PreviewError::SizeMismatch {
                expected: 4,
                actual: 3,
                ..
            }
        ));
        assert_eq!(err.to_string(), "a 2x2 image needs 4 pixels, got 3");
    }

    #[test]
    fn tonemap_is_monotonic_from_black_to_white() {
        assert_eq!(tonemap(&[[0.0; 3]], 1.0), vec![[0; 3]]);
        assert_eq!(tonemap(&[[1e30, f32::INFINITY, 5e3]], 1.0), vec![[255; 3]]);
        assert_eq!(tonemap(&[[1.0; 3]], 1e9), vec![[255; 3]]);
        let mut last = 0u8;
        let mut v = 1e-6f32;
        while v < 1e6 {
            let code = tonemap(&[[v; 3]], 1.0)[0][0];
            assert!(
                code >= last,
                "tonemap({v}) = {code} < {last}, the code of a smaller value"
            );
            last = code;
            v *= 1.01;
        }
        assert_eq!(last, 255);
        // Exposure scales the input.
        assert_eq!(tonemap(&[[0.5; 3]], 2.0), tonemap(&[[1.0; 3]], 1.0));
        // Mid-tones stay mid-tones.
        let mid = tonemap(&[[AUTO_EXPOSURE_KEY; 3]], 1.0)[0][0];
        assert!((80..200).contains(&mid), "the key value maps to code {mid}");
    }

    #[test]
    fn tonemap_turns_nan_and_negative_into_black() {
        assert_eq!(
            tonemap(&[[f32::NAN, -1.0, f32::NEG_INFINITY]], 1.0),
            vec![[0; 3]]
        );
        assert_eq!(tonemap(&[[1.0, f32::NAN, 1.0]], 1.0)[0][1], 0);
        assert_eq!(tonemap(&[[1.0; 3]], f32::NAN), vec![[0; 3]]);
        assert_eq!(tonemap(&[[0.0; 3]], f32::INFINITY), vec![[0; 3]]);
    }

    #[test]
    fn auto_exposure_follows_the_median_and_ignores_fireflies() {
        // 0 (ignored: not positive), then 0.01 .. 1.01: the median is 0.51.
        let base: Vec<[f32; 3]> = (0..=101).map(|i| [i as f32 / 100.0; 3]).collect();
        let e = auto_exposure(&base);
        assert!((e - AUTO_EXPOSURE_KEY / 0.51).abs() < 1e-5, "exposure {e}");
        let mut fireflies = base.clone();
        for p in fireflies.iter_mut().step_by(10) {
            *p = [1e6; 3];
        }
        fireflies.push([f32::NAN; 3]);
        fireflies.push([f32::INFINITY; 3]);
        let ef = auto_exposure(&fireflies);
        assert!(
            (ef / e - 1.0).abs() < 0.15,
            "11 fireflies moved the exposure from {e} to {ef}"
        );
        assert_eq!(auto_exposure(&[]), 1.0);
        assert_eq!(auto_exposure(&[[0.0; 3], [f32::NAN; 3]]), 1.0);
        assert_eq!(auto_exposure(&[[1e-45; 3]]), 1.0, "a subnormal median");
    }

    #[test]
    fn side_by_side_places_panels_left_to_right_with_gaps() {
        let (w, h) = (3u32, 2u32);
        let a: Vec<[u8; 3]> = (0..6).map(|i| [i, 0, 0]).collect();
        let b: Vec<[u8; 3]> = (0..6).map(|i| [0, i, 0]).collect();
        let c: Vec<[u8; 3]> = (0..6).map(|i| [0, 0, i]).collect();
        let (tw, th, px) = side_by_side(w, h, &[&a, &b, &c], 2);
        assert_eq!((tw, th), (3 * 3 + 2 * 2, 2));
        assert_eq!(px.len(), (tw * th) as usize);
        let at = |x: u32, y: u32| px[(y * tw + x) as usize];
        for y in 0..h {
            for x in 0..w {
                let i = (y * w + x) as u8;
                assert_eq!(at(x, y), [i, 0, 0], "panel 0 at ({x}, {y})");
                assert_eq!(at(x + 5, y), [0, i, 0], "panel 1 at ({x}, {y})");
                assert_eq!(at(x + 10, y), [0, 0, i], "panel 2 at ({x}, {y})");
            }
            for gx in [3, 4, 8, 9] {
                assert_eq!(at(gx, y), GAP_COLOUR, "gap column {gx}, row {y}");
            }
        }
        let (tw, th, px) = side_by_side(w, h, &[&a], 5);
        assert_eq!((tw, th, px), (3, 2, a.clone()), "one panel needs no gap");
        let (tw, th, px) = side_by_side(w, h, &[], 5);
        assert_eq!((tw, th, px.len()), (0, 2, 0));
    }

    #[test]
    #[should_panic(expected = "panel 1 has 5 pixels, not 3x2")]
    fn side_by_side_refuses_a_mis_sized_panel() {
        side_by_side(3, 2, &[&[[0; 3]; 6], &[[0; 3]; 5]], 1);
    }
}
