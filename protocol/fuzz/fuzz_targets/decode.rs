//! Arbitrary bytes into every decoding entry point of `spidar-protocol`: the
//! streaming `FrameDecoder` (both directions, fed in pieces whose sizes come
//! from the input), the one-frame `decode`, and the blob header parser.
//! Besides "never panics", it checks that every accepted frame re-encodes and
//! decodes back to the same bytes, and that the decoder's counters account
//! for every frame it reported.
#![no_main]

use libfuzzer_sys::fuzz_target;
use spidar_protocol::blob::{split_blob, ModelHeader, CRC32};
use spidar_protocol::{decode, encode, DeviceMessage, FrameDecoder, Packet, Request, MAX_FRAME};

fn check_device(p: &Packet<DeviceMessage>) {
    let mut buf = [0u8; MAX_FRAME];
    let frame = encode(p.seq, &p.msg, &mut buf).expect("an accepted frame re-encodes");
    let mut copy = [0u8; MAX_FRAME];
    copy[..frame.len()].copy_from_slice(frame);
    let n = frame.len();
    let again: Packet<DeviceMessage> = decode(&mut copy[..n]).expect("a re-encoded frame decodes");
    let mut buf2 = [0u8; MAX_FRAME];
    assert_eq!(frame, encode(again.seq, &again.msg, &mut buf2).unwrap());
}

fuzz_target!(|data: &[u8]| {
    let piece = usize::from(data.first().copied().unwrap_or(1)).max(1);

    let mut host: FrameDecoder = FrameDecoder::new();
    let mut reported = 0u32;
    for c in data.chunks(piece) {
        host.feed_device_messages(c, |r| {
            reported += 1;
            if let Ok(p) = r {
                check_device(&p);
            }
        });
    }
    let s = host.stats();
    assert_eq!(s.ok.wrapping_add(s.rejected()), reported);

    let mut dev: FrameDecoder = FrameDecoder::new();
    let mut reported = 0u32;
    for c in data.chunks(piece) {
        dev.feed_requests(c, |r| {
            reported += 1;
            if let Ok(p) = r {
                let mut buf = [0u8; MAX_FRAME];
                let frame =
                    encode(p.seq, &p.msg, &mut buf).expect("an accepted request re-encodes");
                let mut copy = [0u8; MAX_FRAME];
                copy[..frame.len()].copy_from_slice(frame);
                let n = frame.len();
                let again: Packet<Request> =
                    decode(&mut copy[..n]).expect("re-encoded request decodes");
                let mut buf2 = [0u8; MAX_FRAME];
                assert_eq!(frame, encode(again.seq, &again.msg, &mut buf2).unwrap());
            }
        });
    }
    let s = dev.stats();
    assert_eq!(s.ok.wrapping_add(s.rejected()), reported);

    // One frame, in place.
    let mut copy = data.to_vec();
    let _ = decode::<DeviceMessage>(&mut copy);
    let mut copy = data.to_vec();
    let _ = decode::<Request>(&mut copy);

    // The input as a frame payload (seq + message) with a valid CRC and COBS,
    // so the fuzzer reaches the message decoder without guessing a CRC-32.
    if data.len() <= MAX_FRAME {
        let mut raw = [0u8; MAX_FRAME + 4];
        raw[..data.len()].copy_from_slice(data);
        let crc = CRC32.checksum(data).to_le_bytes();
        raw[data.len()..data.len() + 4].copy_from_slice(&crc);
        let mut framed = [0u8; 2 * MAX_FRAME];
        let n = cobs::encode(&raw[..data.len() + 4], &mut framed);
        let mut copy = framed;
        if let Ok(p) = decode::<DeviceMessage>(&mut copy[..n]) {
            check_device(&p);
        }
        let mut copy = framed;
        if let Ok(p) = decode::<Request>(&mut copy[..n]) {
            let mut buf = [0u8; MAX_FRAME];
            encode(p.seq, &p.msg, &mut buf).expect("an accepted request re-encodes");
        }
    }

    // Blob header and whole-blob checks.
    let _ = ModelHeader::parse(data);
    let _ = split_blob(data);
});
