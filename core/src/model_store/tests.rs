use super::*;

const SLOT: usize = 4096;
type Flash = RamFlash<SLOT>;
type Store = ModelStore<Flash>;

fn rec(seq: u32) -> CommitRecord {
    CommitRecord {
        sequence: seq,
        blob_len: 1000,
        blob_crc32: 0x1234_5678,
        model_id: 7,
    }
}

/// A test blob of `len` bytes; any bytes do (the store does not parse).
fn blob(len: usize, seed: u8) -> std::vec::Vec<u8> {
    (0..len)
        .map(|i| (i as u8).wrapping_mul(31).wrapping_add(seed))
        .collect()
}

fn accept(_: &[u8]) -> Result<(), ()> {
    Ok(())
}

/// Uploads `data` in `chunk`-byte chunks and commits it.
fn upload(store: &mut Store, data: &[u8], chunk: usize, id: u32) -> Result<(), StoreError> {
    let crc = crc32(data);
    let mut next = store.begin(data.len() as u32, crc, id, u32::MAX)?;
    while (next as usize) < data.len() {
        let end = (next as usize + chunk).min(data.len());
        next = store.chunk(next, &data[next as usize..end])?;
    }
    let mut buf = [0u8; SLOT];
    match store.commit(crc, &mut buf, accept) {
        Ok(_) => Ok(()),
        Err(CommitError::Store(e)) => Err(e),
        Err(CommitError::Rejected(())) => Err(StoreError::RecordVerify),
    }
}

fn active_blob(store: &mut Store) -> Option<(u32, std::vec::Vec<u8>)> {
    let a = store.active()?;
    let mut buf = [0u8; SLOT];
    let b = store.read_active(&mut buf).ok()?.to_vec();
    Some((a.record.model_id, b))
}

#[test]
fn crc_is_iso_hdlc() {
    assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
}

#[test]
fn record_round_trip_and_rejections() {
    let r = rec(42);
    let b = r.encode();
    assert_eq!(CommitRecord::decode(&b, 4000), Some(r));
    assert_eq!(CommitRecord::decode(&[0xFF; RECORD_LEN], 4000), None);
    assert_eq!(CommitRecord::decode(&[0x00; RECORD_LEN], 4000), None);
    for i in 0..RECORD_LEN {
        let mut bad = b;
        bad[i] ^= 0x01;
        assert_eq!(CommitRecord::decode(&bad, 4000), None, "flip at {i}");
    }
    // A torn write: the first half programmed, the rest still erased.
    let mut torn = [0xFFu8; RECORD_LEN];
    torn[..16].copy_from_slice(&b[..16]);
    assert_eq!(CommitRecord::decode(&torn, 4000), None);
    assert_eq!(CommitRecord::decode(&b, 999), None); // longer than a slot
    let mut empty = rec(1);
    empty.blob_len = 0;
    assert_eq!(CommitRecord::decode(&empty.encode(), 4000), None);
}

#[test]
fn newest_valid_slot_wins() {
    assert_eq!(select_active(None, None), None);
    assert_eq!(select_active(Some(rec(3)), None), Some((Slot::A, rec(3))));
    assert_eq!(select_active(None, Some(rec(3))), Some((Slot::B, rec(3))));
    assert_eq!(
        select_active(Some(rec(3)), Some(rec(4))),
        Some((Slot::B, rec(4)))
    );
    assert_eq!(
        select_active(Some(rec(5)), Some(rec(4))),
        Some((Slot::A, rec(5)))
    );
    // Wrap-around: u32::MAX then 0.
    assert_eq!(
        select_active(Some(rec(u32::MAX)), Some(rec(0))),
        Some((Slot::B, rec(0)))
    );
    assert_eq!(
        select_active(Some(rec(9)), Some(rec(9))),
        Some((Slot::A, rec(9)))
    );
    assert_eq!(staging_slot(None), Slot::A);
    assert_eq!(staging_slot(Some(Slot::A)), Slot::B);
    assert_eq!(next_sequence(None), 1);
    assert_eq!(next_sequence(Some(&rec(u32::MAX))), 0);
}

#[test]
fn chunk_classification() {
    let mut u = Upload {
        slot: Slot::B,
        total_len: 100,
        crc32: 0xAB,
        model_id: 1,
        received: 0,
    };
    assert_eq!(u.classify(0, 40), Ok(ChunkAction::Append { skip: 0 }));
    u.received = 40;
    assert_eq!(u.classify(0, 40), Ok(ChunkAction::Duplicate));
    assert_eq!(u.classify(20, 40), Ok(ChunkAction::Append { skip: 20 }));
    assert_eq!(
        u.classify(41, 10),
        Err(StoreError::OutOfOrder {
            expected_offset: 40
        })
    );
    assert_eq!(
        u.classify(90, 20),
        Err(StoreError::PastEnd {
            end: 110,
            total_len: 100
        })
    );
    assert_eq!(
        u.classify(u32::MAX, 20),
        Err(StoreError::PastEnd {
            end: u32::MAX,
            total_len: 100
        })
    );
}

#[test]
fn upload_commit_and_reboot() {
    let mut store = Store::open(Flash::new());
    assert_eq!(store.active(), None);
    let a = blob(1000, 1);
    upload(&mut store, &a, 256, 11).unwrap();
    assert_eq!(store.active().map(|s| s.slot), Some(Slot::A));
    assert_eq!(active_blob(&mut store), Some((11, a.clone())));
    let b = blob(777, 2);
    upload(&mut store, &b, 100, 12).unwrap();
    let s = store.active().unwrap();
    assert_eq!((s.slot, s.record.sequence), (Slot::B, 2));
    // Reboot: the newest commit wins and reads back intact.
    let mut store = Store::open(store.into_flash());
    assert_eq!(active_blob(&mut store), Some((12, b)));
    // The next upload goes to A again, never to the active B.
    store.begin(10, 0, 0, u32::MAX).unwrap();
    assert_eq!(store.upload().map(|u| u.slot), Some(Slot::A));
}

#[test]
fn upload_errors_keep_the_active_model() {
    let mut store = Store::open(Flash::new());
    let a = blob(300, 3);
    upload(&mut store, &a, 64, 1).unwrap();
    let b = blob(200, 4);
    let crc = crc32(&b);
    let mut buf = [0u8; SLOT];
    assert_eq!(store.chunk(0, &b), Err(StoreError::NoUpload));
    assert_eq!(store.begin(0, crc, 2, u32::MAX), Err(StoreError::EmptyBlob));
    assert_eq!(
        store.begin(SLOT as u32, crc, 2, u32::MAX),
        Err(StoreError::TooLarge {
            total_len: SLOT as u32,
            capacity: (SLOT - RECORD_LEN) as u32
        })
    );
    assert_eq!(
        store.begin(200, crc, 2, 100),
        Err(StoreError::TooLarge {
            total_len: 200,
            capacity: 100
        })
    );
    assert_eq!(store.begin(200, crc, 2, u32::MAX), Ok(0));
    assert_eq!(store.chunk(0, &b[..50]), Ok(50));
    // Resend of an acked chunk, overlap, gap.
    assert_eq!(store.chunk(0, &b[..50]), Ok(50));
    assert_eq!(store.chunk(40, &b[40..70]), Ok(70));
    assert_eq!(
        store.chunk(80, &b[80..90]),
        Err(StoreError::OutOfOrder {
            expected_offset: 70
        })
    );
    // Same blob again resumes where it stands.
    assert_eq!(store.begin(200, crc, 2, u32::MAX), Ok(70));
    assert_eq!(
        store.commit(crc, &mut buf, accept),
        Err(CommitError::Store(StoreError::Incomplete {
            next_offset: 70,
            total_len: 200
        }))
    );
    assert_eq!(store.chunk(70, &b[70..]), Ok(200));
    assert_eq!(
        store.commit(crc ^ 1, &mut buf, accept),
        Err(CommitError::Store(StoreError::CrcMismatch {
            expected: crc,
            computed: crc ^ 1
        }))
    );
    // The caller's validation refuses it: old model stays, upload gone.
    assert_eq!(
        store.commit(crc, &mut buf, |_| Err::<(), _>("bad")),
        Err(CommitError::Rejected("bad"))
    );
    assert_eq!(store.upload(), None);
    assert_eq!(active_blob(&mut store), Some((1, a.clone())));
    let mut store = Store::open(store.into_flash());
    assert_eq!(active_blob(&mut store), Some((1, a.clone())));
    // Announced CRC that does not match the bytes: refused at read-back.
    let wrong = crc ^ 0x8000_0000;
    store.begin(200, wrong, 2, u32::MAX).unwrap();
    store.chunk(0, &b).unwrap();
    assert_eq!(
        store.commit(wrong, &mut buf, accept),
        Err(CommitError::Store(StoreError::CrcMismatch {
            expected: wrong,
            computed: crc
        }))
    );
    assert_eq!(active_blob(&mut store), Some((1, a)));
}

/// The heart of the store: an upload (erase, every chunk, every word,
/// the commit record) cut by a power loss at each flash operation, then a
/// power cycle, leaves the previous model active and intact; the commit
/// that completes survives a power cycle.
#[test]
fn power_loss_at_every_operation_keeps_the_previous_model() {
    // Chunk sizes: word multiples (cuts at chunk boundaries are between
    // words) and odd ones (a chunk ends mid-word, the word completes in
    // the next chunk).
    for chunk in [64usize, 100, 256] {
        for old_in in [Slot::A, Slot::B] {
            let old = blob(700, 5);
            let new = blob(1111, 6);
            let mut flash = Flash::new();
            {
                let mut store = Store::open(flash);
                if old_in == Slot::B {
                    upload(&mut store, &blob(50, 9), 64, 99).unwrap();
                }
                upload(&mut store, &old, chunk, 1).unwrap();
                assert_eq!(store.active().unwrap().slot, old_in);
                flash = store.into_flash();
            }
            // Count the operations of a whole upload.
            let total = {
                let mut store = Store::open(flash.clone());
                let before = store.flash_mut().operations();
                upload(&mut store, &new, chunk, 2).unwrap();
                store.flash_mut().operations() - before
            };
            // erase + ceil(1111 / 32) words + record.
            assert_eq!(total, 1 + 1111usize.div_ceil(FLASH_WORD) + 1);
            for cut in 0..total {
                let mut f = flash.clone();
                f.cut_after(cut);
                let mut store = Store::open(f);
                let r = upload(&mut store, &new, chunk, 2);
                assert_eq!(
                    r,
                    Err(StoreError::Flash(FlashError::PowerLost)),
                    "chunk {chunk}, cut {cut}"
                );
                let mut f = store.into_flash();
                f.power_cycle();
                let mut store = Store::open(f);
                assert_eq!(
                    active_blob(&mut store),
                    Some((1, old.clone())),
                    "chunk {chunk}, cut {cut}"
                );
                assert_eq!(store.active().unwrap().slot, old_in);
                // And the device can upload again after the cut.
                upload(&mut store, &new, chunk, 2).unwrap();
                let mut f = store.into_flash();
                f.power_cycle();
                let mut store = Store::open(f);
                assert_eq!(active_blob(&mut store), Some((2, new.clone())));
            }
            // No cut: the new model survives a power cycle.
            let mut store = Store::open(flash.clone());
            upload(&mut store, &new, chunk, 2).unwrap();
            let mut f = store.into_flash();
            f.power_cycle();
            let mut store = Store::open(f);
            assert_eq!(active_blob(&mut store), Some((2, new.clone())));
            assert_eq!(store.active().unwrap().slot, old_in.other());
        }
    }
}

#[test]
fn power_loss_during_clear_never_revives_an_older_model() {
    let mut store = Store::open(Flash::new());
    upload(&mut store, &blob(100, 1), 64, 1).unwrap();
    upload(&mut store, &blob(100, 2), 64, 2).unwrap();
    let flash = store.into_flash();
    for cut in 0..2 {
        let mut f = flash.clone();
        f.cut_after(cut);
        let mut store = Store::open(f);
        assert_eq!(store.clear(), Err(StoreError::Flash(FlashError::PowerLost)));
        let mut f = store.into_flash();
        f.power_cycle();
        let store = Store::open(f);
        let id = store.active().map(|a| a.record.model_id);
        // Either the newest model or none, never model 1.
        assert!(id == Some(2) || id.is_none(), "cut {cut}: {id:?}");
    }
    let mut store = Store::open(flash);
    store.clear().unwrap();
    assert_eq!(store.active(), None);
    assert_eq!(Store::open(store.into_flash()).active(), None);
}

#[test]
fn ram_flash_keeps_the_h7_rules() {
    let mut f = Flash::new();
    assert_eq!(
        f.write(Slot::A, 16, &[0; 32]),
        Err(FlashError::Misaligned {
            offset: 16,
            len: 32
        })
    );
    assert_eq!(
        f.write(Slot::A, 0, &[0; 20]),
        Err(FlashError::Misaligned { offset: 0, len: 20 })
    );
    f.write(Slot::A, 32, &[1; 32]).unwrap();
    assert_eq!(
        f.write(Slot::A, 32, &[1; 32]),
        Err(FlashError::NotErased { offset: 32 })
    );
    assert!(matches!(
        f.write(Slot::A, SLOT, &[1; 32]),
        Err(FlashError::OutOfBounds { .. })
    ));
    let mut b = [0u8; 4];
    assert!(f.read(Slot::B, SLOT - 2, &mut b).is_err());
    f.erase(Slot::A).unwrap();
    assert!(f.slot(Slot::A).iter().all(|&x| x == 0xFF));
}
