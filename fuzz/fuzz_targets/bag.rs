//! ROS bags as uploaded to a sequence job: MCAP (chunk compression, CRCs, records that lie about
//! their lengths) and ROS 1 (index position, chunk sizes, connection records), then the image
//! messages inside (CDR and ROS 1 serialisation, raw pixels with any step and encoding).
#![no_main]
use libfuzzer_sys::fuzz_target;
use loopd::bags::{frames, topics, Limits, Selection};

fuzz_target!(|data: &[u8]| {
    let limits = Limits { max_frames: 64, max_chunk_bytes: 1 << 20 };
    if let Ok(all) = topics(&[data], &limits) {
        let sel = Selection { every: 1 + data.len() % 3, ..Selection::default() };
        if let Ok(got) = frames(&[data], &sel, &limits) {
            assert!(got.len() <= limits.max_frames);
            assert!(got.iter().all(|f| all.iter().any(|t| t.topic == f.topic && t.image)));
        }
    }
});
