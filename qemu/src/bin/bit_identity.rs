//! Bit-identity test: recomputes every vector of `spidar_qemu::cases` on the
//! Cortex-M7 and compares each output word with the one the host computed
//! (`build.rs`, same `spidar-core`). Prints one line per mismatch (case,
//! vector, word, expected vs got) and exits 1 if any; exits 0 otherwise.
#![no_std]
#![no_main]

use spidar_qemu::cases::{self, Out, CASES};
use spidar_qemu::{exit, fixtures::fixtures, hprintln};

mod expected {
    include!(concat!(env!("OUT_DIR"), "/expected.rs"));
}

spidar_qemu::fault_handlers!();

/// Compares the device's words with the host's as they come.
struct Check<'a> {
    case: &'static str,
    vector: u32,
    expected: &'a [u64],
    at: usize,
    mismatches: u32,
}

impl Out for Check<'_> {
    fn word(&mut self, got: u64) {
        match self.expected.get(self.at) {
            Some(&want) if want == got => {}
            Some(&want) => {
                self.mismatches += 1;
                if self.mismatches <= 10 {
                    hprintln!(
                        "MISMATCH {} vector {} word {}: expected {:#018x} got {:#018x}",
                        self.case,
                        self.vector,
                        self.at,
                        want,
                        got
                    );
                }
            }
            None => {
                self.mismatches += 1;
                hprintln!(
                    "MISMATCH {} vector {}: extra word {} (host wrote {} words) got {:#018x}",
                    self.case,
                    self.vector,
                    self.at,
                    self.expected.len(),
                    got
                );
            }
        }
        self.at += 1;
    }
}

#[cortex_m_rt::entry]
fn main() -> ! {
    hprintln!("bit_identity: spidar-core on Cortex-M7 (QEMU mps2-an500) vs host");
    if !spidar_qemu::fpu_enabled() {
        hprintln!("FAIL: FPU not enabled (CPACR)");
        exit(false);
    }
    if expected::CASE_NAMES.len() != CASES.len() {
        hprintln!("FAIL: host table has {} cases, device {}", expected::CASE_NAMES.len(), CASES.len());
        exit(false);
    }
    let fx = fixtures();
    let (mut passed, mut failed) = (0u32, 0u32);
    for (c, case) in CASES.iter().enumerate() {
        let table = expected::EXPECTED[c];
        if expected::CASE_NAMES[c] != case.name || table.len() != case.vectors as usize {
            hprintln!("FAIL: case table {} out of step with the host's", case.name);
            exit(false);
        }
        let mut bad_vectors = 0;
        let mut words = 0;
        for v in 0..case.vectors {
            let mut check = Check { case: case.name, vector: v, expected: table[v as usize], at: 0, mismatches: 0 };
            let mut rng = cases::rng_for(case, v);
            (case.run)(&fx, &mut rng, &mut check);
            if check.at < check.expected.len() {
                hprintln!(
                    "MISMATCH {} vector {}: device wrote {} words, host {}",
                    case.name,
                    v,
                    check.at,
                    check.expected.len()
                );
                check.mismatches += 1;
            }
            words += check.at;
            if check.mismatches > 0 {
                bad_vectors += 1;
            }
        }
        if bad_vectors == 0 {
            passed += 1;
            hprintln!("ok   {} ({} vectors, {} words)", case.name, case.vectors, words);
        } else {
            failed += 1;
            hprintln!("FAIL {} ({} of {} vectors differ)", case.name, bad_vectors, case.vectors);
        }
    }
    hprintln!("bit_identity: {} passed, {} failed", passed, failed);
    exit(failed == 0)
}
