//! Stored models: power cycles, uploads that do not disturb the active one,
//! and the uploads refused, with the reason.

use super::bench::{bad_state, calibration, nn, raw_at, Bench, Flash, SLOT};
use crate::blob::compile;
use crate::correction::CorrectionModel;
use crate::device::*;
use spidar_protocol::blob::CRC32;
use spidar_protocol::messages::name;
use spidar_protocol::{
    BadState, BlobRejection, DeviceError, DeviceMessage, Request, Response, UploadState,
};

#[test]
fn models_survive_power_cycles_and_uploads_never_disturb_the_active_one() {
    let blob1 = compile(&calibration(CorrectionModel::None), 1, 0).unwrap();
    let blob2 = compile(&calibration(nn(8)), 2, 0).unwrap();
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    assert_eq!(
        b.upload(&blob1, 1, 256),
        Response::Committed { model_id: 1 }
    );
    b.request(&Request::StreamOn { decimation: 1 });
    // Half of model 2, then the loop still runs model 1.
    let crc2 = CRC32.checksum(&blob2);
    b.request(&Request::UploadBegin {
        total_len: blob2.len() as u32,
        crc32: crc2,
        model_id: 2,
    });
    b.request(&Request::UploadChunk {
        offset: 0,
        data: &blob2[..100],
    });
    b.tick_at(raw_at([0.0; 3]));
    let Some(DeviceMessage::State(s)) = b.stream.last().map(|p| p.msg.clone()) else {
        panic!("no state")
    };
    assert_eq!(s.model_id, Some(1));
    // Power cycle mid-upload: model 1, intact, and no upload.
    let flash = b.dev.into_flash();
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
    let Response::Info(Some(info)) = b.request(&Request::GetInfo) else {
        panic!("model 1 lost")
    };
    assert_eq!(info.header.model_id, 1);
    assert_eq!(info.blob_crc32, CRC32.checksum(&blob1));
    assert_eq!(
        b.request(&Request::UploadStatus),
        Response::UploadStatus(UploadState::Idle)
    );
    // The stored model homed the controller at boot: arming works at once.
    b.tick_at(raw_at([0.0; 3]));
    assert_eq!(b.request(&Request::Arm), Response::Ack);
    b.request(&Request::Disarm);
    // Commit model 2, power cycle: model 2 in slot B.
    assert_eq!(
        b.upload(&blob2, 2, 100),
        Response::Committed { model_id: 2 }
    );
    let flash = b.dev.into_flash();
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
    let Response::Info(Some(info)) = b.request(&Request::GetInfo) else {
        panic!("model 2 lost")
    };
    assert_eq!((info.slot, info.header.model_id), (1, 2));
    // A power loss in the middle of the next upload keeps model 2.
    let mut flash = b.dev.into_flash();
    flash.cut_after(10);
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
    let r = b.upload(&blob1, 1, 256);
    assert!(
        matches!(r, Response::Error(DeviceError::Storage { .. })),
        "{r:?}"
    );
    let mut flash = b.dev.into_flash();
    flash.power_cycle();
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
    let Response::Info(Some(info)) = b.request(&Request::GetInfo) else {
        panic!("model 2 lost")
    };
    assert_eq!(info.header.model_id, 2);
    // ClearModel: no model, no geometry.
    assert_eq!(b.request(&Request::ClearModel), Response::Ack);
    assert_eq!(b.request(&Request::GetInfo), Response::Info(None));
    assert_eq!(b.request(&Request::Arm), bad_state(BadState::NoGeometry));
    let flash = b.dev.into_flash();
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(flash, ram.bytes(), spare.bytes());
    assert_eq!(b.request(&Request::GetInfo), Response::Info(None));
}

/// A model whose correction is larger than the device evaluates within its
/// tick is refused on commit by name, and the model before it stays active:
/// the largest it takes commits, one neuron more does not (a hand-made blob,
/// since the compiler refuses to make one).
#[test]
fn a_correction_over_the_tick_budget_is_refused_on_commit() {
    use crate::correction::{MAX_HIDDEN_NEURONS, NN_NEURON_LEN};
    use spidar_protocol::blob::{ModelHeader, HEADER_LEN};
    let most = MAX_HIDDEN_NEURONS as usize;
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    let largest = compile(&calibration(nn(most)), 5, 0).unwrap();
    assert_eq!(
        b.upload(&largest, 5, 256),
        Response::Committed { model_id: 5 }
    );
    // The same network with one more neuron: its bytes appended, the
    // header's count, length and checksums made to agree.
    let mut over = largest.clone();
    over.extend_from_within(over.len() - NN_NEURON_LEN..);
    let mut header = ModelHeader::parse(&over).unwrap();
    header.hidden += 1;
    header.model_id = 6;
    header.body_len = (over.len() - HEADER_LEN) as u32;
    header.body_crc32 = CRC32.checksum(&over[HEADER_LEN..]);
    over[..HEADER_LEN].copy_from_slice(&header.to_bytes());
    assert_eq!(
        b.upload(&over, 6, 256),
        Response::Error(DeviceError::BlobRejected(BlobRejection::OverBudget {
            field: name("nn.hidden"),
            found: most as u32 + 1,
            most: most as u32,
        }))
    );
    match b.request(&Request::GetInfo) {
        Response::Info(Some(info)) => assert_eq!(info.header.model_id, 5),
        other => panic!("{other:?}"),
    }
}

#[test]
fn bad_uploads_are_refused_with_the_reason() {
    let (mut ram, mut spare) = (ModelBuffer::<SLOT>::new(), ModelBuffer::<SLOT>::new());
    let mut b = Bench::new(Flash::new(), ram.bytes(), spare.bytes());
    let blob = compile(&calibration(CorrectionModel::None), 5, 0).unwrap();
    assert_eq!(
        b.request(&Request::UploadChunk {
            offset: 0,
            data: &blob[..10]
        }),
        bad_state(BadState::NoUpload)
    );
    assert_eq!(
        b.request(&Request::UploadCommit { crc32: 0 }),
        bad_state(BadState::NoUpload)
    );
    assert_eq!(
        b.request(&Request::UploadBegin {
            total_len: 1 << 20,
            crc32: 0,
            model_id: 5
        }),
        Response::Error(DeviceError::TooLarge {
            total_len: 1 << 20,
            capacity: (SLOT - 32) as u32
        })
    );
    assert_eq!(
        b.request(&Request::UploadBegin {
            total_len: 0,
            crc32: 0,
            model_id: 5
        }),
        Response::Error(DeviceError::InvalidArgument {
            field: name("total_len")
        })
    );
    // A corrupted body whose whole-blob CRC matches: from_blob refuses it.
    let mut bad = blob.clone();
    let last = bad.len() - 1;
    bad[last] ^= 0x01;
    let r = b.upload(&bad, 5, 256);
    assert!(
        matches!(
            r,
            Response::Error(DeviceError::BlobRejected(BlobRejection::BodyCrc { .. }))
        ),
        "{r:?}"
    );
    // Announced model id differs from the blob's.
    assert_eq!(
        b.upload(&blob, 6, 256),
        Response::Error(DeviceError::InvalidArgument {
            field: name("model_id")
        })
    );
    // Not a blob at all.
    assert_eq!(
        b.upload(&[0x55; 100], 5, 64),
        Response::Error(DeviceError::BlobRejected(BlobRejection::BadMagic))
    );
    assert_eq!(b.request(&Request::GetInfo), Response::Info(None));
    // Incomplete, then abort.
    let crc = CRC32.checksum(&blob);
    b.request(&Request::UploadBegin {
        total_len: blob.len() as u32,
        crc32: crc,
        model_id: 5,
    });
    assert_eq!(
        b.request(&Request::UploadChunk {
            offset: 0,
            data: &blob[..blob.len().min(200) + 56]
        }),
        Response::ChunkAck {
            next_offset: blob.len().min(200) as u32 + 56
        }
    );
    assert_eq!(
        b.request(&Request::UploadChunk {
            offset: blob.len() as u32 - 10,
            data: &[0; 20]
        }),
        Response::Error(DeviceError::PastEnd {
            end: blob.len() as u32 + 10,
            total_len: blob.len() as u32
        })
    );
    assert_eq!(
        b.request(&Request::UploadCommit { crc32: crc }),
        Response::Error(DeviceError::Incomplete {
            next_offset: blob.len().min(200) as u32 + 56,
            total_len: blob.len() as u32
        })
    );
    assert_eq!(b.request(&Request::UploadAbort), Response::Ack);
    assert_eq!(
        b.request(&Request::UploadStatus),
        Response::UploadStatus(UploadState::Idle)
    );
    assert_eq!(b.upload(&blob, 5, 64), Response::Committed { model_id: 5 });
}
