//! The fixtures `build.rs` wrote into `OUT_DIR` (compiled model blobs), as the
//! device sees them: bytes in flash, 8-byte aligned.

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
    Fixtures { nn_blob: out_bytes!("nn.blob"), svr_blob: out_bytes!("svr.blob") }
}
