//! The fixtures `build.rs` wrote into `OUT_DIR` (compiled model blobs), as the
//! device sees them: bytes in flash, 8-byte aligned (and one copy of the SVR
//! blob deliberately misaligned).

use crate::cases::Fixtures;

#[repr(C, align(8))]
struct Aligned<B: ?Sized>(B);

macro_rules! out_bytes {
    ($file:literal) => {{
        static BYTES: &Aligned<[u8]> = &Aligned(*include_bytes!(concat!(env!("OUT_DIR"), "/", $file)));
        &BYTES.0
    }};
}

/// The fixtures of this build.
pub fn fixtures() -> Fixtures<'static> {
    // svr_odd.blob is svr.blob after one zero byte: at offset 1 of an 8-aligned
    // buffer, the blob (and its SVR records) sit at an address 1 mod 4.
    Fixtures {
        nn_blob: out_bytes!("nn.blob"),
        svr_blob: out_bytes!("svr.blob"),
        svr_blob_odd: &out_bytes!("svr_odd.blob")[1..],
        four_blob: out_bytes!("four.blob"),
        planar_blob: out_bytes!("planar.blob"),
    }
}

// The tick's cost models (`models::cost_models`), `COST_MODELS`.
include!(concat!(env!("OUT_DIR"), "/cost_models.rs"));
