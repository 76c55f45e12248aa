//! Where splatd's firefly-heavy samples come from when no farm is attached: the demo, the tests and
//! the benchmarks use this crate; the server does not.
//!
//! * [`tracer`]: a compact path tracer of one built-in scene with real fireflies (caustics through
//!   a glass sphere, a small bright lamp), rendered pass by pass with any seed;
//! * [`synth`]: synthetic streams with an exactly known per-pixel mean (heavy-tailed, caustic-like
//!   and tame regions), a pure function of `(seed, pass, x, y)`;
//! * [`anchors`]: the robust estimators the resolve is benchmarked against (clamp, MoN, G-MoN);
//! * [`quality`]: the error metrics every benchmark and test reports (relMSE, energy bias);
//! * [`hostile`]: bodies careless or hostile clients send (a zstd bomb).
pub mod anchors;
pub mod hostile;
pub mod quality;
pub mod synth;
pub mod tracer;
