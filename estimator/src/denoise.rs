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
//! The design (its [`DenoisePlan::name`] goes into the EXR header's provenance):
//! * `paper`: one input, the paper's resolve (the first stage of `spread`, with the frame's
//!   `kappa`, `kappa_min` and `kappa_exponent`), no spatial spreading; the final is the
//!   denoiser's output.

use crate::resolve::{resolve_bands, ResolveParams, Resolved, Variant};
use crate::state::FrameState;

/// The denoiser's inputs for one frame and what is needed to combine its outputs.
#[derive(Debug, Clone)]
pub struct DenoisePlan {
    width: usize,
    height: usize,
    inputs: Vec<Vec<[f32; 3]>>,
    design: Design,
}

/// The designs; only one is served, the others are kept for the benchmark's comparison.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Design {
    /// The paper's resolve, denoised as is.
    Paper,
}

impl DenoisePlan {
    /// Resolves the frame held by `bands` (as [`resolve_bands`] takes them: in order, tiling the
    /// frame top to bottom) for the denoiser, on `threads` threads. `params` are the frame's
    /// resolve parameters; the plan uses their `kappa`, `kappa_min` and `kappa_exponent` and
    /// chooses its own variant (never a spatially spreading one).
    ///
    /// # Panics
    /// If the bands do not tile one frame (see [`resolve_bands`], which says why).
    pub fn new(bands: &[&FrameState], params: &ResolveParams, threads: usize) -> DenoisePlan {
        let design = Design::Paper;
        let resolved = resolve(bands, &params.with_variant(Variant::Paper), threads);
        let (width, height) = (resolved.width as usize, resolved.height as usize);
        DenoisePlan {
            width,
            height,
            inputs: vec![resolved.reweighted],
            design,
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
        match self.design {
            Design::Paper => denoised.into_iter().next().expect("one input"),
        }
    }

    /// The design's name, for the EXR header's provenance.
    pub fn name(&self) -> &'static str {
        match self.design {
            Design::Paper => "paper",
        }
    }
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
        let mut state = FrameState::new(w, h, CascadeLayout::with_defaults());
        for y in 0..h {
            for x in 0..w {
                for _ in 0..spp {
                    state.splat(x, y, [0.5, 0.4, 0.3]).unwrap();
                }
            }
        }
        state.splat(w / 2, h / 2, [5000.0; 3]).unwrap();
        state
    }

    #[test]
    fn the_input_is_the_papers_resolve_without_spreading() {
        let state = firefly_frame(9, 7, 32);
        let params = ResolveParams::with_defaults();
        let plan = DenoisePlan::new(&[&state], &params, 2);
        assert_eq!((plan.width(), plan.height()), (9, 7));
        assert_eq!(plan.inputs().len(), 1);
        let paper = state.resolve(&params.with_variant(Variant::Paper));
        assert_eq!(plan.inputs()[0], paper.reweighted);
        // The firefly is removed in its pixel and nowhere else touched (no spreading).
        let centre = 3 * 9 + 4;
        assert!(plan.inputs()[0][centre][0] < 1.0);
        for (p, v) in plan.inputs()[0].iter().enumerate() {
            if p != centre {
                assert_eq!(*v, [0.5, 0.4, 0.3], "pixel {p}");
            }
        }
        assert_eq!(plan.name(), "paper");
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
        let whole = DenoisePlan::new(&[&state], &params, 1);
        let banded = DenoisePlan::new(&bands.iter().collect::<Vec<_>>(), &params, 3);
        assert_eq!(whole.inputs(), banded.inputs());
    }

    #[test]
    fn combine_returns_the_final_from_the_denoised_inputs() {
        let state = firefly_frame(5, 4, 4);
        let plan = DenoisePlan::new(&[&state], &ResolveParams::with_defaults(), 1);
        let denoised: Vec<Vec<[f32; 3]>> = plan
            .inputs()
            .iter()
            .map(|i| i.iter().map(|p| p.map(|v| v * 0.5)).collect())
            .collect();
        let expected = denoised[0].clone();
        assert_eq!(plan.combine(denoised), expected);
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
