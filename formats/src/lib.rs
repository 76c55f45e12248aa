//! splatd's formats, shared by the server and the `splatd` command: what goes in and out of a
//! frame as bytes, and nothing else (no I/O beyond the buffers handed in, no HTTP, no async).
//!
//! * [`exr`]: the resolved OpenEXR image (`image.exr`: the reweighted beauty, `mean`,
//!   `removed`, `spp`, cascades, AOVs, a denoised layer) and its provenance attributes;
//! * [`passes`]: whole passes in, OpenEXR (and raw float) images decoded into records and AOV
//!   values;
//! * [`state`]: frame states to and from their wire form, for exports, imports, pushes,
//!   snapshots and the offline merge;
//! * [`preview`]: the live page's tone-mapped PNG;
//! * [`names`]: which AOV and channel names an OpenEXR file can hold;
//! * [`scratch`]: buffers kept between requests, for decoding passes and encoding images.

pub mod exr;
pub mod names;
pub mod passes;
pub mod preview;
pub mod scratch;
pub mod state;
#[cfg(any(test, feature = "testing"))]
pub mod testing;
