//! Compiling laws and effect terms: the errors name the field, and compiled
//! terms validate.

use super::fixtures::{realistic, Rng};
use crate::model::{Effect, EffectTerm, StringLaw};
use crate::string_law::*;
use crate::test_fixtures::cube_frame;

#[test]
fn string_law_compile_errors_name_the_field() {
    let f = cube_frame([0.0; 3]);
    let law = StringLaw::polynomial(4096, [10.0, -0.02, 0.0, 0.0]);
    assert_eq!(
        compile_string_law(&f, 8, &law),
        Err(StringLawCompileError::StringOutOfRange { string: 8 })
    );
    let bad = StringLaw {
        counts_per_rev: 0,
        ..law
    };
    assert!(matches!(
        compile_string_law(&f, 1, &bad),
        Err(StringLawCompileError::OutOfRange {
            string: 1,
            field: "counts_per_rev",
            ..
        })
    ));
    let bad = StringLaw {
        winding_mm: [10.0, f64::NAN, 0.0, 0.0],
        ..law
    };
    assert_eq!(
        compile_string_law(&f, 2, &bad),
        Err(StringLawCompileError::NotFinite {
            string: 2,
            field: "winding_mm[1]"
        })
    );
    let bad = StringLaw {
        winding_mm: [10.0, 0.0, 0.0, 1e6],
        ..law
    };
    assert!(matches!(
        compile_string_law(&f, 3, &bad),
        Err(StringLawCompileError::DoesNotFit {
            string: 3,
            field: "winding_mm[3]",
            ..
        })
    ));
    let mut nf = f;
    nf.home[1] = f64::INFINITY;
    assert_eq!(
        compile_string_law(&nf, 0, &law),
        Err(StringLawCompileError::NotFinite {
            string: 0,
            field: "home"
        })
    );
    let mut nf = f;
    nf.anchors[5][2] = f64::NAN;
    assert_eq!(
        compile_string_law(&nf, 5, &law),
        Err(StringLawCompileError::NotFinite {
            string: 5,
            field: "anchor"
        })
    );

    let msg = format!(
        "{}",
        StringLawCompileError::NotFinite {
            string: 2,
            field: "winding_mm[1]"
        }
    );
    assert_eq!(msg, "string 2: winding_mm[1] is not finite");
}

/// Which kind of compile error, and for which field.
fn kind_and_field(e: StringLawCompileError) -> (&'static str, &'static str) {
    match e {
        StringLawCompileError::StringOutOfRange { .. } => ("StringOutOfRange", "string"),
        StringLawCompileError::NotFinite { field, .. } => ("NotFinite", field),
        StringLawCompileError::DoesNotFit { field, .. } => ("DoesNotFit", field),
        StringLawCompileError::OutOfRange { field, .. } => ("OutOfRange", field),
    }
}

#[test]
fn effect_compile_errors_name_the_field() {
    let f = cube_frame([0.0; 3]);
    let law = StringLaw::polynomial(4096, [10.0, -0.02, 0.0, 0.0]);
    let laws = [law; STRINGS];
    let term = |string, effect| EffectTerm { string, effect };
    assert_eq!(
        compile_effect(&term(8, Effect::Offset { mm: 1.0 }), &f, &laws),
        Err(StringLawCompileError::StringOutOfRange { string: 8 })
    );
    let sag = |mm_at_1m_1n, home_mm_at_1m| Effect::Sag {
        mm_at_1m_1n,
        home_mm_at_1m,
    };
    let cases = [
        (Effect::Scale { relative: 2.5 }, "DoesNotFit", "relative"),
        (
            Effect::Winding {
                power: 0,
                mm_per_rad_pow: 1.0,
            },
            "OutOfRange",
            "power",
        ),
        (
            Effect::Elasticity { per_newton: 0.1 },
            "DoesNotFit",
            "per_newton",
        ),
        (
            Effect::Slip {
                at_s: -1.0,
                mm: 1.0,
            },
            "OutOfRange",
            "at_s",
        ),
        (
            Effect::Slip {
                at_s: 1.0,
                mm: f64::NAN,
            },
            "NotFinite",
            "mm",
        ),
        (sag(101.0, 1.0), "OutOfRange", "mm_at_1m_1n"),
        (sag(1.6, -101.0), "OutOfRange", "home_mm_at_1m"),
        (sag(f64::NAN, 0.0), "NotFinite", "mm_at_1m_1n"),
        (Effect::Drift { mm_per_s: 1e30 }, "DoesNotFit", "mm_per_s"),
        (
            Effect::Latency { latency_s: 0.3 },
            "OutOfRange",
            "latency_s",
        ),
        (
            Effect::Latency {
                latency_s: f64::INFINITY,
            },
            "NotFinite",
            "latency_s",
        ),
        (Effect::Guide { radius_mm: 51.0 }, "OutOfRange", "radius_mm"),
        (Effect::Creep { per_s: 2e-5 }, "OutOfRange", "per_s"),
        (Effect::Creep { per_s: f64::NAN }, "NotFinite", "per_s"),
        (
            Effect::Guide {
                radius_mm: f64::NAN,
            },
            "NotFinite",
            "radius_mm",
        ),
    ];
    for (effect, kind, field) in cases {
        let got = compile_effect(&term(0, effect), &f, &laws).map(|_| ());
        assert_eq!(
            got.map_err(kind_and_field),
            Err((kind, field)),
            "{effect:?}"
        );
    }
    let zero = [StringLaw {
        counts_per_rev: 0,
        ..law
    }; STRINGS];
    let eccentricity = Effect::Eccentricity {
        sin_mm: 1.0,
        cos_mm: 0.0,
    };
    assert_eq!(
        compile_effect(&term(0, eccentricity), &f, &zero)
            .map(|_| ())
            .map_err(kind_and_field),
        Err(("OutOfRange", "counts_per_rev"))
    );
}

#[test]
fn compiled_effects_validate() {
    let mut rng = Rng(11);
    let (f, laws, effects) = realistic(&mut rng);
    for e in &effects {
        compile_effect(e, &f, &laws).unwrap().validate().unwrap();
    }
    assert!(CompiledEffect::Offset {
        string: 9,
        mm_q16: 0
    }
    .validate()
    .is_err());
    assert!(CompiledEffect::Winding {
        string: 0,
        power: 9,
        coeff_q32: 0
    }
    .validate()
    .is_err());
    assert!(CompiledEffect::Eccentricity {
        string: 0,
        sin_q16: 0,
        cos_q16: 0,
        counts_per_rev: 4096,
        turns_per_count_q48: 3,
    }
    .validate()
    .is_err());
    assert!(CompiledEffect::Latency {
        string: EVERY_STRING,
        latency_q31: i32::MAX,
    }
    .validate()
    .is_err());
    assert!(CompiledEffect::Guide {
        string: EVERY_STRING,
        radius_q24: i32::MIN,
        home_q20: [0; STRINGS],
    }
    .validate()
    .is_err());
}
