//! Offline sequence uploads: a tar archive (raw body or multipart `archive` part) read into
//! frames; headers may lie about sizes, names may climb out of folders, entries may be links.
#![no_main]
use libfuzzer_sys::fuzz_target;
use loopd::api::jobs::SequenceRequest;
use std::collections::HashMap;

fuzz_target!(|data: &[u8]| {
    let Some((&pick, rest)) = data.split_first() else { return };
    let body = bytes::Bytes::copy_from_slice(rest);
    let r = if pick % 2 == 0 {
        SequenceRequest::from_form(HashMap::new(), Vec::new(), Some(body))
    } else {
        SequenceRequest::from_form(HashMap::new(), vec![("archive".into(), None, body)], None)
    };
    if let Ok(seq) = r {
        assert!(!seq.frames.is_empty());
    }
});
