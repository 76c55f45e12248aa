//! Frame states to and from their wire form ([`StateDump`]), for exporting, importing, pushing
//! and the offline `splatd merge`.
//!
//! The dump is the state's fixed-point cells verbatim, so export followed by import is exact, and
//! importing into a frame that has samples of its own adds the two exactly.

use splatd_proto::api::AovSpec;
use splatd_proto::{Applied, Origin, Runs, StateDump, StateError};

use splatd_estimator::{
    check_pixels, AovCellsError, AovSums, CascadeLayout, CellsError, FrameState, MergeError,
    ParamError, FRAC_BITS,
};

use crate::frame::{Importable, PieceVisitor};

/// A frame's AOVs as a state carries them: the declarations and the sums of the rows held.
pub type Aovs<'a> = Option<(&'a [AovSpec], &'a AovSums)>;

/// An imported state that cannot be used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ImportError {
    /// Its cascade parameters make no sense.
    #[error("state has invalid cascade parameters: {0}")]
    Params(#[from] ParamError),
    /// It was written with another fixed-point precision.
    #[error("state uses {found} fractional bits; this build uses {FRAC_BITS}")]
    FracBits {
        /// Bits in the state.
        found: u32,
    },
    /// Its cells do not fit its geometry, or hold what no checked samples could have made.
    #[error(transparent)]
    Cells(#[from] CellsError),
    /// Its AOV words do not fit its geometry, or hold what no checked values could have made.
    #[error(transparent)]
    Aovs(#[from] AovCellsError),
    /// Its run list is malformed (a pixel in a run holds nothing).
    #[error(transparent)]
    State(#[from] StateError),
}

/// The wire form of a state (a whole frame or a band) holding the samples of `batches`.
pub fn dump(
    state: &FrameState,
    aovs: Aovs<'_>,
    frame: &str,
    origin: Option<Origin>,
    batches: Vec<Applied>,
) -> StateDump {
    with_aovs(
        StateDump {
            cells: state.cells().to_vec(),
            batches,
            ..header(state, state.rows(), frame, origin)
        },
        aovs,
    )
}

/// `dump` with the AOVs (declarations and words) set.
fn with_aovs(dump: StateDump, aovs: Aovs<'_>) -> StateDump {
    match aovs {
        None => dump,
        Some((specs, sums)) => StateDump {
            aovs: specs.to_vec(),
            aov_cells: sums.words().to_vec(),
            ..dump
        },
    }
}

/// Takes the AOVs out of a decoded state: `None` for a state without AOVs (version 2, or a
/// frame that declares none), else its declarations and checked sums.
pub fn take_aovs(dump: &mut StateDump) -> Result<Option<(Vec<AovSpec>, AovSums)>, ImportError> {
    let specs = std::mem::take(&mut dump.aovs);
    let words = std::mem::take(&mut dump.aov_cells);
    aov_sums(dump, specs, words)
}

/// The checked AOV sums of a state of `dump`'s rows from its declarations and words: `None`
/// when they declare no channel.
fn aov_sums(
    dump: &StateDump,
    specs: Vec<AovSpec>,
    words: Vec<u64>,
) -> Result<Option<(Vec<AovSpec>, AovSums)>, ImportError> {
    let channels: usize = specs.iter().map(|a| a.channels.len()).sum();
    if channels == 0 {
        return Ok(None);
    }
    let sums = AovSums::from_words(dump.width, dump.rows_start..dump.rows_end, channels, words)?;
    Ok(Some((specs, sums)))
}

/// Streams the wire form of a state (a whole frame or a band) to `out` without copying its cells,
/// naming no applied batches (a snapshot band: the snapshot keeps the frame's batches itself).
pub fn write(
    state: &FrameState,
    aovs: Aovs<'_>,
    frame: &str,
    origin: Option<Origin>,
    out: &mut impl std::io::Write,
) -> std::io::Result<()> {
    with_aovs(header(state, state.rows(), frame, origin), aovs).write_with_cells(state.cells(), out)
}

/// The length of what [`write`] writes, without encoding it.
pub fn encoded_len(state: &FrameState, aovs: Aovs<'_>, frame: &str) -> u64 {
    with_aovs(header(state, state.rows(), frame, None), aovs)
        .encoded_len_with_cell_parts(&[state.cells()])
}

/// Streams the wire form of a whole frame held as row bands (top to bottom, tiling the frame) and
/// holding the samples of `batches` to `out`: the same bytes as [`dump`] of the merged frame,
/// without merging or copying the bands.
///
/// # Panics
/// If `bands` is empty.
pub fn write_bands(
    bands: &[&FrameState],
    aovs: Aovs<'_>,
    frame: &str,
    origin: Option<Origin>,
    batches: Vec<Applied>,
    out: &mut impl std::io::Write,
) -> std::io::Result<()> {
    let first = &bands[0];
    debug_assert!(
        bands
            .windows(2)
            .all(|w| w[0].rows().end == w[1].rows().start),
        "bands tile the frame in order"
    );
    let rows = first.rows().start..bands[bands.len() - 1].rows().end;
    let parts: Vec<&[u64]> = bands.iter().map(|b| b.cells()).collect();
    with_aovs(
        StateDump {
            batches,
            ..header(first, rows, frame, origin)
        },
        aovs,
    )
    .write_with_cell_parts(&parts, out)
}

/// A dump without cells describing `state`'s frame and layout for `rows`.
fn header(
    state: &FrameState,
    rows: std::ops::Range<u32>,
    frame: &str,
    origin: Option<Origin>,
) -> StateDump {
    let layout = state.layout();
    StateDump {
        frame: frame.to_owned(),
        width: state.width(),
        height: state.height(),
        rows_start: rows.start,
        rows_end: rows.end,
        base: layout.base(),
        cascades: layout.cascades() as u32,
        lowest_scale: layout.lowest_scale(),
        luminance: layout.luminance_weights(),
        frac_bits: FRAC_BITS,
        origin,
        cells: Vec::new(),
        batches: Vec::new(),
        aovs: Vec::new(),
        aov_cells: Vec::new(),
    }
}

/// A state from its wire form, validated like a newly created frame.
pub fn load(dump: StateDump) -> Result<FrameState, ImportError> {
    if dump.frac_bits != FRAC_BITS {
        return Err(ImportError::FracBits {
            found: dump.frac_bits,
        });
    }
    let layout = CascadeLayout::new(dump.base, dump.cascades, dump.lowest_scale, dump.luminance)?;
    Ok(FrameState::from_cells(
        dump.width,
        dump.height,
        dump.rows_start..dump.rows_end,
        layout,
        dump.cells,
    )?)
}

/// A state body decoded for import without expanding its cells ([`StateDump::decode_runs`]):
/// its header, its AOVs, and its runs read in place from the body, every pixel of them checked
/// like [`load`] checks a whole state. Importing it adds the runs straight into the frame's bands
/// ([`crate::frame::ShardedFrame::import`]), so the only full-size buffer of an import is the
/// body itself (and the AOV sums of a state that has AOVs).
pub struct Decoded<'a> {
    /// The header (no cells, no AOVs).
    pub dump: StateDump,
    /// The state's AOV declarations and checked sums, `None` for a state without AOVs.
    pub aovs: Option<(Vec<AovSpec>, AovSums)>,
    layout: CascadeLayout,
    runs: Runs<'a>,
    samples: u64,
}

impl Decoded<'_> {
    /// The AOVs, as [`crate::frame::ShardedFrame::import`] takes them.
    pub fn aovs(&self) -> Aovs<'_> {
        self.aovs
            .as_ref()
            .map(|(specs, sums)| (specs.as_slice(), sums))
    }
}

/// Checks a state decoded without its cells ([`StateDump::decode_runs`]) like [`load`] and
/// [`take_aovs`] check a whole one: the precision, the cascade parameters and every pixel of
/// every run (one pass over the runs, a cache-sized piece at a time), then the AOV words (the
/// AOV runs, expanded into the sums of the rows held).
pub fn load_runs<'a>(
    mut dump: StateDump,
    runs: Runs<'a>,
    aov_runs: Option<Runs<'_>>,
) -> Result<Decoded<'a>, ImportError> {
    if dump.frac_bits != FRAC_BITS {
        return Err(ImportError::FracBits {
            found: dump.frac_bits,
        });
    }
    let layout = CascadeLayout::new(dump.base, dump.cascades, dump.lowest_scale, dump.luminance)?;
    let mut samples = 0;
    runs.try_for_each(|first, cells| {
        samples += check_pixels(dump.width, dump.rows_start, layout.cascades(), first, cells)?;
        Ok::<(), ImportError>(())
    })?;
    let words = aov_runs.map(|r| r.expand()).transpose()?;
    let specs = std::mem::take(&mut dump.aovs);
    let aovs = aov_sums(&dump, specs, words.unwrap_or_default())?;
    Ok(Decoded {
        dump,
        aovs,
        layout,
        runs,
        samples,
    })
}

impl Importable for Decoded<'_> {
    fn geometry(&self) -> (u32, u32, &CascadeLayout) {
        (self.dump.width, self.dump.height, &self.layout)
    }

    fn first_row(&self) -> u32 {
        self.dump.rows_start
    }

    fn samples(&self) -> u64 {
        self.samples
    }

    fn pieces(&self, f: &mut PieceVisitor<'_>) -> Result<(), MergeError> {
        /// The runs' own refusals were all found by [`load_runs`]; only `f`'s remain.
        enum Stop {
            Merge(MergeError),
        }
        impl From<StateError> for Stop {
            fn from(e: StateError) -> Stop {
                unreachable!("the runs were checked when the state was loaded: {e}")
            }
        }
        self.runs
            .try_for_each(|first, cells| f(first, cells).map_err(Stop::Merge))
            .map_err(|Stop::Merge(e)| e)
    }
}

/// Fractional bits of state format version 1.
const V1_FRAC_BITS: u32 = 32;

/// A state from its version 1 wire form ([`StateDump::decode_v1`]: 32 fractional bits, `4K`
/// cells per pixel), converted to the current cells
/// ([`FrameState::from_frac32_cells`]). A sum that saturated cannot be converted and is refused,
/// naming its pixel.
pub fn load_v1(dump: StateDump) -> Result<FrameState, ImportError> {
    if dump.frac_bits != V1_FRAC_BITS {
        return Err(ImportError::FracBits {
            found: dump.frac_bits,
        });
    }
    let layout = CascadeLayout::new(dump.base, dump.cascades, dump.lowest_scale, dump.luminance)?;
    Ok(FrameState::from_frac32_cells(
        dump.width,
        dump.height,
        dump.rows_start..dump.rows_end,
        layout,
        &dump.cells,
    )?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use splatd_scenes::synth::FireflyScene;

    #[test]
    fn streaming_writes_the_same_bytes_as_dump() {
        let scene = FireflyScene::new(5, 4, 1);
        let mut state = FrameState::new(5, 4, CascadeLayout::with_defaults());
        state.splat_all(scene.pass(0));
        let origin = Some(Origin {
            node: "n".into(),
            seq: 2,
        });
        let mut streamed = Vec::new();
        write(&state, None, "f", origin.clone(), &mut streamed).unwrap();
        assert_eq!(streamed, dump(&state, None, "f", origin, vec![]).encode());
    }

    #[test]
    fn bands_stream_as_the_whole_frame() {
        let scene = FireflyScene::new(7, 20, 4);
        let layout = CascadeLayout::with_defaults();
        let mut whole = FrameState::new(7, 20, layout.clone());
        let mut bands = FrameState::bands(7, 20, 3, &layout);
        for pass in 0..3 {
            whole.splat_all(scene.pass(pass));
            for band in &mut bands {
                let rows = band.rows();
                band.splat_all(scene.pass(pass).filter(|s| rows.contains(&s.1)));
            }
        }
        let mut streamed = Vec::new();
        let bands: Vec<&FrameState> = bands.iter().collect();
        write_bands(&bands, None, "f", None, vec![], &mut streamed).unwrap();
        assert_eq!(streamed, dump(&whole, None, "f", None, vec![]).encode());
    }

    #[test]
    fn export_then_import_is_exact() {
        let scene = FireflyScene::new(9, 7, 3);
        let mut state = FrameState::new(9, 7, CascadeLayout::with_defaults());
        for pass in 0..20 {
            state.splat_all(scene.pass(pass));
        }
        let bytes = dump(&state, None, "f", None, vec![]).encode();
        let back = load(StateDump::decode(&bytes, u64::MAX).unwrap()).unwrap();
        assert_eq!(back, state);
    }

    #[test]
    fn nonsense_states_are_refused_by_name() {
        let state = FrameState::new(2, 2, CascadeLayout::with_defaults());
        let mut d = dump(&state, None, "f", None, vec![]);
        d.frac_bits = 16;
        assert_eq!(load(d).unwrap_err(), ImportError::FracBits { found: 16 });
        let mut d = dump(&state, None, "f", None, vec![]);
        d.base = 1.0;
        assert!(matches!(load(d), Err(ImportError::Params(p)) if p.name == "base"));
    }
}
