//! Files for tests of the formats' users (the server's tests among them): built with the
//! `testing` feature.

use exr::prelude::*;

/// An uncompressed RGB float EXR of `width x height` pixels, pixel `i` (row-major) `rgb(i)`.
pub fn uncompressed_rgb(width: usize, height: usize, rgb: impl Fn(usize) -> [f32; 3]) -> Vec<u8> {
    let values = |c: usize| (0..width * height).map(|i| rgb(i)[c]).collect();
    let layer = Layer::new(
        (width, height),
        LayerAttributes::default(),
        Encoding::UNCOMPRESSED,
        AnyChannels::sort(SmallVec::from_vec(vec![
            AnyChannel::new("R", FlatSamples::F32(values(0))),
            AnyChannel::new("G", FlatSamples::F32(values(1))),
            AnyChannel::new("B", FlatSamples::F32(values(2))),
        ])),
    );
    let mut bytes = Vec::new();
    Image::from_layer(layer)
        .write()
        .to_buffered(std::io::Cursor::new(&mut bytes))
        .unwrap();
    bytes
}
