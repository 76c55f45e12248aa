//! What splatd hands a denoiser (Intel Open Image Denoise) and how it builds the final frame
//! from the denoiser's outputs.
//!
//! A studio ships the frame after the denoiser, so the resolve that is best on its own (the
//! default `spread`) is not what the denoiser should see: `spread` gives removed energy back
//! blurred over windows up to 17x17, which correlates neighbouring pixels, and OIDN's own
//! documentation warns that correlated pixels make denoising fail. A [`DenoisePlan`] resolves
//! the frame its own way, lists the images to denoise ([`DenoisePlan::inputs`]), and combines
//! the denoised images into the final ([`DenoisePlan::combine`]). The estimator stays pure: the
//! caller runs the denoiser. See docs/ALGORITHM.md, "The denoiser's input".
//!
//! The designs ([`DenoiseDesign`]; the name goes into the EXR header's provenance) are measured
//! by the quality benchmark's denoised table; [`DEFAULT_DENOISE_DESIGN`] is what
//! [`DenoisePlan::new`] uses. None spreads energy over neighbouring pixels before the denoiser.

use crate::resolve::{resolve_bands, ResolveParams, Resolved, Variant};
use crate::state::FrameState;

/// The denoiser's inputs for one frame and what is needed to combine its outputs.
#[derive(Debug, Clone)]
pub struct DenoisePlan {
    width: usize,
    height: usize,
    inputs: Vec<Vec<[f32; 3]>>,
    design: DenoiseDesign,
    /// The luminance weights of the frame's layout.
    weights: [f64; 3],
}

/// The ways of building the denoiser's input that the quality benchmark compares; one of them,
/// [`DEFAULT_DENOISE_DESIGN`], is what [`DenoisePlan::new`] uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DenoiseDesign {
    /// One input, the paper's resolve (the frame's `kappa` settings); the final is its
    /// denoised image.
    Paper,
    /// Two inputs, the paper's resolve and the plain mean; the final is the denoised paper's
    /// image with the denoised mean's local energy: multiplied per pixel by the ratio of the
    /// two denoised images' luminance summed over a `(2 RATIO_RADIUS + 1)^2` window, clamped
    /// to `[1, RATIO_CAP]`. The energy the paper removed comes back after the denoiser (the
    /// inputs stay uncorrelated), where the denoised mean put it, at a scale of a few pixels;
    /// the cap bounds what one firefly's blotch can add around it.
    PaperRatio,
    /// [`PaperRatio`](Self::PaperRatio) with the paper's resolve at a fixed `kappa = 2`
    /// (`kappa_exponent = 0`, the frame's `kappa_min`): it removes less before the denoiser.
    MildRatio,
    /// [`PaperRatio`](Self::PaperRatio) with a fixed `kappa = 1`: removes less still.
    GentleRatio,
}

/// The design [`DenoisePlan::new`] uses, chosen by the quality benchmark (docs/ALGORITHM.md).
pub const DEFAULT_DENOISE_DESIGN: DenoiseDesign = DenoiseDesign::MildRatio;

/// The ratio designs' window radius (5x5), chosen by a sweep of 2, 4, 8 (docs/ALGORITHM.md).
pub const RATIO_RADIUS: usize = 2;
/// The ratio designs' largest gain, chosen by a sweep of 1.1, 1.25, 1.5
/// and none.
pub const RATIO_CAP: f64 = 1.5;

impl DenoiseDesign {
    /// Every design, in declaration order.
    pub const ALL: [DenoiseDesign; 4] = [
        DenoiseDesign::Paper,
        DenoiseDesign::PaperRatio,
        DenoiseDesign::MildRatio,
        DenoiseDesign::GentleRatio,
    ];

    /// The design's name (what [`DenoisePlan::name`] returns).
    pub fn name(self) -> &'static str {
        match self {
            DenoiseDesign::Paper => "paper",
            DenoiseDesign::PaperRatio => "paper+ratio",
            DenoiseDesign::MildRatio => "paper(kappa=2)+ratio",
            DenoiseDesign::GentleRatio => "paper(kappa=1)+ratio",
        }
    }

    /// How many images the design hands the denoiser (the length of [`DenoisePlan::inputs`]).
    pub fn images(self) -> usize {
        match self {
            DenoiseDesign::Paper => 1,
            DenoiseDesign::PaperRatio | DenoiseDesign::MildRatio | DenoiseDesign::GentleRatio => 2,
        }
    }

    /// The paper's resolve this design hands the denoiser, from the frame's parameters.
    pub fn paper_params(self, params: &ResolveParams) -> ResolveParams {
        let fixed = |kappa| {
            ResolveParams::new(Variant::Paper, kappa, params.kappa_min(), 0.0).expect("valid kappa")
        };
        match self {
            DenoiseDesign::Paper | DenoiseDesign::PaperRatio => params.with_variant(Variant::Paper),
            DenoiseDesign::MildRatio => fixed(2.0),
            DenoiseDesign::GentleRatio => fixed(1.0),
        }
    }
}

impl DenoisePlan {
    /// Resolves the frame held by `bands` (as [`resolve_bands`] takes them: in order, tiling the
    /// frame top to bottom) for the denoiser, on `threads` threads, with
    /// [`DEFAULT_DENOISE_DESIGN`]. `params` are the frame's resolve parameters; the plan uses
    /// their `kappa`, `kappa_min` and `kappa_exponent` and chooses its own variant (never one
    /// that spreads energy over neighbouring pixels).
    ///
    /// # Panics
    /// If the bands do not tile one frame (see [`resolve_bands`], which says why).
    pub fn new(bands: &[&FrameState], params: &ResolveParams, threads: usize) -> DenoisePlan {
        Self::with_design(bands, params, threads, DEFAULT_DENOISE_DESIGN)
    }

    /// [`new`](Self::new) with another design (for the quality benchmark's comparison).
    ///
    /// # Panics
    /// If the bands do not tile one frame.
    pub fn with_design(
        bands: &[&FrameState],
        params: &ResolveParams,
        threads: usize,
        design: DenoiseDesign,
    ) -> DenoisePlan {
        let resolved = resolve(bands, &design.paper_params(params), threads);
        let (width, height) = (resolved.width as usize, resolved.height as usize);
        let inputs = match design {
            DenoiseDesign::Paper => vec![resolved.reweighted],
            _ => vec![resolved.reweighted, resolved.mean],
        };
        DenoisePlan {
            width,
            height,
            inputs,
            design,
            weights: bands[0].layout().luminance_weights(),
        }
    }

    /// Width of every input and of the final, in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height of every input and of the final, in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// The images to hand the denoiser, each `width * height` pixels, row-major, top row first,
    /// linear RGB in the samples' units (HDR).
    pub fn inputs(&self) -> &[Vec<[f32; 3]>] {
        &self.inputs
    }

    /// The final frame from the denoiser's outputs, one per input and in the order of
    /// [`inputs`](Self::inputs).
    ///
    /// # Panics
    /// If `denoised` does not hold one image of `width * height` pixels per input.
    pub fn combine(self, denoised: Vec<Vec<[f32; 3]>>) -> Vec<[f32; 3]> {
        assert_eq!(
            denoised.len(),
            self.inputs.len(),
            "one denoised image per input"
        );
        let pixels = self.width * self.height;
        assert!(
            denoised.iter().all(|d| d.len() == pixels),
            "every denoised image has width * height pixels"
        );
        let mut outputs = denoised.into_iter();
        let mut out = outputs.next().expect("one input");
        match self.design {
            DenoiseDesign::Paper => {}
            _ => {
                let mean = outputs.next().expect("two inputs");
                let lum = |img: &[[f32; 3]]| -> Vec<f64> {
                    img.iter()
                        .map(|p| {
                            let l = (0..3).map(|c| self.weights[c] * p[c] as f64).sum::<f64>();
                            // The denoiser may return slightly negative values.
                            l.max(0.0)
                        })
                        .collect()
                };
                let (w, h) = (self.width, self.height);
                let kept = box_sums(&lum(&out), w, h, RATIO_RADIUS);
                let all = box_sums(&lum(&mean), w, h, RATIO_RADIUS);
                for (p, (k, a)) in out.iter_mut().zip(kept.iter().zip(&all)) {
                    let gain = if *k > 0.0 {
                        (a / k).clamp(1.0, RATIO_CAP)
                    } else {
                        1.0
                    };
                    *p = p.map(|v| (v as f64 * gain) as f32);
                }
            }
        }
        out
    }

    /// The design's name, for the EXR header's provenance.
    pub fn name(&self) -> &'static str {
        self.design.name()
    }
}

/// Sums of `values` (a `w x h` plane) over the `(2r + 1)^2` window around every pixel, clamped
/// to the frame: a summed-area table, four lookups per pixel.
fn box_sums(values: &[f64], w: usize, h: usize, r: usize) -> Vec<f64> {
    let mut sat = vec![0.0f64; (w + 1) * (h + 1)];
    for y in 0..h {
        let mut row = 0.0;
        for x in 0..w {
            row += values[y * w + x];
            sat[(y + 1) * (w + 1) + x + 1] = sat[y * (w + 1) + x + 1] + row;
        }
    }
    let mut out = Vec::with_capacity(w * h);
    for y in 0..h {
        let (y0, y1) = (y.saturating_sub(r), (y + r + 1).min(h));
        for x in 0..w {
            let (x0, x1) = (x.saturating_sub(r), (x + r + 1).min(w));
            let at = |yy: usize, xx: usize| sat[yy * (w + 1) + xx];
            out.push(at(y1, x1) - at(y0, x1) - at(y1, x0) + at(y0, x0));
        }
    }
    out
}

fn resolve(bands: &[&FrameState], params: &ResolveParams, threads: usize) -> Resolved {
    match resolve_bands(bands, params, threads) {
        Ok(r) => r,
        Err(e) => panic!("DenoisePlan::new: {e}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::CascadeLayout;

    /// A frame of constant grey with one firefly in the middle.
    fn firefly_frame(w: u32, h: u32, spp: u32) -> FrameState {
        let mut state = FrameState::flat(w, h, spp, [0.5, 0.4, 0.3]);
        state.splat(w / 2, h / 2, [5000.0; 3]).unwrap();
        state
    }

    #[test]
    fn the_inputs_are_the_papers_resolve_without_spreading_and_the_mean() {
        let state = firefly_frame(9, 7, 32);
        let params = ResolveParams::with_defaults();
        let paper = state.resolve(&params.with_variant(Variant::Paper));
        let plan = DenoisePlan::with_design(&[&state], &params, 2, DenoiseDesign::Paper);
        assert_eq!((plan.width(), plan.height()), (9, 7));
        assert_eq!(plan.inputs(), std::slice::from_ref(&paper.reweighted));
        assert_eq!(plan.name(), "paper");
        // The firefly is removed in its pixel and nowhere else touched (no spreading).
        let centre = 3 * 9 + 4;
        assert!(plan.inputs()[0][centre][0] < 1.0);
        for (p, v) in plan.inputs()[0].iter().enumerate() {
            if p != centre {
                assert_eq!(*v, [0.5, 0.4, 0.3], "pixel {p}");
            }
        }
        let plan = DenoisePlan::new(&[&state], &params, 2);
        assert_eq!(plan.name(), DEFAULT_DENOISE_DESIGN.name());
        let mild = state.resolve(&DEFAULT_DENOISE_DESIGN.paper_params(&params));
        assert_eq!(mild.mean, paper.mean);
        assert_eq!(plan.inputs(), &[mild.reweighted, mild.mean]);
    }

    #[test]
    fn a_first_pass_reaches_the_denoiser_whole() {
        // One and two samples a pixel of a flat frame: the paper's input is the mean (it used
        // to reach OIDN black from a first pass, and at half of it from two).
        for spp in 1..=2 {
            let state = FrameState::flat(8, 6, spp, [1.0, 0.5, 0.25]);
            let plan = DenoisePlan::new(&[&state], &ResolveParams::with_defaults(), 1);
            let [paper, mean] = plan.inputs() else {
                panic!("two inputs")
            };
            for (p, m) in paper.iter().zip(mean) {
                for c in 0..3 {
                    assert!((p[c] - m[c]).abs() <= 1e-6 * m[c], "{spp} spp: {p:?} {m:?}");
                }
            }
            // A denoiser that returns its input: the final is the frame.
            let outputs = plan.inputs().to_vec();
            for p in plan.combine(outputs) {
                assert!((p[1] - 0.5).abs() < 1e-6, "{spp} spp: {p:?}");
            }
        }
    }

    #[test]
    fn bands_give_the_same_inputs_as_the_whole_frame() {
        let state = firefly_frame(6, 9, 8);
        let layout = state.layout().clone();
        let mut bands = FrameState::bands(6, 9, 3, &layout);
        for band in &mut bands {
            band.merge_overlap(&state).unwrap();
        }
        let params = ResolveParams::with_defaults();
        for design in DenoiseDesign::ALL {
            let whole = DenoisePlan::with_design(&[&state], &params, 1, design);
            let banded =
                DenoisePlan::with_design(&bands.iter().collect::<Vec<_>>(), &params, 3, design);
            assert_eq!(whole.inputs(), banded.inputs(), "{design:?}");
            assert_eq!(whole.inputs().len(), design.images(), "{design:?}");
        }
    }

    /// Every input of `plan` as the denoiser's output, the first scaled by `first`, the others
    /// by `rest`.
    fn scaled(plan: &DenoisePlan, first: f32, rest: f32) -> Vec<Vec<[f32; 3]>> {
        plan.inputs()
            .iter()
            .enumerate()
            .map(|(i, img)| {
                let s = if i == 0 { first } else { rest };
                img.iter().map(|p| p.map(|v| v * s)).collect()
            })
            .collect()
    }

    #[test]
    fn the_paper_design_returns_the_denoised_paper() {
        let state = firefly_frame(5, 4, 4);
        let plan = DenoisePlan::with_design(
            &[&state],
            &ResolveParams::with_defaults(),
            1,
            DenoiseDesign::Paper,
        );
        let denoised = scaled(&plan, 0.5, 0.5);
        let expected = denoised[0].clone();
        assert_eq!(plan.combine(denoised), expected);
    }

    #[test]
    fn the_ratio_gives_back_the_denoised_means_local_energy_up_to_its_cap() {
        // A flat frame: the denoised paper is a constant, the denoised mean `s` times it.
        let state = firefly_frame(8, 8, 16);
        let params = ResolveParams::with_defaults();
        for (s, gain) in [(1.0, 1.0), (1.2, 1.2), (3.0, RATIO_CAP), (0.5, 1.0)] {
            let plan = DenoisePlan::with_design(&[&state], &params, 1, DenoiseDesign::PaperRatio);
            let flat = vec![vec![[0.5f32, 0.4, 0.3]; 64]; 2];
            let denoised = vec![
                flat[0].clone(),
                flat[1].iter().map(|p| p.map(|v| v * s as f32)).collect(),
            ];
            let out = plan.combine(denoised);
            for p in &out {
                for (c, v) in p.iter().enumerate() {
                    let want = [0.5, 0.4, 0.3][c] * gain;
                    assert!((*v as f64 - want).abs() < 1e-6, "s {s}: {p:?}");
                }
            }
        }
        // A bright spot in the denoised mean raises only the pixels within RATIO_RADIUS of it.
        let plan = DenoisePlan::with_design(&[&state], &params, 1, DenoiseDesign::PaperRatio);
        let paper = vec![[1.0f32; 3]; 64];
        let mut mean = paper.clone();
        mean[3 * 8 + 3] = [2.0; 3];
        let out = plan.combine(vec![paper, mean]);
        for y in 0..8usize {
            for x in 0..8usize {
                let near = y.abs_diff(3) <= RATIO_RADIUS && x.abs_diff(3) <= RATIO_RADIUS;
                assert_eq!(out[y * 8 + x][0] > 1.0, near, "({x}, {y})");
            }
        }
    }

    #[test]
    fn box_sums_are_window_sums_clamped_to_the_frame() {
        let v: Vec<f64> = (0..12).map(f64::from).collect(); // 4 x 3
        let s = box_sums(&v, 4, 3, 1);
        assert_eq!(s[0], 0.0 + 1.0 + 4.0 + 5.0);
        assert_eq!(s[5], (0..12).filter(|i| i % 4 <= 2).sum::<i32>() as f64);
        assert_eq!(s[11], 6.0 + 7.0 + 10.0 + 11.0);
    }

    #[test]
    #[should_panic(expected = "one denoised image per input")]
    fn combine_wants_one_output_per_input() {
        let state = firefly_frame(3, 3, 4);
        DenoisePlan::new(&[&state], &ResolveParams::with_defaults(), 1).combine(vec![]);
    }

    #[test]
    #[should_panic(expected = "DenoisePlan::new")]
    fn bands_that_do_not_tile_are_refused() {
        let layout = CascadeLayout::with_defaults();
        let bands = FrameState::bands(4, 6, 3, &layout);
        DenoisePlan::new(&[&bands[0], &bands[2]], &ResolveParams::with_defaults(), 1);
    }
}
