//! Property-based fuzzing of the two decoders that take untrusted bytes: they never panic, never
//! allocate by what a header claims, and accept exactly the bodies the encoders produce (or
//! mutations that happen to be well-formed, which then re-encode to the same bytes).

use proptest::prelude::*;
use splatd_proto::{Applied, Batch, DecodeLimits, Origin, Record, StateDump};

fn batch_strategy() -> impl Strategy<Value = Batch> {
    (
        "[a-z0-9._-]{1,12}",
        any::<u64>(),
        any::<u64>(),
        prop::collection::vec(
            (any::<u32>(), any::<u32>(), any::<[f32; 3]>()).prop_map(|(x, y, rgb)| Record {
                x,
                y,
                rgb,
            }),
            0..40,
        ),
    )
        .prop_filter("valid ids only", |(f, ..)| f != "." && f != "..")
        .prop_map(|(frame, worker, seq, records)| Batch {
            frame,
            worker,
            seq,
            records,
        })
}

fn state_strategy() -> impl Strategy<Value = StateDump> {
    (1u32..6, 1u32..5, 2u32..5, any::<bool>()).prop_flat_map(|(w, h, k, origin)| {
        let cells = (w * h * (4 * k + 1)) as usize;
        // Mostly zeros, so that states have empty pixels and runs between them.
        let cell = prop_oneof![3 => Just(0u64), 1 => any::<u64>()];
        let batches = prop::collection::btree_map(
            any::<u64>(),
            prop::collection::btree_map(0u64..40, any::<u64>(), 0..6),
            0..3,
        );
        (prop::collection::vec(cell, cells), batches).prop_map(move |(cells, batches)| StateDump {
            frame: "f".into(),
            width: w,
            height: h,
            rows_start: 0,
            rows_end: h,
            base: 8.0,
            cascades: k,
            lowest_scale: 0.125,
            luminance: [0.2126, 0.7152, 0.0722],
            frac_bits: 26,
            origin: origin.then(|| Origin {
                node: "n".into(),
                seq: 3,
            }),
            cells,
            aovs: vec![],
            aov_cells: vec![],
            batches: batches
                .into_iter()
                .filter(|(_, seqs)| !seqs.is_empty())
                .map(|(worker, seqs)| {
                    Applied::from_batches(
                        worker,
                        seqs.into_iter().map(|(s, d)| (s, (d != 0).then_some(d))),
                    )
                })
                .collect(),
        })
    })
}

/// Mutations: bit flips, truncation, insertion, overwriting 8 bytes with an extreme length.
fn mutate(bytes: &mut Vec<u8>, ops: &[(u8, usize, u64)]) {
    for &(op, at, value) in ops {
        if bytes.is_empty() {
            bytes.push(value as u8);
            continue;
        }
        let i = at % bytes.len();
        match op % 4 {
            0 => bytes[i] ^= 1 << (value % 8),
            1 => bytes.truncate(i),
            2 => bytes.insert(i, value as u8),
            _ => {
                let v = [u64::MAX, 1 << 62, value, 0][(value % 4) as usize].to_le_bytes();
                for (k, b) in v.iter().enumerate() {
                    if let Some(slot) = bytes.get_mut(i + k) {
                        *slot = *b;
                    }
                }
            }
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn batch_decoder_survives_anything(
        batch in batch_strategy(),
        ops in prop::collection::vec((any::<u8>(), any::<usize>(), any::<u64>()), 0..6),
    ) {
        let limits = DecodeLimits { max_records: 64, ..DecodeLimits::default() };
        let mut bytes = batch.encode();
        let first = Batch::decode(&bytes, &limits);
        prop_assert_eq!(first.as_ref(), Ok(&batch));
        mutate(&mut bytes, &ops);
        match Batch::decode(&bytes, &limits) {
            Ok(decoded) => prop_assert_eq!(&decoded.encode(), &bytes),
            Err(e) => prop_assert!(!e.code().is_empty() && !e.to_string().is_empty()),
        }
        // The reference decoder agrees on what is well-formed.
        prop_assert_eq!(
            Batch::decode(&bytes, &limits).is_ok(),
            Batch::decode_reference(&bytes, &limits).is_ok()
        );
    }

    #[test]
    fn state_decoder_survives_anything(
        state in state_strategy(),
        ops in prop::collection::vec((any::<u8>(), any::<usize>(), any::<u64>()), 0..6),
    ) {
        let mut bytes = state.encode();
        let max_cells = state.cells.len() as u64;
        let first = StateDump::decode(&bytes, max_cells);
        prop_assert_eq!(first.as_ref(), Ok(&state));
        mutate(&mut bytes, &ops);
        match StateDump::decode(&bytes, max_cells) {
            Ok(decoded) => prop_assert_eq!(&decoded.encode(), &bytes),
            Err(e) => prop_assert!(!e.code().is_empty() && !e.to_string().is_empty()),
        }
    }

    #[test]
    fn random_bytes_are_refused_cleanly(bytes in prop::collection::vec(any::<u8>(), 0..256)) {
        let _ = Batch::decode(&bytes, &DecodeLimits::default());
        let _ = StateDump::decode(&bytes, 1 << 20);
    }
}
