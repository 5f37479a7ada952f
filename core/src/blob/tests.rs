use super::*;
use crate::correction::CorrectionModel;
use crate::model::{Calibration, Effect, EffectTerm, StringLaw};
use crate::test_fixtures::cube_frame;
use spidar_protocol::blob::CorrectionKind;

/// `blob` with its string model replaced by `head` (`rest`: its
/// correction), header and CRCs rewritten: a blob another tool could send.
fn with_head(blob: &[u8], head: &BlobHead, rest: &[u8]) -> alloc::vec::Vec<u8> {
    let mut body = postcard::to_allocvec(head).unwrap();
    body.resize(body.len() + correction_padding(HEADER_LEN + body.len()), 0);
    body.extend_from_slice(rest);
    let h = ModelHeader::parse(blob).unwrap();
    let mut out = alloc::vec![0u8; HEADER_LEN + body.len()];
    spidar_protocol::blob::write_blob(&h, &body, &mut out).unwrap();
    out
}

fn calibration() -> Calibration {
    Calibration {
        frame: cube_frame([1.0, -2.0, 3.0]),
        strings: [StringLaw::polynomial(4096, [12.0, -0.004, 0.0, 0.0]); STRINGS],
        effects: alloc::vec![
            EffectTerm {
                string: 3,
                effect: Effect::Offset { mm: 4.5 },
            },
            EffectTerm {
                string: 5,
                effect: Effect::Backlash { half_width_mm: 0.7 },
            },
        ],
        correction: CorrectionModel::None,
        // String 3 four times noisier than the others.
        length_scale_mm: [0.2, 0.2, 0.2, 0.8, 0.2, 0.2, 0.2, 0.2],
        kinematics: Default::default(),
        home: None,
    }
}

#[test]
fn the_strings_weights_are_compiled_from_their_measured_scales_and_checked() {
    let blob = compile(&calibration(), 7, 0).unwrap();
    let c = CompiledCalibration::from_blob(&blob).unwrap();
    assert_eq!(
        c.head.residual_weight,
        [1.0, 1.0, 1.0, 0.25, 1.0, 1.0, 1.0, 1.0]
    );
    // Unmeasured scales weigh every string alike.
    let mut unmeasured = calibration();
    unmeasured.length_scale_mm = [0.0; STRINGS];
    let c = compile(&unmeasured, 7, 0).unwrap();
    let c = CompiledCalibration::from_blob(&c).unwrap();
    assert_eq!(c.head.residual_weight, [1.0; STRINGS]);
    // A scale that is not a positive number beside measured ones does not
    // compile, naming the string; inactive channels are not read.
    for bad in [0.0, -0.2, f64::NAN, f64::INFINITY] {
        let mut cal = calibration();
        cal.length_scale_mm[6] = bad;
        assert_eq!(
            compile(&cal, 7, 0),
            Err(BlobCompileError::LengthScale { string: 6 }),
            "{bad}"
        );
    }
    let mut four = four_strings();
    four.length_scale_mm[1] = f64::NAN;
    assert!(compile(&four, 7, 0).is_ok());
    // A weight out of [MIN_RESIDUAL_WEIGHT, 1] from another tool is refused,
    // naming the field.
    let (_, body) = split_blob(&blob).unwrap();
    let (head, rest) = split_body(body).unwrap();
    for bad in [0.0, 0.05, 1.5, f32::NAN, f32::INFINITY] {
        let mut h = head.clone();
        h.residual_weight[2] = bad;
        assert_eq!(
            CompiledCalibration::from_blob(&with_head(&blob, &h, rest)),
            Err(BlobError::Body {
                field: "residual_weight"
            }),
            "{bad}"
        );
    }
}

#[test]
fn compiled_blob_parses_back() {
    let blob = compile(&calibration(), 7, 0).unwrap();
    let c = CompiledCalibration::from_blob(&blob).unwrap();
    assert_eq!(c.header.effects, 2);
    assert_eq!(c.header.model_id, 7);
    assert_eq!(c.head.frame.home, [1.0, -2.0, 3.0]);
    assert_eq!(c.correction.kind(), CorrectionKind::None);
}

/// `cal` compiled to a blob and read back: the blob and its effect terms
/// compiled one by one, which the blob carries bit for bit (four: the
/// calibration's two and the two a test adds).
fn round_trip(cal: &Calibration) -> (alloc::vec::Vec<u8>, alloc::vec::Vec<CompiledEffect>) {
    let blob = compile(cal, 7, 0).unwrap();
    let c = CompiledCalibration::from_blob(&blob).unwrap();
    assert_eq!(c.header.effects, 4);
    let expected: alloc::vec::Vec<CompiledEffect> = cal
        .effects
        .iter()
        .map(|t| crate::string_law::compile_effect(t, &cal.frame, &cal.strings).unwrap())
        .collect();
    assert_eq!(c.head.effects.as_slice(), expected.as_slice());
    (blob, expected)
}

/// Latency terms (one string's, one shared) go through the blob bit for
/// bit and evaluate as compiled; a latency beyond the format's range from
/// another tool is refused, naming the field.
#[test]
fn latency_terms_round_trip_and_out_of_range_ones_are_refused() {
    let mut cal = calibration();
    cal.effects.push(EffectTerm {
        string: 2,
        effect: Effect::Latency { latency_s: 0.006 },
    });
    cal.effects.push(EffectTerm {
        string: crate::model::EVERY_STRING,
        effect: Effect::Latency { latency_s: -0.0015 },
    });
    let (blob, expected) = round_trip(&cal);
    assert_eq!(
        expected[2],
        CompiledEffect::Latency {
            string: 2,
            latency_q31: 12_884_902,
        }
    );
    let (_, body) = split_blob(&blob).unwrap();
    let (head, rest) = split_body(body).unwrap();
    let mut h = head.clone();
    h.effects[2] = CompiledEffect::Latency {
        string: 2,
        latency_q31: i32::MIN,
    };
    assert!(matches!(
        CompiledCalibration::from_blob(&with_head(&blob, &h, rest)),
        Err(BlobError::Body { .. })
    ));
}

/// Creep terms (one string's, one shared) go through the blob bit for bit
/// (a rate of 300 ppm/h in Q0.63 per ms).
#[test]
fn creep_terms_round_trip() {
    let mut cal = calibration();
    cal.effects.push(EffectTerm {
        string: 6,
        effect: Effect::Creep { per_s: 8.3e-8 },
    });
    cal.effects.push(EffectTerm {
        string: crate::model::EVERY_STRING,
        effect: Effect::Creep { per_s: -2e-6 },
    });
    let (_, expected) = round_trip(&cal);
    assert_eq!(
        expected[2],
        CompiledEffect::Creep {
            string: 6,
            per_ms_q63: 765_539_879,
        }
    );
}

/// Guide terms (one string's, one shared) go through the blob bit for bit;
/// a radius beyond the format's range from another tool is refused, naming
/// the field.
#[test]
fn guide_terms_round_trip_and_out_of_range_ones_are_refused() {
    let mut cal = calibration();
    cal.effects.push(EffectTerm {
        string: 1,
        effect: Effect::Guide { radius_mm: 12.0 },
    });
    cal.effects.push(EffectTerm {
        string: crate::model::EVERY_STRING,
        effect: Effect::Guide { radius_mm: 7.25 },
    });
    let (blob, expected) = round_trip(&cal);
    assert_eq!(
        expected[2],
        CompiledEffect::Guide {
            string: 1,
            radius_q24: 12 << 24,
            home_q20: match expected[2] {
                CompiledEffect::Guide { home_q20, .. } => home_q20,
                _ => [0; 8],
            },
        }
    );
    // The home part on its string only (a shared term's on every string).
    let CompiledEffect::Guide { home_q20, .. } = expected[2] else {
        panic!("{:?}", expected[2]);
    };
    assert!(home_q20
        .iter()
        .enumerate()
        .all(|(i, &h)| (h != 0) == (i == 1)));
    let CompiledEffect::Guide { home_q20, .. } = expected[3] else {
        panic!("{:?}", expected[3]);
    };
    assert!(home_q20.iter().all(|&h| h > 0));
    let (_, body) = split_blob(&blob).unwrap();
    let (head, rest) = split_body(body).unwrap();
    let mut h = head.clone();
    h.effects[3] = CompiledEffect::Guide {
        string: crate::model::EVERY_STRING,
        radius_q24: 51 << 24,
        home_q20: [0; 8],
    };
    assert!(matches!(
        CompiledCalibration::from_blob(&with_head(&blob, &h, rest)),
        Err(BlobError::Body { .. })
    ));
}

#[test]
fn any_corruption_or_truncation_is_refused_not_panicking() {
    let blob = compile(&calibration(), 7, 0).unwrap();
    for cut in 0..blob.len() {
        assert!(CompiledCalibration::from_blob(&blob[..cut]).is_err());
    }
    for i in 0..blob.len() {
        let mut bad = blob.clone();
        bad[i] ^= 0x40;
        assert!(CompiledCalibration::from_blob(&bad).is_err(), "byte {i}");
    }
}

/// Format 2: whatever the length of the string model, the correction
/// starts at a multiple of 4 bytes from the blob start, after zero
/// padding that the parser checks.
#[test]
fn correction_is_4_aligned_and_padding_checked() {
    let svr = crate::correction::SvrModel {
        input: crate::correction::Standardization {
            mean: [0.0; 3],
            std: [300.0; 3],
        },
        output: crate::correction::Standardization {
            mean: [0.0; 3],
            std: [1.0; 3],
        },
        gamma: 0.5,
        support: alloc::vec![[0.1, 0.2, 0.3], [-0.5, 0.0, 0.25]],
        coef: [
            alloc::vec![0.5, -0.25],
            alloc::vec![0.1, 0.2],
            alloc::vec![-0.3, 0.0],
        ],
        bias: [0.0; 3],
        mode: crate::correction::OutputMode::Residual,
    };
    let mut paddings = [false; 4];
    for extra in 0..8 {
        let mut cal = calibration();
        cal.correction = CorrectionModel::Svr(svr.clone());
        for i in 0..extra {
            cal.effects.push(EffectTerm {
                string: (i % STRINGS) as u8,
                effect: Effect::Offset {
                    mm: 1.0 + i as f64 * 0.37,
                },
            });
        }
        let blob = compile(&cal, 7, 0).unwrap();
        let (_, body) = split_blob(&blob).unwrap();
        let (_, rest): (BlobHead, &[u8]) = postcard::take_from_bytes(body).unwrap();
        let (_, correction) = split_body(body).unwrap();
        let at = blob.len() - correction.len();
        assert_eq!(at % CORRECTION_ALIGN, 0, "{extra} effects");
        let pad = rest.len() - correction.len();
        assert!(pad < CORRECTION_ALIGN);
        paddings[pad] = true;
        let c = CompiledCalibration::from_blob(&blob).unwrap();
        assert_eq!(c.correction.kind(), CorrectionKind::Svr);
        if pad > 0 {
            // A non-zero padding byte, with the CRCs made valid again.
            let mut bad = blob.clone();
            bad[at - 1] = 1;
            let mut h = ModelHeader::parse(&bad).unwrap();
            h.body_crc32 = 0;
            let body = bad[HEADER_LEN..].to_vec();
            let n = spidar_protocol::blob::write_blob(&h, &body, &mut bad).unwrap();
            assert_eq!(n, blob.len());
            assert_eq!(
                CompiledCalibration::from_blob(&bad),
                Err(BlobError::Body { field: "padding" })
            );
        }
    }
    // The effect counts above give every padding length.
    assert!(paddings.iter().filter(|&&p| p).count() >= 2, "{paddings:?}");
}

/// Rewrites a blob's header (CRCs made valid again).
fn with_header(blob: &[u8], edit: impl Fn(&mut ModelHeader)) -> alloc::vec::Vec<u8> {
    let mut h = ModelHeader::parse(blob).unwrap();
    edit(&mut h);
    let body = &blob[HEADER_LEN..];
    let mut out = alloc::vec![0u8; blob.len()];
    spidar_protocol::blob::write_blob(&h, body, &mut out).unwrap();
    out
}

/// A 4-string model on channels 0, 2, 5, 7 (inactive anchors NaN: never
/// read, written as zeros) with an effect on string 5.
fn four_strings() -> Calibration {
    let mut cal = calibration();
    cal.frame.layout = crate::model::StringLayout {
        active: 0b1010_0101,
        planar: false,
    };
    for i in [1, 3, 4, 6] {
        cal.frame.anchors[i] = [f64::NAN; 3];
        cal.strings[i].counts_per_rev = 0;
    }
    cal.effects[0].string = 5;
    cal
}

#[test]
fn header_strings_count_the_layout() {
    let blob = compile(&four_strings(), 7, 0).unwrap();
    let c = CompiledCalibration::from_blob(&blob).unwrap();
    assert_eq!(c.header.strings, 4);
    assert_eq!(c.head.frame.layout.active, 0b1010_0101);
    assert_eq!(c.head.frame.anchors[1], [0.0; 3]);
    assert_eq!(c.head.laws[3], CompiledStringLaw::default());
    // A header that says otherwise is refused, naming the field.
    let bad = with_header(&blob, |h| h.strings = 8);
    assert_eq!(
        CompiledCalibration::from_blob(&bad),
        Err(BlobError::Dimension {
            field: "strings",
            found: 8,
            expected: 4
        })
    );
    // 8 strings still write 8.
    let blob = compile(&calibration(), 7, 0).unwrap();
    assert_eq!(ModelHeader::parse(&blob).unwrap().strings, 8);
}

#[test]
fn layouts_below_the_degrees_of_freedom_and_effects_on_inactive_strings_are_refused() {
    // Effect on an inactive channel: refused by the compiler...
    let mut cal = four_strings();
    cal.effects[1].string = 4;
    assert_eq!(
        compile(&cal, 0, 0),
        Err(BlobCompileError::Layout {
            field: "effects",
            string: Some(4)
        })
    );
    // ... and by the parser (a blob written by something else).
    let blob = compile(&four_strings(), 7, 0).unwrap();
    let (_, body) = split_blob(&blob).unwrap();
    let (mut head, rest) = split_body(body).unwrap();
    head.effects[1] = CompiledEffect::Offset {
        string: 6,
        mm_q16: 1,
    };
    let out = with_head(&blob, &head, rest);
    assert_eq!(
        CompiledCalibration::from_blob(&out),
        Err(BlobError::InactiveString {
            field: "effects",
            string: 6
        })
    );
    // Two strings cannot fix a point in space; in a plane they can.
    let mut cal = calibration();
    cal.effects.clear();
    cal.frame.layout = crate::model::StringLayout::first(2, false);
    assert_eq!(
        compile(&cal, 0, 0),
        Err(BlobCompileError::Layout {
            field: "frame.layout",
            string: None
        })
    );
    cal.frame.layout = crate::model::StringLayout::first(2, true);
    let blob = compile(&cal, 0, 0).unwrap();
    assert!(CompiledCalibration::from_blob(&blob).is_ok());
    // The same blob with the planar flag cleared (a blob from elsewhere).
    let (_, body) = split_blob(&blob).unwrap();
    let (mut head, rest) = split_body(body).unwrap();
    head.frame.layout.planar = false;
    let out = with_head(&blob, &head, rest);
    assert_eq!(
        CompiledCalibration::from_blob(&out),
        Err(BlobError::TooFewStrings { strings: 2, dof: 3 })
    );
}

#[test]
fn nan_frame_does_not_compile() {
    let mut cal = calibration();
    cal.frame.home[1] = f64::NAN;
    assert_eq!(
        compile(&cal, 0, 0),
        Err(BlobCompileError::Frame { field: "home" })
    );
}

#[test]
fn the_kinematics_rule_is_carried_checked_and_run() {
    use crate::kinematics::{FkConfig, KinematicsRule};
    let mut cal = calibration();
    cal.kinematics = KinematicsRule {
        exclusion_threshold_mm: 6.0,
        fault_threshold_mm: 6.0,
    };
    let blob = compile(&cal, 7, 0).unwrap();
    let c = CompiledCalibration::from_blob(&blob).unwrap();
    assert_eq!(
        (c.head.exclusion_threshold_mm, c.head.fault_threshold_mm),
        (6.0, 6.0)
    );
    // The device's configuration takes the blob's thresholds and weights.
    let fk = c.head.fk_config(&FkConfig::default());
    assert_eq!(
        (fk.exclusion_threshold_mm, fk.fault_threshold_mm),
        (6.0, 6.0)
    );
    assert_eq!(fk.residual_weight, c.head.residual_weight);
    // The default rule is the device's fixed one.
    let default_blob = compile(&calibration(), 7, 0).unwrap();
    let c = CompiledCalibration::from_blob(&default_blob).unwrap();
    let fixed = FkConfig::<f32>::default();
    assert_eq!(
        (c.head.exclusion_threshold_mm, c.head.fault_threshold_mm),
        (fixed.exclusion_threshold_mm, fixed.fault_threshold_mm)
    );
    // A rule a device cannot run does not compile.
    for (exclusion, fault) in [
        (3.0, 2.0),
        (0.0, 2.0),
        (1.0, f64::NAN),
        (1.0, f64::INFINITY),
    ] {
        cal.kinematics = KinematicsRule {
            exclusion_threshold_mm: exclusion,
            fault_threshold_mm: fault,
        };
        assert!(
            matches!(
                compile(&cal, 7, 0),
                Err(BlobCompileError::KinematicsRule { .. })
            ),
            "{exclusion} {fault}"
        );
    }
    // One from another tool is refused at load, naming the field.
    let (_, body) = split_blob(&blob).unwrap();
    let (head, rest) = split_body(body).unwrap();
    let refused = |exclusion: f32, fault: f32| {
        let mut h = head.clone();
        h.exclusion_threshold_mm = exclusion;
        h.fault_threshold_mm = fault;
        CompiledCalibration::from_blob(&with_head(&blob, &h, rest)).map(|_| ())
    };
    assert_eq!(
        refused(-1.0, 2.0),
        Err(BlobError::Body {
            field: "exclusion_threshold_mm"
        })
    );
    assert_eq!(
        refused(3.0, 2.0),
        Err(BlobError::Body {
            field: "fault_threshold_mm"
        })
    );
    assert_eq!(
        refused(1.0, f32::NAN),
        Err(BlobError::Body {
            field: "fault_threshold_mm"
        })
    );
}

/// `calibration()` with the training's slips: 6 mm on string 2 from 2 s
/// after home capture `0x5eed_0000_0001`, -1.5 mm on string 5 from 0 s.
fn with_home_slips() -> Calibration {
    let mut cal = calibration();
    cal.home = Some(crate::model::HomeSlips {
        home_id: 0x5eed << 32 | 1,
        slips: alloc::vec![
            EffectTerm {
                string: 2,
                effect: Effect::Slip { at_s: 2.0, mm: 6.0 },
            },
            EffectTerm {
                string: 5,
                effect: Effect::Slip {
                    at_s: 0.0,
                    mm: -1.5,
                },
            },
        ],
    });
    cal
}

#[test]
fn home_slips_round_trip_and_apply_only_under_their_home_capture() {
    let cal = with_home_slips();
    let blob = compile(&cal, 7, 0).unwrap();
    let c = CompiledCalibration::from_blob(&blob).unwrap();
    let home = c.head.home.as_ref().expect("the blob carries the slips");
    assert_eq!(home.home_id, 0x5eed << 32 | 1);
    assert_eq!(
        home.slips.as_slice(),
        &[
            CompiledSlip {
                string: 2,
                at_ms: 2000,
                mm_q16: 6 << 16
            },
            CompiledSlip {
                string: 5,
                at_ms: 0,
                mm_q16: -3 << 15
            },
        ]
    );
    // The effects stay the model for a new home capture.
    assert_eq!(c.header.effects, 2);
    assert_eq!(c.head.effects.len(), 2);
    let plain = compile(&calibration(), 7, 0).unwrap();
    let plain = CompiledCalibration::from_blob(&plain).unwrap();
    assert_eq!(plain.head.home, None);
    let inputs = |time_ms| StringInputs {
        counts: [1000, -2000, 3000, 500, 0, 7000, -300, 40],
        time_ms,
        ..StringInputs::default()
    };
    for time_ms in [0, 1999, 2000, 60_000] {
        let without = plain
            .head
            .string_lengths(&inputs(time_ms), Some(home.home_id));
        let under = c.head.string_lengths(&inputs(time_ms), Some(home.home_id));
        // The same bits as the slips among the effect terms.
        let mut as_effects = cal.clone();
        as_effects
            .effects
            .extend(cal.home.as_ref().unwrap().slips.iter().copied());
        as_effects.home = None;
        let e = CompiledCalibration::from_blob(&compile(&as_effects, 7, 0).unwrap())
            .unwrap()
            .head;
        assert_eq!(under, e.string_lengths(&inputs(time_ms), None), "{time_ms}");
        for i in 0..STRINGS {
            let step = match i {
                2 if time_ms >= 2000 => 6 << 16,
                5 => -3 << 15,
                _ => 0,
            };
            assert_eq!(under[i] - without[i], step, "string {i} at {time_ms} ms");
        }
        // Another home capture (a `Home`, a reboot), or none known: no slip.
        for other in [Some(home.home_id + 1), Some(0x1234 << 32 | 1), None] {
            assert_eq!(c.head.string_lengths(&inputs(time_ms), other), without);
        }
    }
}

#[test]
fn home_slips_that_do_not_fit_are_refused_naming_them() {
    let refused = |edit: &dyn Fn(&mut crate::model::HomeSlips)| {
        let mut cal = with_home_slips();
        edit(cal.home.as_mut().unwrap());
        compile(&cal, 7, 0).unwrap_err()
    };
    let slip = |string, at_s, mm| EffectTerm {
        string,
        effect: Effect::Slip { at_s, mm },
    };
    let problem = |index, problem| BlobCompileError::HomeSlip { index, problem };
    assert_eq!(
        refused(&|h| h.slips[1] = slip(8, 1.0, 1.0)),
        problem(1, HomeSlipProblem::String { string: 8 })
    );
    assert_eq!(
        refused(&|h| h.slips[0].string = crate::model::EVERY_STRING),
        problem(0, HomeSlipProblem::String { string: u8::MAX })
    );
    assert_eq!(
        refused(&|h| h.slips[0].effect = Effect::Offset { mm: 1.0 }),
        problem(0, HomeSlipProblem::NotASlip)
    );
    assert!(matches!(
        refused(&|h| h.slips[0] = slip(2, -1.0, 1.0)),
        BlobCompileError::HomeSlip {
            index: 0,
            problem: HomeSlipProblem::Value(crate::string_law::StringLawCompileError::OutOfRange {
                field: "at_s",
                ..
            })
        }
    ));
    assert!(matches!(
        refused(&|h| h.slips[1] = slip(2, 1.0, f64::NAN)),
        BlobCompileError::HomeSlip {
            index: 1,
            problem: HomeSlipProblem::Value(crate::string_law::StringLawCompileError::NotFinite {
                field: "mm",
                ..
            })
        }
    ));
    assert_eq!(
        refused(&|h| h.slips = alloc::vec![slip(1, 1.0, 1.0); MAX_HOME_SLIPS + 1]),
        BlobCompileError::TooManyHomeSlips {
            found: MAX_HOME_SLIPS + 1,
            max: MAX_HOME_SLIPS
        }
    );
    let e = problem(1, HomeSlipProblem::String { string: 8 }).to_string();
    assert!(
        e.contains("`home.slips[1]`") && e.contains("string 8"),
        "{e}"
    );
    // On a channel the layout marks inactive.
    let mut four = four_strings();
    four.home = Some(crate::model::HomeSlips {
        home_id: 1,
        slips: alloc::vec![slip(6, 1.0, 1.0)],
    });
    assert_eq!(
        compile(&four, 7, 0),
        Err(problem(0, HomeSlipProblem::String { string: 6 }))
    );
    // From another tool: a slip on an inactive or out-of-range string is
    // refused by the parser, naming the field.
    let blob = compile(&with_home_slips(), 7, 0).unwrap();
    let (_, body) = split_blob(&blob).unwrap();
    let (head, rest) = split_body(body).unwrap();
    for string in [8, u8::MAX] {
        let mut h = head.clone();
        h.home.as_mut().unwrap().slips[0].string = string;
        assert_eq!(
            CompiledCalibration::from_blob(&with_head(&blob, &h, rest)),
            Err(BlobError::InactiveString {
                field: "home.slips",
                string
            })
        );
    }
}

#[test]
fn a_calibration_without_home_slips_reads_and_writes_as_before() {
    // Old calibrations (no `home`) still load; one without slips writes no
    // `home` (its JSON, and so its model id, as before).
    let cal = calibration();
    let json = serde_json::to_string(&cal).unwrap();
    assert!(!json.contains("home_id"), "{json}");
    let back: Calibration = serde_json::from_str(&json).unwrap();
    assert_eq!(back, cal);
    let with = with_home_slips();
    let json = serde_json::to_string(&with).unwrap();
    assert!(json.contains("\"home\":{\"home_id\":"), "{json}");
    assert_eq!(serde_json::from_str::<Calibration>(&json).unwrap(), with);
}

/// A model whose tick the device could not run within its budget neither
/// compiles nor loads (`tick_cost`): seven guides every string shares fit
/// (16,270 + 7 x 5,340 instructions), an eighth does not; the same blob
/// from another tool is refused at load, by the estimate.
#[test]
fn a_model_over_the_tick_budget_neither_compiles_nor_loads() {
    use crate::tick_cost::{tick_instructions, TICK_BUDGET};
    let guide = EffectTerm {
        string: crate::model::EVERY_STRING,
        effect: Effect::Guide { radius_mm: 10.0 },
    };
    let mut cal = calibration();
    cal.effects = alloc::vec![guide; 7];
    let blob = compile(&cal, 7, 0).unwrap();
    let c = CompiledCalibration::from_blob(&blob).unwrap();
    let fits = tick_instructions(&c.head, CorrectionKind::None, 0, 0);
    assert_eq!(fits, 16_270 + 7 * 5_340);
    cal.effects.push(guide);
    assert_eq!(
        compile(&cal, 7, 0),
        Err(BlobCompileError::TickOverBudget {
            instructions: fits + 5_340,
            most: TICK_BUDGET
        })
    );
    let (_, body) = split_blob(&blob).unwrap();
    let (head, rest) = split_body(body).unwrap();
    let mut h = head.clone();
    h.effects.push(h.effects[0]).unwrap();
    let over = with_header(&with_head(&blob, &h, rest), |m| m.effects += 1);
    assert_eq!(
        CompiledCalibration::from_blob(&over),
        Err(BlobError::OverBudget {
            field: "tick",
            found: fits + 5_340,
            most: TICK_BUDGET
        })
    );
}
