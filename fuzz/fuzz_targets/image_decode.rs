//! Image bytes as a client sends them: decoded under the limits, then preprocessed into the
//! network's input (what the engine's decode workers run).
#![no_main]
use libfuzzer_sys::fuzz_target;
use loopd::model::config::Preprocess;
use loopd::model::preprocess::{prepare, ImageLimits};

fuzz_target!(|data: &[u8]| {
    let limits = ImageLimits { max_bytes: 1 << 20, max_pixels: 4_000_000, min_side: 16, max_decode_bytes: 16 << 20 };
    let _ = prepare(data, &limits, &Preprocess::default());
});
