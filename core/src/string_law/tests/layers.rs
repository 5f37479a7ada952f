//! Layer tables: interpolation, compile errors, serialization, the knot
//! spacing.

use crate::model::{Knots, StringLaw, LAYER_KNOTS};
use crate::string_law::*;
use crate::test_fixtures::cube_frame;

fn layered(start_counts: i32, step_log2: u8, knots: &[f64]) -> StringLaw {
    let mut law = StringLaw::polynomial(4096, [10.0, -0.02, 0.0, 0.0]);
    law.layers = crate::model::LayerTable {
        start_counts,
        step_log2,
        knots_mm: Knots::from_slice(knots).expect("at most LAYER_KNOTS"),
    };
    law
}

/// The table interpolates between its knots and holds the end values
/// outside them, in f64 and in fixed point alike.
#[test]
fn layer_table_interpolates_and_holds_its_ends() {
    let law = layered(-1000, 10, &[1.0, -1.0, 2.0]); // knots at -1000, 24, 1048
    let t = &law.layers;
    let cases = [
        (i32::MIN, 1.0),
        (-5000, 1.0),
        (-1000, 1.0),
        (-488, 0.0),
        (24, -1.0),
        (536, 0.5),
        (1048, 2.0),
        (1049, 2.0),
        (i32::MAX, 2.0),
    ];
    let f = cube_frame([0.0; 3]);
    let c = compile_string_law(&f, 0, &law).expect("compiles");
    for (counts, want) in cases {
        assert!((t.departure_mm(counts) - want).abs() < 1e-12, "{counts}");
        let got = c.layers.departure_q16(counts) as f64 / 65536.0;
        assert!((got - want).abs() < 2e-5, "{counts}: fixed {got}");
        let whole = polynomial_payout_f64(&law, counts) + want;
        assert!((payout_f64(&law, counts) - whole).abs() < 1e-9);
    }
    // No table: nothing added, and the compiled law is the polynomial's.
    let plain = StringLaw::polynomial(4096, [10.0, -0.02, 0.0, 0.0]);
    assert_eq!(plain.layers.departure_mm(12345), 0.0);
    let cp = compile_string_law(&f, 0, &plain).expect("compiles");
    assert_eq!(cp.layers, CompiledLayerTable::NONE);
    assert_eq!(
        cp.payout_q32(5000) + q16_to_q32(c.layers.departure_q16(5000)),
        c.payout_q32(5000)
    );
}

#[test]
fn layer_table_compile_errors_name_the_field() {
    let f = cube_frame([0.0; 3]);
    let err = compile_string_law(&f, 3, &layered(0, 31, &[0.0, 1.0])).unwrap_err();
    assert!(
        matches!(
            err,
            StringLawCompileError::OutOfRange {
                string: 3,
                field: "layers.step_log2",
                ..
            }
        ),
        "{err}"
    );
    let err = compile_string_law(&f, 2, &layered(0, 10, &[0.0, f64::NAN])).unwrap_err();
    assert_eq!(
        err,
        StringLawCompileError::NotFinite {
            string: 2,
            field: "layers.knots_mm"
        }
    );
    let err = compile_string_law(&f, 1, &layered(0, 10, &[0.0, 150.0])).unwrap_err();
    assert!(
        matches!(
            err,
            StringLawCompileError::OutOfRange {
                string: 1,
                field: "layers.knots_mm",
                ..
            }
        ),
        "{err}"
    );
    // 1024 counts = 1.57 rad; the polynomial rises by ~15.7 mm there: a
    // table falling by 20 mm over it would make the payout fall.
    let err = compile_string_law(&f, 0, &layered(0, 10, &[0.0, -20.0])).unwrap_err();
    assert!(
        matches!(
            err,
            StringLawCompileError::OutOfRange {
                string: 0,
                field: "layers (payout slope, mm/rad)",
                ..
            }
        ),
        "{err}"
    );
    assert!(err.to_string().contains("layers"), "{err}");
    compile_string_law(&f, 0, &layered(0, 10, &[0.0, -10.0])).expect("still rising");
    // A compiled table read from a blob is checked too.
    let mut c = compile_string_law(&f, 0, &layered(0, 10, &[0.0, 1.0])).expect("compiles");
    c.validate(0).expect("valid");
    c.layers.knots_q16.as_mut_slice()[1] = 101 << 16;
    assert!(matches!(
        c.validate(0),
        Err(StringLawCompileError::OutOfRange {
            field: "layers.knots_mm",
            ..
        })
    ));
    c.layers.knots_q16.as_mut_slice()[1] = 0;
    c.layers.step_log2 = 40;
    assert!(matches!(
        c.validate(0),
        Err(StringLawCompileError::OutOfRange {
            field: "layers.step_log2",
            ..
        })
    ));
}

/// A law written before layer tables existed still reads (no table); a
/// table round-trips through JSON and postcard; more than LAYER_KNOTS
/// knots is an error, not a truncation.
#[test]
fn layer_tables_serialize_and_old_laws_still_read() {
    let old = r#"{"counts_per_rev":4096,"winding_mm":[10.0,-0.02,0.0,0.0]}"#;
    let law: StringLaw = serde_json::from_str(old).expect("old law reads");
    assert!(law.layers.is_empty());
    let law = layered(-300, 12, &[0.5, -0.25, 1.0]);
    let json = serde_json::to_string(&law).expect("serializes");
    assert!(json.contains("[0.5,-0.25,1.0]"), "{json}");
    assert_eq!(
        serde_json::from_str::<StringLaw>(&json).expect("reads"),
        law
    );
    let f = cube_frame([0.0; 3]);
    let c = compile_string_law(&f, 0, &law).expect("compiles");
    let bytes = postcard::to_allocvec(&c).expect("postcard");
    assert_eq!(
        postcard::from_bytes::<CompiledStringLaw>(&bytes).expect("reads"),
        c
    );
    let too_many = format!(
        r#"{{"start_counts":0,"step_log2":10,"knots_mm":[{}]}}"#,
        vec!["0.0"; LAYER_KNOTS + 1].join(",")
    );
    let err = serde_json::from_str::<crate::model::LayerTable>(&too_many).unwrap_err();
    assert!(err.to_string().contains("at most 32"), "{err}");
}

/// The layer table's knot spacing, `2^step_log2` counts, is read as an
/// integer power of two: the value libm's `exp2` gives, to the bit.
#[test]
fn layer_step_is_exp2_of_its_log() {
    for n in 0..=crate::model::MAX_LAYER_STEP_LOG2 {
        assert_eq!(f64::from(1u32 << n), libm::exp2(f64::from(n)), "2^{n}");
    }
}
