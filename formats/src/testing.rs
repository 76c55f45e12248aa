//! Files for tests of the formats' users (the server's tests among them): built with the
//! `testing` feature.

use exr::prelude::*;

/// An uncompressed RGB float EXR of `width x height` pixels, pixel `i` (row-major) `rgb(i)`.
pub fn uncompressed_rgb(width: usize, height: usize, rgb: impl Fn(usize) -> [f32; 3]) -> Vec<u8> {
    uncompressed_with_aovs(width, height, rgb, &[])
}

/// [`uncompressed_rgb`] with AOV channels beside the beauty's: each a full channel name
/// (`albedo.R`) and one value per pixel, row-major.
pub fn uncompressed_with_aovs(
    width: usize,
    height: usize,
    rgb: impl Fn(usize) -> [f32; 3],
    aovs: &[(&str, Vec<f32>)],
) -> Vec<u8> {
    let values = |c: usize| (0..width * height).map(|i| rgb(i)[c]).collect();
    let mut channels = vec![
        AnyChannel::new("R", FlatSamples::F32(values(0))),
        AnyChannel::new("G", FlatSamples::F32(values(1))),
        AnyChannel::new("B", FlatSamples::F32(values(2))),
    ];
    channels.extend(
        aovs.iter()
            .map(|(name, values)| AnyChannel::new(*name, FlatSamples::F32(values.clone()))),
    );
    let layer = Layer::new(
        (width, height),
        LayerAttributes::default(),
        Encoding::UNCOMPRESSED,
        AnyChannels::sort(SmallVec::from_vec(channels)),
    );
    let mut bytes = Vec::new();
    Image::from_layer(layer)
        .write()
        .to_buffered(std::io::Cursor::new(&mut bytes))
        .unwrap();
    bytes
}
