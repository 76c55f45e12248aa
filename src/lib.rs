//! splatd: render-farm workers stream Monte Carlo samples in; frames with the fireflies taken out
//! come back.
//!
//! * [`core`] is the estimator (cascade splat, exact merge, reweighted resolve). It is pure and
//!   could be published on its own; everything else is a shell around it.
//! * [`synth`] generates deterministic firefly-heavy sample streams with an exactly known mean,
//!   for the offline demo, the tests and the benchmarks.
//! * [`image`] writes resolved frames as multi-layer OpenEXR.
//! * [`export`] turns frame states into their wire form and back, for merging nodes.
//! * [`quality`] holds the error metrics of the demo, tests and benchmarks.
pub mod batchfile;
pub mod core;
pub mod demo;
pub mod export;
pub mod image;
pub mod passes;
pub mod preview;
pub mod quality;
pub mod service;
pub mod synth;
pub mod tev;
pub mod tracer;
