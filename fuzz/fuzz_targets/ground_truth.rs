//! Ground-truth files `loopd eval` reads: MATLAB v5 matrices and CSV pair lists (the first
//! byte picks the reader).
#![no_main]
use libfuzzer_sys::fuzz_target;
use loopd::eval::gt::GroundTruth;
use loopd::eval::matfile::read_matrix;

fuzz_target!(|data: &[u8]| {
    let Some((&pick, rest)) = data.split_first() else { return };
    if pick % 2 == 0 {
        let _ = read_matrix(rest);
    } else if let Ok(text) = std::str::from_utf8(rest) {
        if let Ok(gt) = GroundTruth::parse_csv(text, std::path::Path::new("fuzz.csv")) {
            let _ = (gt.pairs(), gt.has_loop(0), gt.is_match(1, 0, 2));
        }
    }
});
